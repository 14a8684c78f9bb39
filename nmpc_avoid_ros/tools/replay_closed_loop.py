"""`replay BAG --closed-loop`: the counterfactual closed loop of a bag, its figures and sweeps (see replay.py).

What the replay runs comes from the bag unless a flag says otherwise (`replay_inputs`): the
controller settings from the controller's recorded parameters (else --config, else the shipped
van_der_pol.yaml, said so), the plant from the plant node's (evaluation/counterfactual.recorded_plant)
and, for a real-time plant, the loop's timing from the recorded states (evaluation/recorded_timing.py;
`--timing ideal`: every sample lasts sample_time and its command holds from its start) and, for a controller
that compensated latency, the latency each sample predicted (evaluation/recorded_latency.py). The output
says which timing and latency were used and the max deviation against the bound REPLAY_BOUND, or where and
why the replay left it.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..bag.analysis import RecordedRun, controller_samples, load_run
from ..bag.figures import Trace, phase_portrait, run_figures, value_function_plot
from ..bag.mcap_io import Bag, BagError, load_bag
from ..bag.node_parameters import RecordedSetup, recorded_setup
from ..core.config.settings import ControllerSettings, default_config_path, load_params_file
from ..core.errors import NmpcError
from ..evaluation.counterfactual import (
    REPLAY_BOUND,
    Counterfactual,
    PlantChoice,
    metrics_table,
    parse_sweep,
    recorded_metrics,
    recorded_plant,
    replay_closed_loop,
)
from ..evaluation.recorded_latency import recorded_latency


@dataclass
class ReplayInputs:
    """A bag read for replaying: the bag, its run, the controller settings to replay it with and their
    source (one line), and what the bag recorded about its nodes (`setup`)."""

    bag: Bag
    run: RecordedRun
    settings: ControllerSettings
    settings_source: str
    setup: RecordedSetup


def replay_inputs(path: Path, config: Path | None = None, solver: str | None = None,
                  overrides: dict[str, Any] | None = None) -> ReplayInputs:
    """Read the bag once; the settings are the file `config` if given, else the recorded controller's
    parameters, else the shipped van_der_pol.yaml (the source says which and why), then `solver` and
    `overrides` (checked here, before the run is read). BagError / ConfigError on failure."""
    bag = load_bag(path)
    setup = recorded_setup(bag, controller_samples(bag)[1])
    if config is not None:
        params, source = load_params_file(config).section("controller"), f"--config {config}"
    elif setup.controller is not None:
        params, source = dict(setup.controller), f"the bag's {setup.controller_node} parameters"
    else:
        default = default_config_path()
        params = load_params_file(default).section("controller")
        source = (f"assumed: the bag holds no usable controller parameters (bags recorded before the recorder "
                  f"kept them have none): the shipped {default.name}; --config to choose")
    if solver is not None:
        params["solver"] = solver
    settings = ControllerSettings.from_params(params)
    settings.replace(**(overrides or {}))  # validated before the run is read
    return ReplayInputs(bag, load_run(path, settings=settings, bag=bag), settings, source, setup)


def describe_inputs(inputs: ReplayInputs, plant: PlantChoice | None = None) -> list[str]:
    """Lines saying where the settings (and the plant) come from, and what was missing in the bag."""
    lines = [f"controller settings: {inputs.settings_source}"]
    if plant is not None:
        lines.append(f"plant: {plant.integration} integration of {plant.model}"
                     + (f", {plant.step:g} s per command" if plant.step else "") + f" ({plant.source})")
        lines += plant.notes
    return lines + inputs.setup.notes


def timing_line(plant: PlantChoice, timing: str) -> str:
    """What timing the replay's plant runs with, in one line."""
    if plant.timing is not None:
        return plant.timing.describe()
    if timing != "recorded":
        return "ideal (--timing ideal): every sample lasts sample_time, its command acts from its start"
    if not plant.real_time:
        return "lockstep: every sample lasts the plant's step, its command acts from its start"
    return (f"ideal (every sample lasts sample_time, its command acts from its start): the recorded timing cannot be "
            f"recovered: {plant.timing_note or 'not asked'}")


def recorded_trace(run: RecordedRun, label: str = "recorded") -> Trace:
    t = np.arange(len(run.states_with_final)) * run.sample_time
    return Trace(label, t, run.states_with_final, run.u, run.y_a)


def counterfactual_trace(cf: Counterfactual) -> Trace:
    return Trace(cf.label, np.arange(len(cf.run.x)) * cf.run.sample_time, cf.run.x, cf.run.u, cf.run.y_a)


