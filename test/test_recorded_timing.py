"""A real-time bag's timing recovered from its states (evaluation/recorded_timing.py) and an unchanged
closed-loop replay of a latency-compensated bag reproducing it (evaluation/recorded_latency.py).

The bags are made without a ROS graph: the causal real-time plant (nodes/plant.py) simulated offline, a
command acting from its arrival within a period, written with the package's MCAP writer."""

from __future__ import annotations

import json

import numpy as np
import pytest

PERIOD = 0.05  # s, the plant node's default publish_rate 20 Hz
PER_SAMPLE = 10  # plant periods per 0.5 s sample
HELD = 3  # ticks the plant holds x0 before the first command


def _plant():
    from nmpc_avoid_ros.core.loop.closed_loop import ContinuousPlant
    from nmpc_avoid_ros.core.problem.models import make_model

    return ContinuousPlant(make_model("van_der_pol"))


class CausalPlant:
    """The real-time plant node offline: ticks every PERIOD s; a command acts from its arrival (s after the
    tick of the period it arrives in), the period integrated piecewise as the node does; x0 held until the
    first command."""

    def __init__(self, x0):
        self.plant, self.x, self.u = _plant(), np.asarray(x0, float), None
        self.tick = 0
        self.pending: list[tuple[float, np.ndarray]] = []  # (absolute s, command)
        self.states = [(0, self.x)]  # (tick, state)

    def send(self, at: float, u) -> None:
        self.pending.append((at, np.asarray(u, float)))
        self.pending.sort(key=lambda p: p[0])

    def run_to(self, tick: int) -> None:
        while self.tick < tick:
            start, done = self.tick * PERIOD, 0.0
            while self.pending and self.pending[0][0] < start + PERIOD:
                at, u = self.pending.pop(0)
                upto = min(max(at - start, 0.0), PERIOD)
                if self.u is not None and upto > done:
                    self.x = self.plant.advance(self.x, self.u, upto - done)
                done, self.u = upto, u
            if self.u is not None and PERIOD > done:
                self.x = self.plant.advance(self.x, self.u, PERIOD - done)
            self.tick += 1
            self.states.append((self.tick, self.x))


def _write_bag(path, states, commands, samples, plant_params=None, controller=None):
    """states [(tick, x)], commands [(log s, u)], samples [(log s, values)] -> a bag as the recorder writes it."""
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
    from std_msgs.msg import Float64MultiArray

    from nmpc_avoid_ros.bag.mcap_writer import Ros2McapWriter
    from nmpc_avoid_ros.bag.node_parameters import PARAMETERS_RECORD, parameters_record

    base = 10**9  # ns: log times from 1 s

    def ns(t):
        return base + round(t * 1e9)

    with Ros2McapWriter(path) as bag:
        plant = {"model": "van_der_pol", "integration": "continuous", "sample_time": 0.5, "lockstep": False,
                 "publish_rate": 1 / PERIOD, "initial_state": states[0][1].tolist(), "hold_until_command": True,
                 **(plant_params or {})}
        bag.add_metadata(PARAMETERS_RECORD, parameters_record("/plant", plant, 0))
        if controller is not None:
            fields = {k: (list(v) if isinstance(v, tuple) else v) for k, v in vars(controller).items()}
            bag.add_metadata(PARAMETERS_RECORD, parameters_record("/controller", fields, 0))
        bag.write_message("/target", Float64MultiArray(data=[5.0]), base - 1)
        for tick, x in states:  # published 0.3 ms after the tick
            bag.write_message("/state", Float64MultiArray(data=x.tolist()), ns(tick * PERIOD + 3e-4))
        for t, u in commands:
            bag.write_message("/command", Float64MultiArray(data=list(u)), ns(t))
        for t, values in samples:
            status = DiagnosticStatus(level=DiagnosticStatus.OK, name="/controller: nmpc", message="ok",
                                      hardware_id="/controller")
            status.values = [KeyValue(key=k, value=v) for k, v in values.items()]
            bag.write_message("/diagnostics", DiagnosticArray(status=[status]), ns(t))


