"""`figures`: the paper's example offline, with and without avoidance -> Fig. 1, Fig. 2, metrics.

    python -m nmpc_avoid_ros figures --out out/offline [--config FILE] [--plant euler|continuous]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from ..bag.figures import Trace, phase_portrait, time_series
from ..core.errors import NmpcError
from ..core.loop.closed_loop import PLANTS, ClosedLoopRun
from .simulate import load_scenario, simulate


def run_trace(label: str, run: ClosedLoopRun) -> Trace:
    t = np.arange(len(run.x)) * run.sample_time
    return Trace(label, t, run.x, run.u, run.y_a)


def paper_figures(out_dir: Path, config: str | None = None, plant: str = "euler") -> dict:
    """Run the scenario with the configured mu and with mu = 0; write PNGs, runs and metrics.json."""
    out_dir.mkdir(parents=True, exist_ok=True)
    base = load_scenario(config, plant=plant)
    metrics: dict = {"config": str(base.config_path), "plant": plant, "runs": {}}
    traces = []
    for name, mu in (("with_avoidance", base.settings.mu), ("without_avoidance", 0.0)):
        scenario = load_scenario(config, plant=plant, mu=mu)
        run, summary = simulate(scenario)
        metrics["runs"][name] = {"mu": mu, **summary}
        data = run.to_json()
        data["summary"] = summary
        (out_dir / f"{name}.json").write_text(json.dumps(data))
        traces.append(run_trace(f"{name.replace('_', ' ')} (mu={mu:g})", run))
    target = base.target
    x_s = [target[0], 0.0]
    phase_portrait(traces, out_dir / "phase_portrait.png", target_state=x_s,
                   title=f"Van der Pol, y_t = {target[0]:g} ({plant} plant)")
    time_series(traces, out_dir / "time_series.png", target=target, title=f"States and input ({plant} plant)")
    (out_dir / "metrics.json").write_text(json.dumps(metrics, indent=2))
    return metrics


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="figures", description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=Path("out/offline"), help="output directory")
    ap.add_argument("--config", help="ROS 2 params file (default: the shipped van_der_pol.yaml)")
    ap.add_argument("--plant", choices=PLANTS, default="euler")
    args = ap.parse_args(argv)
    try:
        metrics = paper_figures(args.out, args.config, args.plant)
    except NmpcError as exc:
        print(f"figures: error: {exc}", file=sys.stderr)
        return 2
    for name, m in metrics["runs"].items():
        print(f"figures: {name}: settled at step {m['settling_step']}, max|x1x2| = {m['max_abs_x1x2']:.4f}")
    print(f"figures: wrote {args.out}/phase_portrait.png, time_series.png, metrics.json")
    return 0
