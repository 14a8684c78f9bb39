"""The live configs searched every sample against prepared and answered by the feedback law, side by side.

    python -m nmpc_avoid_ros.bench.feedback --json bench/feedback.json --markdown bench/feedback.md

Each scenario runs the same shipped live config twice, `feedback: false` (every sample searches) and
`feedback: true` (core/sample/feedback.py: the next sample prepared after each command, answered by the
feedback law), interleaved sample by sample in one process so that load hits both alike, against the
continuous plant, with the compiled solvers (waited for: core/nlp/background.py). Per sample it times the
whole `step` call (the state-to-command time in process: validation, prediction, the search or the law,
the result) and, for the prepared variant, `prepare` (between the samples, off the command's path).
Scenarios: the paper's run (x0 = [-5, 0], y_t = 5) with mu = 1e8 and 0; the same run among the bench's 4
ellipses (bench/main.py VDP_ELLIPSES); the mobile robot (config/mobile_robot_live.yaml, N = 20) among its
4 ellipses. Results: BENCHMARKS.md, 'Preparation and feedback'.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..core.config.settings import ControllerSettings, default_config_path, load_params_file
from ..core.loop.closed_loop import ClosedLoop, ContinuousPlant
from ..core.loop.metrics import max_abs_product, outputs, penetration, tracking
from ..core.nlp import background
from ..core.problem.regions import Region
from ..core.sample.controller import NmpcController
from ..core.sample.step_result import StepResult
from .main import ROBOT_ELLIPSES, VDP_ELLIPSES, machine


class Timed:
    """An NmpcController whose `step` and `prepare` calls are timed (wall time, s)."""

    def __init__(self, controller: NmpcController) -> None:
        self.controller = controller
        self.step_s: list[float] = []
        self.prepare_s: list[float] = []

    def step(self, x: np.ndarray, y_t: np.ndarray, regions: Sequence[Region] | None, time: float | None = None
             ) -> StepResult:
        begin = _clock()
        result = self.controller.step(x, y_t, regions, time=time)
        self.step_s.append(_clock() - begin)
        return result

    def prepare(self) -> None:
        begin = _clock()
        self.controller.prepare()
        self.prepare_s.append(_clock() - begin)


def _clock() -> float:
    return time.perf_counter()


def _settings(config: str, **changes: Any) -> ControllerSettings:
    params = load_params_file(default_config_path().parent / config).section("controller")
    return ControllerSettings.from_params(params).replace(**changes)


#: (name, config, changes, x0, target, samples, regions of sample 0)
SCENARIOS: tuple[tuple[str, str, dict, list[float], list[float], int, Sequence[Region]], ...] = (
    ("paper/mu=1e8", "van_der_pol_live.yaml", {}, [-5.0, 0.0], [5.0], 50, ()),
    ("paper/mu=0", "van_der_pol_live.yaml", {"mu": 0.0}, [-5.0, 0.0], [5.0], 50, ()),
    ("vdp_4_ellipses", "van_der_pol_live.yaml", {}, [-5.0, 0.0], [5.0], 60, VDP_ELLIPSES),
    ("robot_4_ellipses/N=20", "mobile_robot_live.yaml", {}, [-8.0, -6.0, 0.0, 0.0], [8.0, 6.0], 80, ROBOT_ELLIPSES),
)


def _stats(values_ms: np.ndarray) -> dict[str, float]:
    if not values_ms.size:
        return {}
    warm = values_ms[1:] if values_ms.size > 1 else values_ms
    return {"median": float(np.median(values_ms)), "p99": float(np.percentile(values_ms, 99)),
            "max_warm": float(np.max(warm)), "cold_start": float(values_ms[0])}


def run(scenario: tuple, progress: Callable[[str], None]) -> list[dict[str, Any]]:
    """Both variants of one scenario, interleaved; one record each."""
    name, config, changes, x0, target, samples, regions = scenario
    loops, timed = {}, {}
    for feedback in (False, True):
        settings = _settings(config, feedback=feedback, **changes)
        controller = NmpcController(settings)
        background.wait_compiled()
        timed[feedback] = Timed(controller)
        loops[feedback] = ClosedLoop(timed[feedback], ContinuousPlant(controller.model), x0, target,
                                     settings.sample_time, lambda k: list(regions) if k == 0 else None)
    for _ in range(samples):
        for loop in loops.values():
            loop.advance()
    records = []
    for feedback, loop in loops.items():
        run_ = loop.trajectory()
        results: list[StepResult] = run_.outcomes
        settings = timed[feedback].controller.settings
        model = timed[feedback].controller.model
        step_ms = np.array(timed[feedback].step_s) * 1e3
        answered = np.array([r.answered for r in results])
        y = outputs(model, run_.x, run_.u)
        outcomes: dict[str, int] = {}
        for r in results:
            key = str(r.feedback) if r.feedback is not None else "not_prepared"
            outcomes[key] = outcomes.get(key, 0) + 1
        record = {
            "scenario": name, "variant": "prepared" if feedback else "searched", "samples": samples,
            "step_ms": _stats(step_ms), "step_ms_answered": _stats(step_ms[answered]),
            "step_ms_searched": _stats(step_ms[~answered]),
            "prepare_ms": _stats(np.array(timed[feedback].prepare_s) * 1e3),
            "feedback": outcomes, "fallbacks": int(sum(r.is_fallback for r in results)),
            "settling_step": tracking(y, np.asarray(target, float), settings.sample_time)["settling_step"],
        }
        if model.name == "van_der_pol":
            record["max_abs_x1x2"] = max_abs_product(run_.x)
        if regions:
            record["max_penetration"] = penetration(settings, model, run_.x, run_.u, run_.regions, y)[
                "max_penetration"]
        records.append(record)
        s = record["step_ms"]
        progress(f"{name:22s} {record['variant']:9s} step median {s['median']:7.3f} ms p99 {s['p99']:7.2f} "
                 f"max warm {s['max_warm']:7.2f}  answered {int(answered.sum())}/{samples}  "
                 f"settle {record['settling_step']}")
    return records


def markdown(records: list[dict[str, Any]]) -> str:
    """The table of BENCHMARKS.md, 'Preparation and feedback'."""
    lines = ["| scenario | variant | step ms: median / p99 / max warm | answered samples: median / max ms | "
             "answered | prepare ms: median / max | settles | max \\|x1 x2\\| or penetration |",
             "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in records:
        s, a, p = r["step_ms"], r["step_ms_answered"], r["prepare_ms"]
        quality = r.get("max_abs_x1x2", r.get("max_penetration"))
        if "max_penetration" in r and "max_abs_x1x2" in r:
            quality = f"{r['max_abs_x1x2']:.4f} / {r['max_penetration']:.2g}"
        elif quality is not None:
            quality = f"{quality:.4g}"
        lines.append(
            f"| {r['scenario']} | {r['variant']} | {s['median']:.3f} / {s['p99']:.2f} / {s['max_warm']:.2f} | "
            + (f"{a['median']:.3f} / {a['max_warm']:.3f}" if a else "-")
            + f" | {r['feedback'].get('answered', 0)} of {r['samples']} | "
            + (f"{p['median']:.1f} / {max(p['max_warm'], p['cold_start']):.1f}" if p else "-")
            + f" | {r['settling_step']} | {quality} |")
    return "\n".join(lines) + "\n"


def dds_latency(samples: int, progress: Callable[[str], None]) -> dict[str, Any]:
    """State published -> command received through DDS (bench/node.py's probe, lockstep: the controller answers
    each state as it arrives) with the live config, searched and prepared, from the user's solver cache. The
    probe waits 0.3 s after each command (the preparation runs then, as it would within a 0.5 s sample)."""
    from .node import measure_echo, measure_node

    config = default_config_path().parent / "van_der_pol_live.yaml"
    out = {"echo": measure_echo(samples, progress)}  # rclpy's own floor, the same probe and stamps
    for feedback in ("false", "true"):
        out["prepared" if feedback == "true" else "searched"] = measure_node(
            samples, progress, config=config, parameters={"lockstep": "true", "target": "[5.0]", "feedback": feedback},
            starts=("warm",), pause=0.3)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="bench.feedback", description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", type=Path, required=True, help="write the records here")
    ap.add_argument("--markdown", type=Path, help="also write the table here")
    ap.add_argument("--scenarios", help="comma-separated name prefixes (default: all)")
    ap.add_argument("--node-samples", type=int, default=200,
                    help="samples of the DDS measurement per variant (0: skip it)")
    args = ap.parse_args(argv)
    chosen = [s for s in SCENARIOS if not args.scenarios or any(s[0].startswith(p)
                                                                 for p in args.scenarios.split(","))]
    records: list[dict[str, Any]] = []
    for scenario in chosen:
        records += run(scenario, lambda line: print(line, file=sys.stderr, flush=True))
    report: dict[str, Any] = {"machine": machine(), "records": records}
    if args.node_samples:
        report["dds"] = dds_latency(args.node_samples, lambda line: print(line, file=sys.stderr, flush=True))
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(report, indent=1))
    if args.markdown:
        args.markdown.write_text(markdown(records))
    print(markdown(records))
    for variant, node in report.get("dds", {}).items():
        r, d = node["round_trip_ms"], node["dds_round_trip_ms"]
        if variant == "echo":
            print(f"DDS echo (bench/echo.py, rclpy's floor): median {r['median']:.3f} ms in the probe's callback, "
                  f"{d.get('median', float('nan')):.3f} to the reception stamp, p99 {d.get('p99', float('nan')):.3f}")
            continue
        print(f"DDS {variant}: state published -> command in the probe's callback median {r['median']:.3f} ms, "
              f"p90 {r['p90']:.3f}, p99 {r['p99']:.3f}, max {r['max']:.3f} ({r['count']} samples); -> the command's "
              f"reception stamp median {d.get('median', float('nan')):.3f}, p99 {d.get('p99', float('nan')):.3f}; "
              f"in the node {node['step_latency_ms'].get('median', float('nan')):.3f} ms median")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
