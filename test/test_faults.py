"""Faults in the graph, through real DDS and real processes: kill -9 and restart of each node,
a controller restarted mid-run (transient local target and obstacles), state loss and delay
between plant and controller, and a starved solver.

Real time only where the fault needs the node clock (stale state, loss, delay, starved samples);
the restarted-controller test runs in lockstep with the probe as the plant.
"""

from __future__ import annotations

import heapq
import json
import math
import random
import signal
import time
from collections import Counter

import numpy as np
import pytest
from std_msgs.msg import Float64MultiArray
from test_nodes_behaviour import PARAMS, Listener, lockstep_command
from test_recorder import tolerant_mcap_messages
from visualization_msgs.msg import MarkerArray

from nmpc_avoid_ros.bag.mcap_io import load_bag
from nmpc_avoid_ros.core.config.settings import ControllerSettings
from nmpc_avoid_ros.core.loop.closed_loop import DiscretePlant, run_closed_loop
from nmpc_avoid_ros.core.problem.models import make_model
from nmpc_avoid_ros.core.problem.regions import Ellipse
from nmpc_avoid_ros.core.sample.controller import NmpcController
from nmpc_avoid_ros.core.sample.status import StepStatus
from nmpc_avoid_ros.ros.markers import ellipse_marker
from nmpc_avoid_ros.ros.parameters import STREAM_QOS

pytestmark = [pytest.mark.dds, pytest.mark.slow]

ERROR, OK_LEVEL = 2, 0
#: the bound on |x1 x2| asserted with the continuous (not the Euler) plant: the constraint is 2,
#: the controller predicts with Euler, so the real plant may exceed it slightly
PRODUCT_BOUND = 2.05


def timed(probe, topic: str) -> list[tuple[float, list[float]]]:
    """(monotonic arrival time, data) of every Float64MultiArray on `topic`, collected by the probe."""
    got: list[tuple[float, list[float]]] = []
    probe.node.create_subscription(Float64MultiArray, topic, lambda m: got.append((time.monotonic(), list(m.data))),
                                   STREAM_QOS)
    return got


def wait(listen: Listener, what: str, done, timeout: float, *procs) -> float:
    """Spin until done(); return the monotonic time it became true, or fail with the nodes' output."""
    if not listen.spin_until(done, timeout):
        for proc in procs:
            print(f"--- {proc.command} (alive: {proc.alive()}):\n{proc.output()[-4000:]}")
        print(f"--- last diagnostics: {listen.diags[-3:]}")
        pytest.fail(f"timed out after {timeout} s waiting for: {what}")
    return time.monotonic()


def recorded_state_set(path) -> set[tuple[float, ...]]:
    """The /state messages in the completed chunks of a bag being written (empty before its first chunk)."""
    if not path.exists():
        return set()
    return {tuple(m.data) for _, m in load_bag(path, ["/state"]).topics.get("/state", [])}


def states_to_judge(states: list[tuple[float, list[float]]], first_plant_states: int,
                    recorded: set[tuple[float, ...]], until: float) -> set[tuple[float, ...]]:
    """The probe's states (arrival time, x) that a recorder which kept every state must have on disk by `until`.

    Per plant (the first `first_plant_states` are the first plant's), from a second after the recorder's first
    state of that plant on (dated by a state the probe saw once) to a second before `until` (monotonic, s).
    """
    seen = Counter(tuple(x) for _, x in states)
    expected: set[tuple[float, ...]] = set()
    for plant_states in (states[:first_plant_states], states[first_plant_states:]):
        since = next((t for t, x in plant_states if seen[tuple(x)] == 1 and tuple(x) in recorded), None)
        if since is not None:
            expected |= {tuple(x) for t, x in plant_states if since + 1.0 <= t < until - 1.0}
    return expected


# ------------------------------------------------------------------------------------------------
# kill -9 and restart, each node in turn


