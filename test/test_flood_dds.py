"""A node that always answers (issue item): a real-time loop keeps its command stream through a
20 s flood of garbage on every input, then settles on the target, then exits cleanly.

The shipped config/van_der_pol.yaml, in real time as the README runs it: the plant integrates
the continuous dynamics at 20 Hz, the controller samples every 0.5 s on its timer. A probe
floods `state`, `target` and `obstacles` at FLOOD_RATE each for FLOOD_SECONDS with NaN/inf,
wrong lengths, finite values up to 1e6 and 1e12, and MarkerArrays of up to 1000 markers
(malformed and well-formed, huge sizes and centres, moving stamps). Finite right-length states
and targets pass validation: they are legitimate input the controller answers, competing with
the plant's real state. Held:

- a command every sample, during and after the flood (the controller's source timestamps of
  `command`, so the probe's own load does not count). A step may take up to max_solve_time (0.4 s)
  warm and 10x that on a cold start (the core's bound), and a flood of valid garbage states and
  regions makes such steps (measured: up to 1.5 s); the node's late cover
  (nodes/controller_threads.py) publishes the last plan's next input when a sample is late, so a
  gap is at most 1.26 sample periods plus the time the cover's thread waits for Python's GIL.
  That wait is not bounded by the node: CasADi calls hold the GIL (the fallback's recovery solve
  up to 0.2 max_solve_time = 80 ms, the target projection up to 50 ms for each new garbage
  target) and so does deserialising a 1000-marker array (57 ms). Held: no gap longer than 1.5
  sample periods (MAX_GAP, the issue's goal); measured 0.59-0.65 s in five runs on a quiet
  machine with the cover as shipped (0.78-0.84 s with earlier versions of it). Before this test:
  11 commands in the 20 s; before the late cover: gaps up to 1.9 s;
- the controller's RSS (VmRSS of its PID; the solver worker's forked child is a separate
  process, not counted in it) grows by less than 50 MiB, and the child's is bounded as well;
- after the flood, DELETEALL on `obstacles` and target 5: x1 settles at 5 (|x1 - 5| < 0.05,
  |x2| < 0.05, held 2 s) within 30 s;
- SIGINT to each node's PID: each exits with code 0 within 1 s.

The measured figures are printed (run with -s to see them).
"""

from __future__ import annotations

import math
import os
import random
import signal
import time
from dataclasses import dataclass
from pathlib import Path

import pytest
from builtin_interfaces.msg import Duration, Time
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import Point
from rclpy.serialization import serialize_message
from rosgraph import CONFIG
from std_msgs.msg import Float64MultiArray, MultiArrayDimension
from visualization_msgs.msg import Marker, MarkerArray

from nmpc_avoid_ros.ros.markers import delete_all_marker, yaw_to_quaternion
from nmpc_avoid_ros.ros.parameters import LATCHED_QOS, STREAM_QOS

pytestmark = [pytest.mark.dds, pytest.mark.slow]

PARAMS = ["--ros-args", "--params-file", str(CONFIG)]
SEED = 20250301
SAMPLE_TIME = 0.5  # config/van_der_pol.yaml
FLOOD_SECONDS = 20.0
FLOOD_RATE = 200.0  # Hz, on each of the three topics
MAX_GAP = 1.5 * SAMPLE_TIME
RSS_GROWTH_MIB = 50.0
SETTLE_WITHIN = 30.0
SETTLED_FOR = 2.0  # s the settled band must hold
EXIT_WITHIN = 1.0
TARGET = 5.0


# -- garbage --------------------------------------------------------------------------------
def huge(rng: random.Random, top: float = 12.0) -> float:
    """A finite value of either sign, magnitude log-uniform from 1e-3 to 10**top."""
    return rng.choice([-1.0, 1.0]) * 10.0 ** rng.uniform(-3.0, top)