def write_outputs(out: Path, run: RecordedRun, settings: ControllerSettings, runs: list[Counterfactual],
                  report: dict[str, Any]) -> None:
    """OUT/phase_portrait.png, time_series.png, value_function.png (one run) or sweep.png, metrics.json, sweep.md."""
    out.mkdir(parents=True, exist_ok=True)
    traces = [recorded_trace(run)] + [counterfactual_trace(cf) for cf in runs]
    target = run.targets[-1].tolist()
    if len(runs) == 1:
        run_figures(traces, settings, target, out, "recorded vs counterfactual")
        series = [(cf.label, np.arange(len(cf.run.certificate)),
                   np.array([c["value_function"] for c in cf.run.certificate], dtype=float),
                   np.array([bool(c["violated"]) for c in cf.run.certificate])) for cf in runs]
        if run.certificate:
            series.insert(0, ("recorded", np.arange(len(run.x)), run.certificate["value_function"],
                              run.certificate["violated"]))
        value_function_plot(series, out / "value_function.png")
    else:
        lo, hi = settings.state_min, settings.state_max
        phase_portrait(traces, out / "sweep.png", product_bound=2.0 if settings.model == "van_der_pol" else None,
                       xlim=(lo[0], hi[0]), ylim=(lo[1], hi[1]), title="Counterfactual sweep")
        (out / "sweep.md").write_text(report["table"] + "\n")
    (out / "metrics.json").write_text(json.dumps(report, indent=2))


def closed_loop_main(args: argparse.Namespace) -> int:
    started = time.perf_counter()
    try:
        overrides = {k: v for k, v in (("mu", args.mu), ("kappa", args.kappa)) if v is not None}
        sweep = parse_sweep(args.sweep) if args.sweep else None
        inputs = replay_inputs(args.bag, args.config, args.solver, overrides)
        run, settings = inputs.run, inputs.settings
        plant = recorded_plant(inputs.bag, inputs.setup, settings, args.plant,
                               run if args.timing == "recorded" else None)
        # a real-time controller's samples as it stepped them: the latency each predicted, at its state times
        latency = recorded_latency(inputs.bag, run, settings) if args.timing == "recorded" and plant.real_time \
            else None
        if sweep is None:
            variants = [("counterfactual", overrides)]
        else:
            name, values = sweep
            variants = [(f"{name}={v:g}", {**overrides, name: v}) for v in values]
        runs = [replay_closed_loop(run, settings, plant, changes, label, latency) for label, changes in variants]
    except (BagError, NmpcError) as exc:
        print(f"replay: error: {exc}", file=sys.stderr)
        return 1
    notes = describe_inputs(inputs, plant)
    timing = timing_line(plant, args.timing)
    latency_used = ("none (--timing ideal)" if args.timing != "recorded" else
                    latency.line if latency is not None else "none: the plant ran in lockstep (it waits for each "
                                                             "command; the controller predicts nothing)")
    notes += [f"timing: {timing}", f"latency: {latency_used}"]
    recorded = recorded_metrics(run, settings)
    rows = [("recorded", recorded)] + [(cf.label, cf.metrics) for cf in runs]
    table = metrics_table(rows)
    seconds = time.perf_counter() - started
    partial = "" if run.finished else f" (the file was not finished: {len(run.x)} samples recovered, replayed)"
    for line in notes:
        print(f"replay --closed-loop: {line}")
    print(table)
    for cf in runs:
        deviation = cf.verdict() if not cf.changes else f"max |x - x_recorded| {cf.max_state_error:.3g}"
        print(f"replay --closed-loop: {cf.label}: {len(cf.run.u)} samples on the {plant.integration} plant from "
              f"x0 = {run.x[0].tolist()}; {deviation}")
    print(f"replay --closed-loop: {len(runs)} run(s) in {seconds:.1f} s{partial}")
    report = {"bag": str(args.bag), "finished": run.finished, "plant": plant.integration, "plant_model": plant.model,
              "plant_source": plant.source, "settings_source": inputs.settings_source, "notes": notes,
              "timing": None if plant.timing is None else plant.timing.describe(), "timing_used": timing,
              # the same as data: commands a plant step or more late (None: no recorded timing)
              "timing_late_commands": None if plant.timing is None else plant.timing.late_commands,
              "latency": latency_used, "bound": REPLAY_BOUND,
              "seconds": seconds, "recorded": recorded, "table": table,
              "runs": [{"label": cf.label, "changes": cf.changes, "metrics": cf.metrics,
                        "max_state_error": cf.max_state_error, "first_beyond": cf.first_beyond,
                        "verdict": cf.verdict()} for cf in runs]}
    if args.json:
        cf = runs[0]
        doc = {**cf.run.to_json(), "summary": cf.metrics, "replay": {k: v for k, v in report.items() if k != "runs"}}
        doc["replay"].update(changes=cf.changes, max_state_error=cf.max_state_error, first_beyond=cf.first_beyond,
                             verdict=cf.verdict())
        if len(runs) > 1:
            doc["sweep"] = [{**r.run.to_json(), "label": r.label, "summary": r.metrics} for r in runs]
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(doc))
    if args.out:
        write_outputs(args.out, run, settings, runs, report)
    return 0