@pytest.mark.serial  # judges the second plant over a window of real time: alone on the machine
def test_kill_9_and_restart_plant_controller_and_recorder_in_turn(ros_graph, tmp_path):
    _, _, start, probe = ros_graph
    p = probe()
    listen = Listener(p)
    states = timed(p, "state")
    listen.publish_target(5.0)  # latched: only this once, also for the restarted controller
    bag1, bag2 = tmp_path / "bag_before.mcap", tmp_path / "bag_after.mcap"
    rec = start("recorder", "--ros-args", "-p", f"output:={bag1}", "-p", "flush_period:=0.5")
    ctrl_args = (*PARAMS, "-p", "state_timeout:=1.0", "-p", "stale_behavior:=hold_steady")
    ctrl = start("controller", *ctrl_args)
    plant = start("plant", *PARAMS)
    procs = [rec, ctrl, plant]
    ok = lambda since=0: [d for d in listen.diags[since:] if d["level"] == OK_LEVEL and "status" in d]  # noqa: E731
    # the probe matches each writer on its own: on a loaded machine the controller can be solving
    # before the probe has seen a state, and the plant's last state is needed for its restart
    wait(listen, "the loop closes and the probe sees states", lambda: len(ok()) >= 3 and len(states) >= 3, 60,
         *procs)

    # -- 1. the plant dies: stale state, safe behaviour with an ERROR every sample, others alive
    assert plant.stop(signal.SIGKILL) == -signal.SIGKILL
    t_kill = time.monotonic()
    n_diag, n_cmd = len(listen.diags), len(listen.commands)
    stale = lambda: [d for d in listen.diags[n_diag:] if d["level"] == ERROR]  # noqa: E731
    t_error = wait(listen, "stale ERRORs", lambda: len(stale()) >= 3, 20, *procs)
    counted = [int(d["stale"]) for d in stale()]  # each an ERROR sample counted as stale (the fields, not the text)
    assert counted == sorted(counted) and counted[-1] > counted[0], stale()
    assert all("solve_time_ms" not in d for d in stale())  # no solve on a stale state
    assert ctrl.alive() and rec.alive()
    # hold_steady: u_a of the last plan, and for van der Pol u_a = y_a (x_a = [y_a, 0])
    first_error = listen.diags.index(stale()[0])
    # the last sample before the ERRORs, whatever its level (a WARN one, e.g. an alarm's, is the last plan too)
    last_solved = [d for d in listen.diags[:first_error] if "status" in d][-1]
    u_a = json.loads(last_solved["y_a"])[0]
    stale_commands = [json.loads(d["command"])[0] for d in stale()]
    assert stale_commands == pytest.approx([u_a] * len(stale_commands), abs=1e-9)
    x_last = states[-1][1]
    first_plant_states = len(states)  # the probe's states from here on are the second plant's
    plant = start("plant", *PARAMS, "-p", f"initial_state:=[{x_last[0]!r}, {x_last[1]!r}]")
    procs[2] = plant
    t_restart = time.monotonic()
    n_resume = len(listen.diags)
    t_resumed = wait(listen, "control resumes", lambda: len(ok(n_resume)) >= 1, 60, *procs)
    during = listen.diags[n_diag:n_resume]
    assert len(listen.commands) - n_cmd >= len(during)  # a command every sample, stale or not
    resumed = ok(n_resume)[0]
    assert resumed["stale_episodes"] == "1" and float(resumed["last_stale_s"]) > 0.5
    assert json.loads(resumed["state"]) == pytest.approx(x_last, abs=0.3)  # the new plant goes on from there
    plant_kill = dict(three_stale_errors_after_s=t_error - t_kill, restart_to_control_s=t_resumed - t_restart,
                      stale_s=float(resumed["last_stale_s"]), stale_samples=int(resumed["stale"]))

    # -- 2. the controller dies: the plant keeps publishing (ZOH), the recorder keeps recording
    wait(listen, "two more solves", lambda: len(ok(n_resume)) >= 3, 30, *procs)
    assert ctrl.stop(signal.SIGKILL) == -signal.SIGKILL
    n_states = len(states)
    wait(listen, "the plant goes on alone", lambda: len(states) >= n_states + 20, 30, *procs)
    assert plant.alive() and rec.alive()
    n_diag = len(listen.diags)
    ctrl = start("controller", *ctrl_args)
    procs[1] = ctrl
    t_restart = time.monotonic()
    t_resumed = wait(listen, "the new controller solves", lambda: len(ok(n_diag)) >= 1, 60, *procs)
    first = ok(n_diag)[0]
    assert first["stale"] == "0" and json.loads(first["target_applied"]) == [[5.0]]  # the latched target, again
    controller_restart_s = t_resumed - t_restart

    # -- 3. the recorder dies: the loop goes on; the bag keeps every completed chunk
    wait(listen, "two more solves", lambda: len(ok(n_diag)) >= 3, 30, *procs)
    # The kill is judged on the states that reached the recorder more than a second before it; on a loaded CI machine
    # the recorder matched the second plant so late that none were left to judge (0). So the kill waits until the
    # bag on disk has the second plant's first states and 20 more have come since.
    judged_now = lambda: states_to_judge(states, first_plant_states, recorded_state_set(bag1), time.monotonic())  # noqa: E731
    wait(listen, "the bag has the second plant, 20 states to judge", lambda: len(judged_now()) >= 20, 30, *procs)
    n_cmd = len(listen.commands)
    assert rec.stop(signal.SIGKILL) == -signal.SIGKILL
    t_rec_kill = time.monotonic()
    wait(listen, "commands after the recorder died", lambda: len(listen.commands) >= n_cmd + 3, 30, *procs)
    assert ctrl.alive() and plant.alive()
    bag = load_bag(bag1)
    independent, chunks = tolerant_mcap_messages(bag1)
    assert not bag.finished and bag.chunks == chunks >= 5 and bag.message_count == independent
    # flush_period 0.5 s: whatever reached the recorder more than ~1 s before the kill is on disk
    # (the probe and the recorder receive the same state messages; the plant's states are distinct while it moves)
    recorded = [tuple(m.data) for _, m in bag.topics["/state"]]
    recorded_set = set(recorded)
    # Each plant is a new DDS writer that the probe and the recorder match independently, and a
    # volatile writer's samples before a match are not delivered (seen: the recorder matched the
    # restarted plant about 1 s after the probe). So, per plant, compare from the recorder's first
    # state of that plant on, dated by a state the probe saw once (a holding plant repeats its x0:
    # (-5, 0) for the first, the first one's last state for the second). The recorder's first second
    # of each is skipped too: start-up of a reliable match can drop early states (seen once: 2 of
    # 125). The property under test is the kill.
    expected = states_to_judge(states, first_plant_states, recorded_set, t_rec_kill)
    assert len(expected) >= 20, f"the recorder got too few states of the second plant to judge: {len(expected)}"
    missing = expected - recorded_set
    if missing:
        where = [(i, round(t - t_rec_kill, 2)) for i, (t, x) in enumerate(states) if tuple(x) in missing]
        pytest.fail(f"{len(missing)} of {len(expected)} states missing from the bag (probe index, s before the "
                    f"kill; second plant from index {first_plant_states}): {where[:8]} ... {where[-3:]}\n"
                    f"recorder output:\n{rec.output()[-3000:]}")
    recorded_states, settled_before = len(recorded), len(expected)
    lag = (time.time_ns() - bag.topics["/state"][-1][0]) * 1e-9 - (time.monotonic() - t_rec_kill)
    assert bag.counts()["/target"] == 1 and bag.counts()["/command"] >= 10
    assert any("stale" in m.status[0].message for _, m in bag.topics["/diagnostics"])  # the plant's outage
    rec = start("recorder", "--ros-args", "-p", f"output:={bag2}", "-p", "flush_period:=0.5")
    procs[0] = rec
    wait(listen, "the new recorder subscribes", lambda: "recording /state" in rec.output(), 30, *procs)

    # -- the loop still reaches the target, all three (restarted) nodes stop cleanly
    settled = lambda: abs(states[-1][1][0] - 5.0) < 0.05 and abs(states[-1][1][1]) < 0.05  # noqa: E731
    wait(listen, "the target is reached", settled, 90, *procs)
    # and the new recorder has written some of the loop: subscribed is not yet matched, and with the target reached
    # before it, a recorder stopped at once had written no state (a CI run: 0 messages)
    writes = lambda: bag2.exists() and tolerant_mcap_messages(bag2)[0] >= 20  # noqa: E731
    wait(listen, "the new recorder writes the loop", writes, 30, *procs)
    assert rec.stop(signal.SIGINT) == 0, rec.output()
    after = load_bag(bag2)
    assert after.finished and after.counts()["/state"] > 0 and after.counts()["/command"] > 0
    assert after.counts()["/target"] == 1  # the latched target again, for the new bag
    assert ctrl.stop() == 0 and plant.stop() == 0
    print(f"plant kill: {plant_kill}; controller restart to first solve {controller_restart_s:.2f} s; "
          f"recorder killed: {bag.chunks} chunks, {bag.message_count} messages kept "
          f"({recorded_states} states incl. all {settled_before} distinct ones the probe got > 1 s before the kill; "
          f"last recorded state {lag:.2f} s before the kill)")


