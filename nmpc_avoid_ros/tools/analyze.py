"""`analyze`: bags -> metrics.json and the paper's figures, without a running ROS graph.

    python -m nmpc_avoid_ros analyze out/with_avoidance.mcap out/without_avoidance.mcap --out out/analysis

Per bag: settling step and time, overshoot (the excursion beyond the target in the direction of
the step, as a fraction of the step; None with `overshoot_note` saying why when the run starts
within the settling tolerance of its target), final error, maximum penetration into any avoided
region and minimum clearance (moving regions where they were at each sample's time), solve-time
median/p99/max, deadline overruns, fallbacks, rejected inputs, whether the file was finished,
and the stability certificate's violations (V_N per sample in value_function.png;
docs/certificate.md). Several bags are overlaid in the figures; the phase portrait draws moving
obstacles at a few sample times beside the state of that time.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from ..bag.analysis import load_run, moving_snapshots, run_metrics, union_regions
from ..bag.figures import Trace, run_figures, value_function_plot
from ..bag.mcap_io import BagError, load_bag
from ..bag.report import report_data
from ..bag.report_page import write_report
from ..core.config.settings import ControllerSettings, default_config_path, load_params_file
from ..core.errors import NmpcError


def analyze(bags: list[Path], out: Path, config: Path | None = None, labels: list[str] | None = None,
            html: Path | None = None) -> dict:
    """Read every bag, write DIR/metrics.json, phase_portrait.png, time_series.png, value_function.png;
    with `html`, also the self-contained report page there (bag/report_page.py)."""
    config = config or default_config_path()
    settings = ControllerSettings.from_params(load_params_file(config).section("controller"))
    labels = labels or [b.stem.replace("_", " ") for b in bags]
    runs, results = [], []
    for bag, label in zip(bags, labels):
        print(f"analyze: reading {bag} ...", file=sys.stderr, flush=True)
        run = load_run(bag, progress=True, settings=settings)
        if not run.finished:
            print(f"analyze: {bag}: the file was not finished; using the complete chunks recovered",
                  file=sys.stderr)
        runs.append((label, run))
        results.append({"label": label, **run_metrics(run, settings)})
    out.mkdir(parents=True, exist_ok=True)
    traces = []
    for label, run in runs:
        t = run.t if run.final_state is None else np.append(run.t, run.t[-1] + settings.sample_time)
        traces.append(Trace(label, t, run.states_with_final, run.u, run.y_a, union_regions([run]),
                            moving_snapshots(run, settings)))
    run_figures(traces, settings, runs[0][1].targets[-1].tolist(), out, f"from {len(bags)} bag(s)")
    certified = [(label, np.arange(len(run.x)), run.certificate["value_function"], run.certificate["violated"])
                 for label, run in runs if run.certificate]
    if certified:
        value_function_plot(certified, out / "value_function.png")
    if html is not None:
        pages = [report_data(run, load_bag(bag), settings, label) for bag, (label, run) in zip(bags, runs)]
        write_report(html, pages, f"nmpc_avoid_ros report: {', '.join(labels)}")
    report = {"config": str(config), "bags": results}
    (out / "metrics.json").write_text(json.dumps(report, indent=2))
    return report


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="analyze", description=__doc__.split("\n\n")[0])
    ap.add_argument("bags", nargs="+", type=Path, help="MCAP bags (files, or directories of split files)")
    ap.add_argument("--out", type=Path, required=True, help="output directory")
    ap.add_argument("--config", type=Path, help="params file of the runs (default: the shipped van_der_pol.yaml)")
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
        print(f"analyze: {r['label']}: settled at step {r.get('settling_step')}, max penetration "
              f"{r['max_penetration']:.4g}, solve median {r['solve_ms']['median']:.1f} ms, fallbacks {r['fallbacks']}, "
              + (f"certificate violations {r['certificate_violations']} of {r['certificate_checked']} checked"
                 if r["certificate_checked"] is not None else "no certificate in the bag")
              + ("" if r["finished"] else " (file not finished)"))
    print(f"analyze: wrote {args.out}/metrics.json, phase_portrait.png, time_series.png"
          + (", value_function.png" if (args.out / "value_function.png").exists() else "")
          + (f"; report {args.html} ({args.html.stat().st_size / 1e3:.0f} kB)" if args.html else ""))
    return 0
