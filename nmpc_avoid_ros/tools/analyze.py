"""`analyze`: bags -> metrics.json and the paper's figures, without a running ROS graph.

    python -m nmpc_avoid_ros analyze out/with_avoidance.mcap out/without_avoidance.mcap --out out/analysis

Each bag is analysed with the controller settings it recorded (the controller's parameters, as
`replay` reads them; `--config` replaces them; a bag recorded before the recorder kept parameters
gets the shipped van_der_pol.yaml, and `config.source` says so): the model, the boxes, the keep-in
expressions and the regions' capacities are the run's. `config` in metrics.json names where the
settings came from and the shipped params file they match (or differ from the least, and in what).

Per bag: the targets the controller accepted (a refused one, of the wrong size or not finite, is
listed under `targets_refused`; goals on `goal_pose` count on the robot interface), the run cut
per target into `segments`, each with its settling step and time from the target change, overshoot
and final error (the top-level settling_step/settling_time: the sample from which the output stays
at the last target); `clearance` from three views (bag/truth.py): `recorded_states` (every plant
state the bag recorded, at the plant's rate: the truth), `at_samples` (the states solved on) and
`resimulated_between_samples` (the model from each sample under ideal timing), each with the
keep-in/region g and the Euclidean `min_obstacle_distance` in the plane's units (metres for a
robot); the state box on the recorded states and the input box on the recorded commands
(`state_box`, `input_box`: the largest excursion beyond the bounds); solve-time median/p99/max,
deadline overruns, fallbacks, rejected inputs, whether the file was finished, the stability
certificate's violations (V_N per sample in value_function.png; docs/certificate.md). Several bags
are overlaid in the figures (they must share a model); the time series draws each target where it
held; the phase portrait draws moving obstacles at a few sample times beside the state of that time.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

from ..bag.analysis import moving_snapshots, union_regions
from ..bag.figures import Trace, run_figures, value_function_plot
from ..bag.mcap_io import BagError
from ..bag.report import report_data
from ..bag.report_page import write_report
from ..bag.truth import bag_metrics
from ..core.config.settings import ControllerSettings, default_config_path, load_params_file
from ..core.errors import NmpcError
from .replay_closed_loop import ReplayInputs, replay_inputs


def shipped_match(settings: ControllerSettings) -> dict[str, Any]:
    """The shipped params file whose controller settings equal `settings`, else the one that differs in the
    fewest settings: {"file", "differs_in": [setting names]} (file None when none can be read)."""
    best: tuple[int, str | None, list[str]] = (10**9, None, [])
    for path in sorted(default_config_path().parent.glob("*.yaml")):
        try:
            shipped = ControllerSettings.from_params(load_params_file(path).section("controller"))
        except NmpcError:
            continue
        differs = [f.name for f in dataclasses.fields(settings)
                   if getattr(settings, f.name) != getattr(shipped, f.name)]
        if len(differs) < best[0]:
            best = (len(differs), f"config/{path.name}", differs)
    return {"file": best[1], "differs_in": best[2]}


def config_entry(inputs: ReplayInputs) -> dict[str, Any]:
    """Where a bag's settings came from (`source`, the controller node) and the shipped file they match."""
    return {"source": inputs.settings_source, "controller_node": inputs.run.controller_node,
            "interface": inputs.run.interface.name, "interface_source": inputs.run.interface.source,
            "closest_shipped": shipped_match(inputs.settings), "notes": inputs.setup.notes}