# ------------------------------------------------------------------------------------------------
# a restarted controller picks up the latched target and obstacles


RESTART_AT = 6  # samples of the paper run before the controller is killed


def test_restarted_controller_picks_up_target_and_obstacles_published_only_before(ros_graph):
    """Lockstep, the probe is the plant (the paper's Euler map): deterministic, compared offline."""
    _, _, start, probe = ros_graph
    p = probe()
    listen = Listener(p)
    settings = ControllerSettings()
    paper = run_closed_loop(NmpcController(settings), [-5.0, 0.0], [5.0], 2 * RESTART_AT, "euler").x
    # an ellipse on the path the loop takes 6 samples after the restart (beyond the horizon N = 5,
    # so the first controller's plan never reaches it and the dynamics leave room to go around)
    blocker = Ellipse(center=tuple(paper[2 * RESTART_AT]), semi_axes=(0.4, 0.2))
    listen.publish_target(5.0)
    listen.obstacles.publish(MarkerArray(markers=[ellipse_marker(blocker, marker_id=1, ns="fault")]))
    ctrl = start("controller", *PARAMS, "-p", "lockstep:=true")
    wait(listen, "controller 1 has both", lambda: "region(s) stored" in ctrl.output()
         and "target y_t" in ctrl.output(), 30, ctrl)
    plant = DiscretePlant(make_model("van_der_pol"), 0.5)
    x = [-5.0, 0.0]
    for _ in range(RESTART_AT):
        u, diag = lockstep_command(listen, x)
        assert diag["regions"] == "1" and diag["status"] == "ok"
        x = plant.advance(np.array(x), np.array(u), 0.5).tolist()
    np.testing.assert_allclose(x, paper[RESTART_AT], atol=1e-6)  # the obstacle is beyond every plan so far

    assert ctrl.stop(signal.SIGKILL) == -signal.SIGKILL
    ctrl = start("controller", *PARAMS, "-p", "lockstep:=true")  # no target parameter: topics only
    wait(listen, "controller 2 has both", lambda: "region(s) stored" in ctrl.output()
         and "target y_t = [5.0]" in ctrl.output(), 30, ctrl)
    n_pred = len(listen.predictions)
    states = [x]
    for _ in range(34):
        u, diag = lockstep_command(listen, x)
        assert diag["regions"] == "1" and diag["samples"] == str(len(states)), diag
        x = plant.advance(np.array(x), np.array(u), 0.5).tolist()
        states.append(x)
    # the restarted controller starts cold, exactly like a fresh offline controller that knows the region
    with_region = NmpcController(settings)
    with_region.set_regions([blocker])
    offline = run_closed_loop(with_region, states[0], [5.0], len(states) - 1, "euler").x
    np.testing.assert_allclose(states, offline, atol=1e-6)
    free = run_closed_loop(NmpcController(settings), states[0], [5.0], len(states) - 1, "euler").x
    depth = max(blocker.depth(s) for s in states)
    predicted_depth = max(blocker.depth(q) for path in listen.predictions[n_pred:] for q in path)
    assert max(blocker.depth(s) for s in free) > 0.9  # without the region the loop runs through it
    assert depth <= 0.01 and predicted_depth <= 0.01, (depth, predicted_depth)
    assert abs(x[0] - 5.0) < 0.05 and abs(x[1]) < 0.05
    assert ctrl.stop() == 0
    print(f"restarted controller: region depth {depth:.2e} (closed loop), {predicted_depth:.2e} (predictions); "
          f"without the region {max(blocker.depth(s) for s in free):.2f}")