def vector_garbage(rng: random.Random, size: int, box: list[float]) -> Float64MultiArray:
    """A Float64MultiArray for a `size`-vector input: rejected (NaN/inf, wrong length) or finite and
    valid (near the box, up to 1e6, up to 1e12), with odd layouts now and then."""
    kind = rng.randrange(7)
    if kind == 0:  # NaN or inf somewhere
        data = [rng.uniform(-5, 5) for _ in range(size)]
        data[rng.randrange(size)] = rng.choice([math.nan, math.inf, -math.inf])
    elif kind == 1:  # all NaN
        data = [math.nan] * size
    elif kind == 2:  # wrong length
        data = [huge(rng, 6) for _ in range(rng.choice([n for n in (0, 1, 2, 3, 5, 17, 1000, 10_000) if n != size]))]
    elif kind == 3:  # valid, near the box (the solver runs on it)
        data = [rng.uniform(-2 * b, 2 * b) for b in box]
    elif kind == 4:  # valid, up to 1e6
        data = [huge(rng, 6) for _ in range(size)]
    elif kind == 5:  # valid, up to 1e12
        data = [huge(rng, 12) for _ in range(size)]
    else:  # beyond the validation box, or subnormal
        data = [rng.choice([1e13, -1e300, 5e-324, 1e308]) for _ in range(size)]
    msg = Float64MultiArray(data=data)
    if rng.random() < 0.2:
        msg.layout.dim = [MultiArrayDimension(label="x" * rng.randrange(100), size=rng.randrange(2**32),
                                              stride=rng.randrange(2**32)) for _ in range(rng.randrange(1, 4))]
        msg.layout.data_offset = rng.randrange(2**32)
    return msg


def garbage_marker(rng: random.Random) -> Marker:
    """One marker: well-formed (CYLINDER/SPHERE/CUBE/LINE_STRIP, sizes and centres up to 1e6 or 1e12,
    static or moving) or malformed (NaN, bad scale, quaternion, type, action, points, lifetime, frame)."""
    m = Marker()
    m.header.frame_id = rng.choice(["state", "state", "", "output", "map", "\u00e9" * 50])
    m.ns = rng.choice(["flood", "walls", "", "n" * 300])
    m.id = rng.randrange(-2**31, 2**31) if rng.random() < 0.1 else rng.randrange(40)
    m.type = rng.choice([1, 2, 3, 4])
    m.action = 0
    top = rng.choice([6.0, 6.0, 12.0])
    m.pose.position = Point(x=huge(rng, top), y=huge(rng, top), z=0.0)
    m.pose.orientation = yaw_to_quaternion(rng.uniform(-4, 4))
    m.scale.x, m.scale.y, m.scale.z = 10.0 ** rng.uniform(-3, top), 10.0 ** rng.uniform(-3, top), 0.01
    if m.type == 4:
        m.points = [Point(x=huge(rng, top), y=huge(rng, top)) for _ in range(rng.randrange(3, 9))]
    if rng.random() < 0.2:  # moving: a stamp (velocity estimated) or an explicit velocity
        m.header.stamp = Time(sec=rng.randrange(0, 2**31), nanosec=rng.randrange(10**9))
        if rng.random() < 0.5:
            m.text = f"velocity={huge(rng, 8)},{huge(rng, 8)}"
    if rng.random() < 0.5:  # malformed, one way or another
        fault = rng.randrange(10)
        if fault == 0:
            m.pose.position.x = math.nan
        elif fault == 1:
            m.scale.x = rng.choice([0.0, -1.0, math.inf, math.nan])
        elif fault == 2:
            m.pose.orientation.w, m.pose.orientation.z = 3.0, 7.0  # not a unit quaternion
        elif fault == 3:
            m.type = rng.choice([0, 5, 6, 7, 8, 9, 10, 11, 12, 99, -1])
        elif fault == 4:
            m.action = rng.choice([1, 4, 99, -7])
        elif fault == 5:
            m.type, m.points = 4, [Point(x=huge(rng), y=huge(rng)) for _ in range(rng.choice([0, 1, 2, 50, 500]))]
        elif fault == 6:
            m.type, m.points = 4, [Point(x=0.0, y=0.0), Point(x=1.0, y=1.0), Point(x=1.0, y=0.0), Point(x=0.0, y=1.0)]
        elif fault == 7:
            m.lifetime = Duration(sec=rng.choice([-5, 2**31 - 1]), nanosec=999_999_999)
        elif fault == 8:
            m.text = rng.choice(["velocity=nan,1", "velocity=1e300,-1e300", "velocity=", "velocity=a,b,c"])
        else:
            m.action = rng.choice([2, 3])  # DELETE / DELETEALL in the middle of the burst
    return m