def _open_loop_bag(path, offsets, late_steps=False, cover_at=None, plant_params=None, predicted=None):
    """A real-time bag of fixed commands: sample k solves on the state of tick HELD + k PER_SAMPLE and its command
    arrives offsets[k] s after that tick (late_steps: the earlier plant, whole periods); `cover_at` (sample,
    s): a late cover before that sample's command; `predicted` (s per sample): the delay its diagnostics say the
    controller predicted. Returns the true arrival offsets."""
    plant = CausalPlant([-5.0, 0.0])
    commands, samples = [], []
    rng = np.random.default_rng(3)
    us = np.round(rng.uniform(-4, 4, len(offsets)), 3)
    for k, d in enumerate(offsets):
        tick = HELD + k * PER_SAMPLE
        plant.run_to(tick)
        x = plant.x
        if cover_at is not None and cover_at[0] == k:
            plant.send(tick * PERIOD + cover_at[1], [us[k] / 2])
            commands.append((tick * PERIOD + cover_at[1], [us[k] / 2]))
        plant.send(tick * PERIOD + d, [us[k]])
        commands.append((tick * PERIOD + d + (-1e-3 if late_steps else 2e-5), [us[k]]))  # the recorder's log time
        samples.append((tick * PERIOD + d + 1e-4, {
            "state": str(x.tolist()), "command": str([float(us[k])]), "y_a": "[0.0]", "status": "ok",
            "solve_time_ms": "1.0", "state_time": repr(1.0 + tick * PERIOD + 1e-3),
            **({} if predicted is None else {"predicted_delay_ms": f"{predicted[k] * 1e3:.2f}"})}))
    plant.run_to(HELD + len(offsets) * PER_SAMPLE)
    _write_bag(path, plant.states, commands, samples, plant_params)
    return plant


def _recover(path):
    from nmpc_avoid_ros.bag.analysis import load_run
    from nmpc_avoid_ros.bag.mcap_io import load_bag
    from nmpc_avoid_ros.bag.node_parameters import recorded_setup
    from nmpc_avoid_ros.core.config.settings import ControllerSettings
    from nmpc_avoid_ros.evaluation.counterfactual import recorded_plant

    bag, settings = load_bag(path), ControllerSettings()
    run = load_run(path, settings=settings, bag=bag)
    choice = recorded_plant(bag, recorded_setup(bag, "/controller"), settings, None, run)
    return run, choice


def test_each_commands_arrival_is_recovered_from_the_states_of_the_causal_plant(tmp_path):
    from nmpc_avoid_ros.evaluation.recorded_timing import TIMING_TOLERANCE, reproduction_error

    # arrivals within the first period, a later one, on a tick, beyond the next tick
    offsets = [0.0213, 0.0617, 0.1038, 0.05, 0.0004, 0.0799, 0.1472]
    _open_loop_bag(tmp_path / "causal.mcap", offsets, cover_at=(3, 0.017))
    run, choice = _recover(tmp_path / "causal.mcap")
    timing = choice.timing
    assert timing is not None, choice.timing_note
    assert timing.steps == [PER_SAMPLE] * (len(offsets) - 1) + [1]  # the last: to the final state
    # the last command arrives after the final state (a tick after the last sample's): not seen acting
    assert timing.offsets[-1] is None
    recovered = np.array(timing.offsets[:-1], float)
    # measured: to 3e-16 s (the fit's scalar least squares on each period's end state)
    assert np.max(np.abs(recovered - offsets[:-1])) < 1e-12, recovered - offsets[:-1]
    assert [a.sample for a in timing.arrivals][3:5] == [None, 3]  # the late cover, replayed as recorded
    error = reproduction_error(timing, _plant(), run, 0.5)
    assert error < 1e-9 < TIMING_TOLERANCE  # measured: ~1e-13
    assert choice.timing_note.startswith("the recorded timing: plant steps of 50 ms, 10 to 10 per sample, each "
                                         "command acting 0.4 to 103.8 ms")
    assert "1 other recorded command(s) (late cover, deactivation) replayed as recorded" in choice.timing_note
    assert choice.timing_note.endswith(", 5 of 7 commands a plant step or more late")