# ------------------------------------------------------------------------------------------------
# message loss and delay between plant and controller


class LossyRelay:
    """plant `raw_state` -> controller `state`: drops a share, delays the rest (uniform), and once
    drops everything for `blackout` seconds when `blackout_when(x)` first holds. Runs in the probe."""

    def __init__(self, listen: Listener, drop: float, max_delay: float, blackout: float, blackout_when,
                 seed: int = 6) -> None:
        self.listen, self.drop, self.max_delay = listen, drop, max_delay
        self.blackout, self.blackout_when = blackout, blackout_when
        self.rng = random.Random(seed)
        self.queue: list[tuple[float, int, list[float]]] = []
        self.received = self.dropped = self.relayed = 0
        self.bursts = 0  # release() calls that published (a held-back state goes out with the ones behind it)
        self.blackout_until: float | None = None
        self.release_at = 0.0
        self.closed = False  # stop relaying (to count what arrived)
        self.raw: list[list[float]] = []
        node = listen.probe.node
        node.create_subscription(Float64MultiArray, "raw_state", self.on_raw, STREAM_QOS)
        node.create_timer(0.005, self.release)

    def on_raw(self, msg: Float64MultiArray) -> None:
        # forward only once the controller's subscription is matched (besides the probe's own), so that
        # every relayed state must reach it
        if self.closed or self.listen.state_pub.get_subscription_count() < 2:
            return
        now = time.monotonic()
        x = list(msg.data)
        self.raw.append(x)
        self.received += 1
        if self.blackout_until is None and self.blackout_when(x):
            self.blackout_until = now + self.blackout
        if (self.blackout_until is not None and now < self.blackout_until) or self.rng.random() < self.drop:
            self.dropped += 1
            return
        # reliable DDS delivers in order: a delayed message holds back the ones behind it (no overtaking)
        self.release_at = max(self.release_at, now + self.rng.uniform(0.0, self.max_delay))
        heapq.heappush(self.queue, (self.release_at, self.received, x))

    def release(self) -> None:
        now = time.monotonic()
        self.bursts += bool(self.queue and self.queue[0][0] <= now)
        while self.queue and self.queue[0][0] <= now:
            _, _, x = heapq.heappop(self.queue)
            self.listen.state_pub.publish(Float64MultiArray(data=x))
            self.relayed += 1


