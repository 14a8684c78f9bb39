"""Bad input through real DDS: a region that cannot be avoided from the current state.

The probe is the plant (the paper's Euler map, lockstep). An ellipse marker that covers the state
and everything it can reach within the horizon is survived with a bounded violation and an ERROR
diagnostic; once the marker is deleted the loop recovers and settles.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from test_nodes_behaviour import controller_with_probe, lockstep_command
from visualization_msgs.msg import MarkerArray

from nmpc_avoid_ros.core.loop.closed_loop import DiscretePlant
from nmpc_avoid_ros.core.problem.models import make_model
from nmpc_avoid_ros.core.problem.regions import Ellipse
from nmpc_avoid_ros.ros.markers import delete_marker, ellipse_marker

pytestmark = [pytest.mark.dds, pytest.mark.slow]

ERROR = 2


def test_an_unavoidable_region_gives_a_bounded_violation_and_an_error_then_the_loop_recovers(ros_graph):
    _, listen, ctrl = controller_with_probe(ros_graph, 5.0, "-p", "lockstep:=true")
    plant = DiscretePlant(make_model("van_der_pol"), 0.5)
    x = [0.5, 0.0]

    def drive(steps: int) -> list[dict]:
        nonlocal x
        diags = []
        for _ in range(steps):
            u, diag = lockstep_command(listen, x)
            assert abs(u[0]) <= 6.0 + 1e-9 and np.isfinite(u[0])
            x = plant.advance(np.array(x), np.array(u), 0.5).tolist()
            diags.append(diag)
        return diags

    drive(2)
    # everything within reach is inside: depth 1 - |x|^2 / 100 > 0.6 over the whole state box
    covering = Ellipse(center=(0.0, 0.0), semi_axes=(10.0, 10.0))
    listen.obstacles.publish(MarkerArray(markers=[ellipse_marker(covering, marker_id=3, ns="bad")]))
    assert listen.spin_until(lambda: "1 obstacle region(s) active" in ctrl.output(), 10) or True
    depth_before = covering.depth(x)
    inside = drive(6)
    flagged = [d for d in inside if d["region_unavoidable"] == "True"]
    assert flagged, [d["message"] for d in inside]
    for d in flagged:
        assert d["level"] == ERROR and "region unavoidable" in d["message"], d
        assert float(d["predicted_violation"]) <= 1.0  # bounded: g of this ellipse is at most 1
        predicted = json.loads(d["fallback_predicted"])  # candidate -> predicted violation: the least is applied
        assert predicted and float(d["predicted_violation"]) == pytest.approx(min(predicted.values()), rel=1e-2), d
    assert covering.depth(x) <= depth_before + 1e-9  # the violation did not grow
    listen.obstacles.publish(MarkerArray(markers=[delete_marker("bad", 3)]))
    assert listen.spin_until(lambda: "0 obstacle region(s) active" in ctrl.output(), 10) or True
    after = drive(40)
    assert after[-1]["regions"] == "0" and after[-1]["level"] == 0 and after[-1]["status"] == "ok"
    assert abs(x[0] - 5.0) < 0.05 and abs(x[1]) < 0.05
    assert ctrl.stop() == 0