def test_the_commands_timing_beyond_the_controllers_prediction_is_measured(tmp_path):
    # a compensated controller predicted each command's effect; the plant got some later, one earlier
    offsets = [0.0213, 0.0617, 0.1038, 0.0800, 0.0404, 0.0150, 0.1472]
    jitter = np.array([0.0021, 0.0140, -0.0005, 0.0033, 0.0, 0.0012])  # the last command: after the final state
    _open_loop_bag(tmp_path / "jitter.mcap", offsets, predicted=[*(np.array(offsets[:-1]) - jitter), 0.0])
    _, choice = _recover(tmp_path / "jitter.mcap")
    assert choice.timing is not None, choice.timing_note
    beyond = choice.timing.beyond_prediction()
    assert beyond == pytest.approx(jitter, abs=1e-5)  # predicted_delay_ms is printed to 10 us
    assert choice.timing_note.endswith("against the controller's prediction: +1.65 ms at the median, +8.65 at p90, "
                                       "+14 at most"), choice.timing_note
    # without the controller's prediction in the bag, nothing is claimed
    _open_loop_bag(tmp_path / "plain.mcap", offsets)
    _, plain = _recover(tmp_path / "plain.mcap")
    assert plain.timing.beyond_prediction().size == 0 and "prediction" not in plain.timing_note


def test_the_earlier_plants_whole_late_steps_are_the_special_case_of_arrivals_on_a_tick(tmp_path):
    # the earlier plant applied a command from a tick: arrivals at whole periods (here logged just before)
    offsets = [0.0, 0.05, 0.0, 0.1, 0.05]
    _open_loop_bag(tmp_path / "ticks.mcap", offsets, late_steps=True)
    run, choice = _recover(tmp_path / "ticks.mcap")
    assert choice.timing is not None, choice.timing_note
    # whole periods (snapped to the period's bounds, to the float sum's rounding); the last after the final state
    assert choice.timing.offsets[:-1] == pytest.approx(offsets[:-1], abs=1e-15)
    assert choice.timing.late == [0, 1, 0, 2, 1]


def test_a_bag_whose_states_follow_no_timing_says_why(tmp_path):
    _open_loop_bag(tmp_path / "noise.mcap", [0.03, 0.06, 0.07], plant_params={"process_noise_std": 1e-3})
    _, choice = _recover(tmp_path / "noise.mcap")
    assert choice.timing is None and "process noise (std 0.001)" in choice.timing_note
    # a state the plant cannot have reached under any arrival of the recorded commands (a lost state)
    from nmpc_avoid_ros.bag.mcap_io import load_bag

    _open_loop_bag(tmp_path / "full.mcap", [0.03, 0.06, 0.07])
    bag = load_bag(tmp_path / "full.mcap")
    states = [np.asarray(m.data) for _, m in bag.topics["/state"]]
    kept = [(i, x) for i, x in enumerate(states) if i != HELD + 14]
    commands = [(t * 1e-9 - 1, list(m.data)) for t, m in bag.topics["/command"]]
    samples = [(t * 1e-9 - 1, {kv.key: kv.value for kv in m.status[0].values}) for t, m in bag.topics["/diagnostics"]]
    _write_bag(tmp_path / "lost.mcap", [(i, x) for i, x in kept], commands, samples)
    _, choice = _recover(tmp_path / "lost.mcap")
    assert choice.timing is None
    assert choice.timing_note.startswith(f"the recorded state {HELD + 14} follows from state {HELD + 13} under no "
                                         "arrival of the recorded commands within the plant's 50 ms period")