@pytest.mark.serial  # state gaps and delays in real time: alone on the machine
def test_state_loss_and_delay_keep_the_loop_stable_and_inside_the_constraint(ros_graph):
    _, _, start, probe = ros_graph
    p = probe()
    listen = Listener(p)
    # 30 % of the 20 Hz states dropped, the rest delayed 0..100 ms (in order, as reliable DDS
    # delivers), and a 1 s blackout (two samples, below state_timeout 1.5 s) on the final approach.
    # (A blackout while the loop rides the boundary |x1 x2| = 2 gave max |x1 x2| = 2.08: a sample
    # without a new state solves the old state again and repeats an outdated u(0).)
    relay = LossyRelay(listen, drop=0.3, max_delay=0.1, blackout=1.0, blackout_when=lambda x: x[0] > 4.0)
    listen.publish_target(5.0)
    ctrl = start("controller", *PARAMS)
    plant = start("plant", *PARAMS, "-r", "state:=raw_state")
    settled = lambda: len(relay.raw) > 10 and abs(relay.raw[-1][0] - 5.0) < 0.05 \
        and abs(relay.raw[-1][1]) < 0.05  # noqa: E731
    wait(listen, "the target is reached", settled, 120, ctrl, plant)
    xs = np.array(relay.raw)
    product = float(np.max(np.abs(xs[:, 0] * xs[:, 1])))
    x2_max = float(np.max(np.abs(xs[:, 1])))
    assert relay.blackout_until is not None
    assert product <= PRODUCT_BOUND, product
    # the box |x2| <= 2 is a constraint on the Euler prediction; the continuous plant with delayed
    # states overshoots it (measured up to 2.19 here, 1.94 without faults): bounded, not kept exactly
    assert np.all(np.abs(xs[:, 0]) <= 6.0) and x2_max <= 2.3, x2_max
    # what the controller saw: the states the relay let through, the blackout as a gap. It reads the
    # latest state only (LATEST_QOS): of the states one release sends together (a delayed one holds
    # back those behind it) it may take only the last, and of two releases 5 ms apart only the later:
    # never more than relayed, nearly one per release (236 of 237 releases, 263 states, measured)
    relay.closed = True
    counts: list[str] = []

    def accounted() -> bool:  # the count has stopped changing (the last relayed state is taken)
        if listen.diags:
            counts.append(listen.diags[-1]["states_received"])
        return len(counts) >= 40 and len(set(counts[-40:])) == 1

    wait(listen, "the controller's state count settles", accounted, 10, ctrl)
    last = listen.diags[-1]
    assert relay.relayed < relay.received
    assert 0.9 * relay.bursts <= int(last["states_received"]) <= relay.relayed, (last["states_received"], relay.bursts,
                                                                           relay.relayed)
    assert int(last["missed_samples"]) >= 1 and float(last["max_state_gap_ms"]) >= 1000.0, last
    assert last["stale"] == "0" and last["stale_episodes"] == "0"
    solved = [d for d in listen.diags if "status" in d]
    fallbacks = sum(StepStatus(d["status"]).is_fallback for d in solved)
    assert ctrl.stop() == 0 and plant.stop() == 0
    print(f"loss/delay: plant sent {relay.received}, relay dropped {relay.dropped} "
          f"({relay.dropped / relay.received:.0%}), controller received {last['states_received']}; "
          f"max |x1 x2| = {product:.4f}, max |x2| = {x2_max:.3f}; missed samples {last['missed_samples']}, max gap "
          f"{last['max_state_gap_ms']} ms, {fallbacks} fallbacks in {len(solved)} samples; "
          f"settled after {len(solved)} samples")


