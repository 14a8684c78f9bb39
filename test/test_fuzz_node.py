"""Hostile input, fuzzed, through DDS: nothing raises out of a running controller node.

Extends test_nodes_behaviour's fixed garbage test with hypothesis-generated bursts: hostile
markers (test_fuzz_inputs' strategy: random types/actions, NaN/inf/huge numbers, non-unit
quaternions, self-intersecting or oversized LINE_STRIPs, odd frames and lifetimes) and
state/target vectors of wrong length, NaN/inf values, 10^5 entries or odd layouts, interleaved with
good states. Proves the node stays alive, keeps answering good states with finite commands, counts
the rejections in /diagnostics, keeps its last good target, and its region store still works.
"""

from __future__ import annotations

import json
import math
import random

import pytest
from fuzzing import fuzz_settings
from hypothesis import Phase, given, settings
from hypothesis import strategies as st
from std_msgs.msg import Float64MultiArray, MultiArrayDimension
from test_fuzz_inputs import hostile_markers
from test_nodes_behaviour import controller_with_probe
from visualization_msgs.msg import MarkerArray

from nmpc_avoid_ros.core.problem.regions import Ellipse, rotated_box
from nmpc_avoid_ros.ros.markers import regions_to_markers

pytestmark = [pytest.mark.dds, pytest.mark.slow]

SEED = 20240606


def _bad_value(rng: random.Random) -> float:
    return rng.choice([math.nan, math.inf, -math.inf, rng.uniform(-1e300, 1e300), 1e308])


def bad_vector(rng: random.Random, size: int) -> Float64MultiArray:
    """A Float64MultiArray a controller with `size`-vectors must reject: wrong length, non-finite or huge."""
    kind = rng.randrange(3)
    if kind == 0:
        data = [rng.uniform(-10, 10) for _ in range(rng.choice([n for n in range(9) if n != size]))]
    elif kind == 1:
        data = [rng.uniform(-10, 10) for _ in range(size)]
        data[rng.randrange(size)] = _bad_value(rng)
    else:
        data = [0.5] * rng.randint(10_000, 100_000)
    msg = Float64MultiArray(data=data)
    msg.layout.dim = [MultiArrayDimension(label="".join(rng.choice("xyz\u00e9 ") for _ in range(rng.randrange(200))),
                                          size=rng.randrange(2**32), stride=rng.randrange(2**32))
                      for _ in range(rng.randrange(4))]
    msg.layout.data_offset = rng.randrange(2**32)
    return msg


def hostile_marker_arrays(count: int) -> list[MarkerArray]:
    """`count` MarkerArrays of 2 to 8 markers each from test_fuzz_inputs' hostile strategy, reproducibly.

    At least 2 per array by construction: derandomized generation still draws on the constants of
    the modules loaded so far (hypothesis' constant pool), so the sizes of a run inside the whole
    suite differ from a run alone (measured: 42 markers in the last 25 arrays vs 167).
    """
    arrays: list[MarkerArray] = []

    @settings(fuzz_settings(count), phases=[Phase.generate])
    @given(st.lists(hostile_markers(), min_size=2, max_size=8))
    def collect(markers) -> None:
        arrays.append(MarkerArray(markers=markers))

    collect()
    return arrays


def test_fuzzed_bursts_never_stop_the_controller(ros_graph) -> None:
    rng = random.Random(SEED)
    marker_arrays = hostile_marker_arrays(40)[-25:]  # past hypothesis' simplest examples
    burst = [(bad_vector(rng, 2), bad_vector(rng, 1), markers) for markers in marker_arrays]
    assert sum(len(a.markers) for a in marker_arrays) >= 50
    p, listen, ctrl = controller_with_probe(ros_graph, 1.0, "-p", "sample_time:=0.2", "-p", "state_timeout:=5.0")
    good = Float64MultiArray(data=[0.5, 0.0])

    def loop_closed() -> bool:  # discovery done both ways: our state reaches it, its command reaches us
        listen.state_pub.publish(good)
        p.spin_for(0.1)
        return bool(listen.commands) and bool(listen.diags)

    # generous: a first start on a fresh machine compiles the solver first (core/nlp/codegen.py)
    assert listen.spin_until(loop_closed, 60), ctrl.output()
    rejected_before = int(listen.diags[-1]["rejected_inputs"])
    n_cmd = len(listen.commands)
    for bad_state, bad_target, markers in burst:
        listen.state_pub.publish(bad_state)
        listen.target.publish(bad_target)
        listen.obstacles.publish(markers)
        p.spin_for(0.05)
        listen.state_pub.publish(good)
        p.spin_for(0.05)
    # the store still works after the garbage: a complete replacement set is applied as sent
    regions = [Ellipse((3.0, 1.5), (0.3, 0.2)), rotated_box((-3.0, -1.5), (0.4, 0.4), 0.3)]
    listen.obstacles.publish(regions_to_markers(regions))

    def regions_in_force() -> bool:  # good states keep coming: a sample that solves installs the regions (a stale
        listen.state_pub.publish(good)  # one does not; one good state and a 10 s wait let it go stale in a full run)
        p.spin_for(0.1)
        return bool(listen.diags) and listen.diags[-1]["regions"] == "2"

    assert listen.spin_until(regions_in_force, 10), (listen.diags[-1:], ctrl.output())
    for _ in range(5):  # good states only: the controller solves normally again
        listen.state_pub.publish(good)
        p.spin_for(0.1)

    assert ctrl.alive(), ctrl.output()
    assert "Traceback" not in ctrl.output(), ctrl.output()
    assert len(listen.commands) - n_cmd >= 10, "good states must keep being answered (one command per 0.2 s)"
    assert all(math.isfinite(u) for cmd in listen.commands[n_cmd:] for u in cmd)
    last = listen.diags[-1]
    # every bad state and target is rejected and counted (some may be coalesced by the depth-limited QoS)
    assert int(last["rejected_inputs"]) - rejected_before >= len(burst), last
    # solved samples (a sample that finds no new state coasts on the plan: solver_status no_new_state)
    solved = [d for d in listen.diags[-6:] if d.get("solver_status") not in (None, "no_new_state")]
    assert solved and all(d["status"] == "ok" for d in solved), listen.diags[-6:]  # not stuck on a fallback
    assert json.loads(solved[-1]["state"]) == [0.5, 0.0]  # bad states never replaced the good one
    assert "rejected" in ctrl.output()
    assert ctrl.stop() == 0