def marker_garbage(rng: random.Random) -> MarkerArray:
    count = rng.choice([0, 1, 3, 10, 50, 200, 1000, 1000])
    return MarkerArray(markers=[garbage_marker(rng) for _ in range(count)])


def flood_messages(rng: random.Random) -> tuple[list[bytes], list[bytes], list[bytes]]:
    """Pre-serialised garbage (states, targets, marker arrays): publishing bytes keeps the probe light."""
    states = [serialize_message(vector_garbage(rng, 2, [6.0, 2.0])) for _ in range(400)]
    targets = [serialize_message(vector_garbage(rng, 1, [6.0])) for _ in range(400)]
    obstacles = [serialize_message(marker_garbage(rng)) for _ in range(48)]
    return states, targets, obstacles


# -- process figures ------------------------------------------------------------------------
def rss_mib(pid: int) -> float:
    """VmRSS of `pid` in MiB (that process alone: a child's memory is not in it)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    raise AssertionError(f"no VmRSS for {pid}")


def live_children(pid: int) -> list[int]:
    """PIDs of the live (not zombie) child processes of `pid`."""
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text()
            except OSError:
                continue
            fields = stat[stat.rindex(")") + 2:].split()
            if int(fields[1]) == pid and fields[0] != "Z":
                found.append(int(entry.name))
    return found


@dataclass
class Gap:
    """The interval between two commands (s, controller's clock) and the step time of the sample
    that ended it (s; 0 for a sample without a solve)."""

    begin: float
    length: float
    latency: float


def gaps(stamps: list[float], diags: list[dict], begin: float, end: float) -> list[Gap]:
    """The intervals between consecutive commands stamped in [begin, end]; the edges count (a
    silence at the start or the end of the window is a gap too). A command's sample is the first
    diagnostic published after it (the same callback publishes both, the command first)."""
    points = [begin, *[t for t in stamps if begin <= t <= end], end]
    found = []
    for a, b in zip(points, points[1:]):
        diag = next((d for d in diags if b <= d["stamp"] <= b + 0.2), {})
        found.append(Gap(a, b - a, float(diag.get("step_latency_ms", 0.0)) / 1e3))
    return found


def test_a_garbage_flood_on_every_input_never_silences_the_loop(ros_graph):
    _, _, start, probe = ros_graph
    p = probe()
    node = p.node
    commands: list[tuple[float, list[float]]] = []  # (controller's source stamp s, command)
    diags: list[dict] = []

    def on_command(msg, info) -> None:
        commands.append((info["source_timestamp"] * 1e-9, list(msg.data)))

    def on_diag(msg: DiagnosticArray, info) -> None:
        for status in msg.status:
            if status.name.startswith("/controller"):
                diags.append({kv.key: kv.value for kv in status.values} | {"message": status.message,
                                                                           "stamp": info["source_timestamp"] * 1e-9})

    node.create_subscription(Float64MultiArray, "command", on_command, STREAM_QOS)
    node.create_subscription(DiagnosticArray, "/diagnostics", on_diag, STREAM_QOS)
    target_pub = node.create_publisher(Float64MultiArray, "target", LATCHED_QOS)
    obstacles_pub = node.create_publisher(MarkerArray, "obstacles", LATCHED_QOS)
    state_pub = node.create_publisher(Float64MultiArray, "state", STREAM_QOS)
    target_pub.publish(Float64MultiArray(data=[TARGET]))
    states, targets, obstacles = flood_messages(random.Random(SEED))

    ctrl = start("controller", *PARAMS)
    plant = start("plant", *PARAMS)
    # the loop closes (a first start on a fresh machine compiles the solver first), then runs 5 s
    assert p.spin_until(lambda: len(commands) >= 3, 120), (ctrl.output()[-3000:], plant.output()[-2000:])
    p.spin_for(5.0)
    assert state_pub.get_subscription_count() >= 1 and obstacles_pub.get_subscription_count() >= 2
    rss_before = rss_mib(ctrl.pid)
    child_rss_before = {c: rss_mib(c) for c in live_children(ctrl.pid)}
    diag_before = dict(diags[-1])

    # -- the flood ---------------------------------------------------------------------------
    flood_begin = time.time()
    period = 1.0 / FLOOD_RATE
    sent = 0
    rss_samples: list[tuple[float, float, dict[int, float]]] = []
    next_sample = flood_begin
    next_rss = flood_begin + 1.0
    while (now := time.time()) < flood_begin + FLOOD_SECONDS:
        if now >= next_sample:
            state_pub.publish(states[sent % len(states)])
            target_pub.publish(targets[sent % len(targets)])
            obstacles_pub.publish(obstacles[sent % len(obstacles)])
            sent += 1
            next_sample += period
        if now >= next_rss:
            children = live_children(ctrl.pid)
            rss_samples.append((now - flood_begin, rss_mib(ctrl.pid), {c: rss_mib(c) for c in children}))
            next_rss += 1.0
        p.executor.spin_once(timeout_sec=max(0.0, min(next_sample, next_rss) - time.time()))
    flood_end = time.time()
    rate = sent / (flood_end - flood_begin)
    assert rate >= FLOOD_RATE * 0.95, f"the probe published only {rate:.0f} Hz per topic"

    # -- after: a clean scene, the target, the plant's state alone ---------------------------
    obstacles_pub.publish(MarkerArray(markers=[delete_all_marker()]))
    target_pub.publish(Float64MultiArray(data=[TARGET]))
    plant_states: list[tuple[float, list[float]]] = []
    node.create_subscription(Float64MultiArray, "state", lambda m: plant_states.append((time.time(), list(m.data))),
                             STREAM_QOS)  # created now: it hears the plant only

    def settled_since() -> float | None:
        """When the last run of in-band states began, if it has lasted SETTLED_FOR s."""
        since = None
        for t, x in plant_states:
            if t < flood_end + 0.5:  # any flood message still in flight is long delivered by then
                continue
            inside = len(x) == 2 and abs(x[0] - TARGET) < 0.05 and abs(x[1]) < 0.05
            since = (since or t) if inside else None
        return since if since is not None and plant_states[-1][0] - since >= SETTLED_FOR else None

    settled = p.spin_until(lambda: settled_since() is not None, SETTLE_WITHIN + SETTLED_FOR + 1.0)
    settle_time = settled_since() - flood_end if settled else math.inf
    check_end = time.time()
    rss_after = rss_mib(ctrl.pid)
    children_after = live_children(ctrl.pid)
    child_rss_after = {c: rss_mib(c) for c in children_after}
    diag_after = dict(diags[-1])

    # -- stop: SIGINT to each node's PID, each exits 0 within EXIT_WITHIN --------------------
    exits = {}
    for proc in (ctrl, plant):
        begin = time.monotonic()
        os.kill(proc.pid, signal.SIGINT)
        try:
            code = proc.proc.wait(10)
        except Exception:  # noqa: BLE001 - reported below; the fixture kills it
            code = None
        exits[proc.command] = (code, time.monotonic() - begin)

    stamps = [t for t, _ in commands]
    during = gaps(stamps, diags, flood_begin, flood_end)
    after = gaps(stamps, diags, flood_end, check_end)
    child_peak = max((r for _, _, cs in rss_samples for r in cs.values()), default=0.0)
    child_counts = sorted({len(cs) for _, _, cs in rss_samples})
    latencies = sorted(float(d["step_latency_ms"]) for d in diags if "step_latency_ms" in d
                       and flood_begin <= d["stamp"] <= check_end)

    def counter(name: str) -> int:
        return int(diag_after.get(name, 0)) - int(diag_before.get(name, 0))

    def worst(phase: list[Gap], key) -> Gap:
        return max(phase, key=key)

    def line(name: str, phase: list[Gap], origin: float) -> str:
        raw, late = worst(phase, lambda g: g.length), worst(phase, lambda g: g.length - g.latency)
        over = [(round(g.length, 3), round(g.latency, 3), round(g.begin - origin, 1)) for g in phase
                if g.length > MAX_GAP]
        return (f"{name}: max command gap {raw.length:.3f} s (at +{raw.begin - origin:.1f} s; the sample "
                f"ending it took {raw.latency:.3f} s); max gap less its sample's step "
                f"{late.length - late.latency:.3f} s; gaps over {MAX_GAP} s (gap, its step, at +s): {over}")

    print(f"\nflood: {sent} messages per topic in {flood_end - flood_begin:.1f} s ({rate:.0f} Hz); "
          f"{len([t for t in stamps if flood_begin <= t <= flood_end])} commands during it\n"
          f"{line('during', during, flood_begin)}\n{line('after', after, flood_end)}\n"
          f"step latency during and after: median {latencies[len(latencies) // 2]:.1f} ms, max "
          f"{latencies[-1]:.1f} ms, {sum(v > 250 for v in latencies)} of {len(latencies)} over 250 ms\n"
          f"controller RSS: {rss_before:.1f} -> {rss_after:.1f} MiB (each second of the flood: "
          f"{[round(r, 1) for _, r, _ in rss_samples]}); solver child RSS before {child_rss_before}, after "
          f"{child_rss_after}, peak {child_peak:.1f} MiB; live children seen {child_counts}\n"
          f"settled at x1 = {TARGET} {settle_time:.1f} s after the flood\n"
          f"counters over the flood and after: samples {counter('samples')}, fallbacks {counter('fallbacks')}, "
          f"rejected_inputs {counter('rejected_inputs')}, deadline_overruns {counter('deadline_overruns')}, "
          f"stale {counter('stale')}, missed_samples {counter('missed_samples')}, "
          f"late_samples {counter('late_samples')}; the late cover's longest wake-up delay "
          f"{diag_after.get('cover_wake_delay_ms')} ms\n"
          f"exits after SIGINT (code, s): {exits}\ncontroller log: {ctrl.log_path}")

    for phase in (during, after):
        raw = worst(phase, lambda g: g.length)
        assert raw.length <= MAX_GAP, (raw, f"cover wake-up delay {diag_after.get('cover_wake_delay_ms')} ms",
                                       ctrl.output()[-3000:])
    assert rss_after - rss_before < RSS_GROWTH_MIB, (rss_before, rss_after, rss_samples)
    assert all(len(cs) <= 1 for _, _, cs in rss_samples) and len(children_after) <= 1, rss_samples
    assert child_peak < rss_before + RSS_GROWTH_MIB, (child_peak, rss_before, rss_samples)
    assert settled, (plant_states[-5:], diags[-1:], ctrl.output()[-3000:])
    assert settle_time <= SETTLE_WITHIN, settle_time
    out_of_box = [(round(t - flood_begin, 2), cmd) for t, cmd in commands
                  if not all(math.isfinite(u) and abs(u) <= 6.0 for u in cmd)]
    assert not out_of_box, (out_of_box[:10], ctrl.output()[-3000:])
    assert counter("rejected_inputs") > 0
    for command, (code, took) in exits.items():
        assert code == 0 and took <= EXIT_WITHIN, (command, code, took)
    assert "Traceback" not in ctrl.output(), ctrl.output()[-5000:]