# ------------------------------------------------------------------------------------------------
# a starved solver


@pytest.mark.serial  # one command per sample in real time: alone on the machine
def test_a_starved_solver_still_commands_every_sample_through_the_fallback(ros_graph):
    _, _, start, probe = ros_graph
    p = probe()
    listen = Listener(p)
    listen.publish_target(5.0)
    # starved by both budgets: the shipped FATROP path (its cold start on a tier included) is bounded by
    # iterations, the IPOPT reference that takes over when it fails by the clock
    ctrl = start("controller", *PARAMS, "-p", "max_solve_time:=0.0001", "-p", "max_iterations:=1")
    p.node.create_timer(0.05, lambda: listen.state_pub.publish(Float64MultiArray(data=[-5.0, 0.0])))
    solved = lambda: [d for d in listen.diags if "status" in d]  # noqa: E731
    wait(listen, "a first sample", lambda: len(solved()) >= 1, 60, ctrl)
    n_diag, t0 = len(solved()), time.monotonic()
    wait(listen, "ten more samples", lambda: len(solved()) >= n_diag + 10, 30, ctrl)
    elapsed = time.monotonic() - t0
    assert ctrl.stop() == 0  # SIGINT between callbacks: every sample published both messages
    p.spin_for(1.0)
    window = solved()[n_diag:n_diag + 10]
    # one command per sample (the first may precede the match of the probe's command subscription), and the
    # deactivate_command the stop publishes (test_stop_dds; here zero like the starved samples' own)
    assert len(solved()) - 1 <= len(listen.commands) <= len(solved()) + 1, (len(listen.commands), len(solved()))
    assert elapsed <= 10 * 0.5 + 2.0  # ... at the sample rate (0.5 s), not slower
    assert all(StepStatus(d["status"]).is_fallback and d["level"] == 1 for d in window), window
    assert all(d["budget_exhausted"] == "True" and int(d["iterations"]) <= 1 for d in window), window
    assert all(float(d["solve_time_ms"]) < 500.0 for d in window)  # the budget bounds the solve
    for key in ("samples", "fallbacks"):  # ten consecutive samples, every one a fallback
        assert int(window[-1][key]) - int(window[0][key]) == 9, (key, window)
    print(f"starved (max_solve_time 1e-4 s): {len(listen.commands)} commands in {len(solved())} samples; "
          f"10 samples in "
          f"{elapsed:.2f} s; statuses {sorted({d['status'] for d in window})}, solver "
          f"{sorted({d['solver_status'] for d in window})}, iterations {sorted({d['iterations'] for d in window})}, "
          f"solve_time_ms max {max(float(d['solve_time_ms']) for d in window):.2f}")