def analyze(bags: list[Path], out: Path, config: Path | None = None, labels: list[str] | None = None,
            html: Path | None = None) -> dict:
    """Read every bag, write DIR/metrics.json, phase_portrait.png, time_series.png, value_function.png;
    with `html`, also the self-contained report page there (bag/report_page.py)."""
    labels = labels or [b.stem.replace("_", " ") for b in bags]
    runs, results = [], []
    for path, label in zip(bags, labels):
        print(f"analyze: reading {path} ...", file=sys.stderr, flush=True)
        inputs = replay_inputs(path, config)
        run = inputs.run
        print(f"analyze: {path}: controller settings: {inputs.settings_source}", file=sys.stderr)
        if not run.finished:
            print(f"analyze: {path}: the file was not finished; using the complete chunks recovered",
                  file=sys.stderr)
        runs.append((label, inputs))
        results.append({"label": label, "config": config_entry(inputs),
                        **bag_metrics(inputs.bag, run, inputs.settings)})
    models = {inputs.settings.model for _, inputs in runs}
    if len(models) > 1:
        raise NmpcError(f"the bags' controllers ran different models ({', '.join(sorted(models))}): the figures "
                        "overlay one model's runs; analyze them separately")
    settings = runs[0][1].settings
    out.mkdir(parents=True, exist_ok=True)
    traces = []
    for label, inputs in runs:
        run = inputs.run
        t = run.t if run.final_state is None else np.append(run.t, run.t[-1] + settings.sample_time)
        traces.append(Trace(label, t, run.states_with_final, run.u, run.y_a, union_regions([run]),
                            moving_snapshots(run, inputs.settings), targets=run.targets))
    run_figures(traces, settings, None, out, f"from {len(bags)} bag(s)")
    certified = [(label, np.arange(len(inputs.run.x)), inputs.run.certificate["value_function"],
                  inputs.run.certificate["violated"]) for label, inputs in runs if inputs.run.certificate]
    if certified:
        value_function_plot(certified, out / "value_function.png")
    if html is not None:
        pages = [report_data(inputs.run, inputs.bag, inputs.settings, label) for label, inputs in runs]
        write_report(html, pages, f"nmpc_avoid_ros report: {', '.join(labels)}")
    report = {"config": str(config) if config is not None else "per bag: bags[].config", "bags": results}
    (out / "metrics.json").write_text(json.dumps(report, indent=2))
    return report


def _summary(r: dict[str, Any]) -> str:
    """One line per bag: settling, the three clearances, solve times, fallbacks, the certificate."""
    clearance = r["clearance"]
    truth = clearance["recorded_states"]
    pen = (f"max penetration {truth['max_penetration']:.4g} over {truth['states']} recorded states"
           if truth else "no recorded plant states") + \
        f" ({clearance['at_samples']['max_penetration']:.4g} at the samples, " \
        f"{clearance['resimulated_between_samples']['max_penetration']:.4g} re-simulated between them)"
    return (f"{r['label']}: {len(r['segments'])} target segment(s), settled at step {r.get('settling_step')}, {pen}, "
            f"solve median {r['solve_ms']['median']:.1f} ms, fallbacks {r['fallbacks']}, "
            + (f"certificate violations {r['certificate_violations']} of {r['certificate_checked']} checked"
               if r["certificate_checked"] is not None else "no certificate in the bag")
            + ("" if r["finished"] else " (file not finished)"))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="analyze", description=__doc__.split("\n\n")[0])
    ap.add_argument("bags", nargs="+", type=Path, help="MCAP bags (files, or directories of split files)")
    ap.add_argument("--out", type=Path, required=True, help="output directory")
    ap.add_argument("--config", type=Path, help="params file of the runs (default: the controller parameters each "
                    "bag recorded, else the shipped van_der_pol.yaml)")
    ap.add_argument("--labels", nargs="+", help="legend labels, one per bag")
    ap.add_argument("--html", type=Path, help="also write one self-contained HTML report here (scrub through samples)")
    args = ap.parse_args(argv)
    if args.labels and len(args.labels) != len(args.bags):
        print("analyze: error: give one label per bag", file=sys.stderr)
        return 2
    try:
        report = analyze(args.bags, args.out, args.config, args.labels, args.html)
    except (BagError, NmpcError) as exc:
        print(f"analyze: error: {exc}", file=sys.stderr)
        return 1
    for r in report["bags"]:
        print(f"analyze: {_summary(r)}")
    print(f"analyze: wrote {args.out}/metrics.json, phase_portrait.png, time_series.png"
          + (", value_function.png" if (args.out / "value_function.png").exists() else "")
          + (f"; report {args.html} ({args.html.stat().st_size / 1e3:.0f} kB)" if args.html else ""))
    return 0