@pytest.fixture(scope="module")
def compensated_bag(tmp_path_factory):
    """The shipped paper config's controller on the causal real-time plant with latency compensation, as the
    node runs it: sample k solves on the state of its tick, predicted over the delay until its command
    arrives (state age and solve time, here 12-140 ms), and the command arrives then."""
    from nmpc_avoid_ros.core.config.settings import ControllerSettings, default_config_path, load_params_file
    from nmpc_avoid_ros.core.sample.controller import NmpcController

    settings = ControllerSettings.from_params(load_params_file(default_config_path()).section("controller"))
    controller = NmpcController(settings)
    plant = CausalPlant([-5.0, 0.0])
    delays = np.random.default_rng(7).uniform(0.012, 0.14, 12)
    commands, samples = [], []
    for k, d in enumerate(delays):
        tick = HELD + k * PER_SAMPLE
        plant.run_to(tick)
        t = 1.0 + tick * PERIOD
        result = controller.step(plant.x, [5.0], time=t, latency=float(d) if k else 0.0)
        controller.command_sent(t + d)
        plant.send(tick * PERIOD + d, result.u)
        commands.append((tick * PERIOD + d, result.u.tolist()))
        values = {"command": str(result.u.tolist()), "mu": f"{settings.mu:g}", "kappa": f"{settings.kappa:g}",
                  "predicted_delay_ms": f"{result.delay * 1e3:.2f}", "state_age_ms": "0.0",
                  "step_latency_ms": f"{d * 1e3:.3f}",
                  "state": str(plant.x.tolist()), "planned_state": str(result.states[0].tolist()),
                  "state_time": repr(t), "status": str(result.status),
                  "solve_time_ms": f"{result.solve_time * 1e3:.3f}", "y_a": str(result.y_a.tolist())}
        samples.append((tick * PERIOD + d + 1e-4, values))
    plant.run_to(HELD + len(delays) * PER_SAMPLE)
    path = tmp_path_factory.mktemp("compensated") / "compensated.mcap"
    _write_bag(path, plant.states, commands, samples, controller=settings)
    return path, delays


def test_an_unchanged_replay_of_a_compensated_real_time_bag_reproduces_it(compensated_bag, tmp_path, capsys):
    from nmpc_avoid_ros.evaluation.counterfactual import REPLAY_BOUND
    from nmpc_avoid_ros.tools.replay import main as replay_main

    path, delays = compensated_bag
    assert replay_main([str(path), "--closed-loop", "--json", str(tmp_path / "same.json")]) == 0
    out = capsys.readouterr().out
    same = json.loads((tmp_path / "same.json").read_text())["replay"]
    # the recorded timing and each sample's latency, said in the output, and the bag reproduced (measured ~1e-13)
    assert "replay --closed-loop: timing: the recorded timing: plant steps of 50 ms" in out
    assert "replay --closed-loop: latency: each sample stepped with the latency it predicted" in out
    assert "11 of 11 refined against planned_state" in same["latency"]
    assert same["max_state_error"] <= 1e-9 < REPLAY_BOUND and same["first_beyond"] is None
    assert f"within the bound {REPLAY_BOUND:g}" in out
    # without the latency (ideal timing): another loop, and the output says where it parted and why
    assert replay_main([str(path), "--closed-loop", "--timing", "ideal", "--json", str(tmp_path / "ideal.json")]) == 0
    out = capsys.readouterr().out
    ideal = json.loads((tmp_path / "ideal.json").read_text())["replay"]
    assert ideal["latency"] == "none (--timing ideal)" and ideal["max_state_error"] > 1e-3
    assert ideal["timing_used"].startswith("ideal (--timing ideal)")
    assert "beyond the bound" in out and "the replay's timing or latency is not the recording's" in out


def test_a_bag_without_latency_keys_is_stepped_without_latency_and_says_so(tmp_path):
    from nmpc_avoid_ros.bag.mcap_io import load_bag
    from nmpc_avoid_ros.core.config.settings import ControllerSettings
    from nmpc_avoid_ros.evaluation.recorded_latency import recorded_latency

    _open_loop_bag(tmp_path / "old.mcap", [0.03, 0.06])
    run, _ = _recover(tmp_path / "old.mcap")
    rec = recorded_latency(load_bag(tmp_path / "old.mcap"), run, ControllerSettings())
    assert rec.latency == [0.0, 0.0] and rec.sent is None
    assert rec.line.startswith("none: the bag's diagnostics carry no predicted_delay_ms")