@pytest.mark.slow
def test_a_sample_without_a_new_state_sends_the_plans_next_input_when_the_command_in_force_has_acted(ros_graph):
    """A tick that finds no new state coasts on the last plan (core `coast`): that plan assumed each input in force
    one sample_time from when it left, so the next input leaves then, not at the tick (with command_latency 0.2 s of
    the 0.5 s sample it left 0.2 s early; the tutorial's crane swung past its bound so)."""
    _, _, start, probe = ros_graph
    p = probe()
    listen = Listener(p)
    arrivals = timed(p, "command")
    listen.publish_target(5.0)
    ctrl = start("controller", *PARAMS, "-p", "command_latency:=0.2")
    blackout = {"until": -math.inf}
    p.node.create_timer(0.05, lambda: time.monotonic() < blackout["until"]
                        or listen.state_pub.publish(Float64MultiArray(data=[-5.0, 0.0])))
    solved = lambda: [d for d in listen.diags if "status" in d]  # noqa: E731
    wait(listen, "four samples", lambda: len(solved()) >= 4, 60, ctrl)
    judged_from = len(arrivals) - 1  # the commands of regular samples on: the cold start's lateness is behind
    blackout["until"] = time.monotonic() + 0.8  # at least one tick without a new state (state_timeout 1.5 s)
    coasted = lambda: any(d["message"].startswith("no new state") for d in listen.diags)  # noqa: E731
    wait(listen, "a sample without a new state", coasted, 10, ctrl)
    n = len(solved())
    wait(listen, "two samples after it", lambda: len(solved()) >= n + 2, 10, ctrl)
    assert ctrl.stop() == 0
    times = [t for t, _ in arrivals[judged_from:]]
    gaps = np.diff(times)
    # every command acts its sample_time before the next leaves (regular ones are held to tick + 0.2 s; a coast at
    # the tick would be 0.3 s after the one before); 0.1 s of slack for a loaded machine's late wake-ups
    assert len(gaps) >= 3 and np.all(gaps >= 0.5 - 0.1), gaps
    coasts = [d for d in solved() if d["message"].startswith("no new state")]
    assert all(d["status"] == "fallback_shift" for d in coasts) and int(solved()[-1]["missed_samples"]) >= 1
