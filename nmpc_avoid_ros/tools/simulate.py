"""`simulate`: the offline closed loop of one configuration or scene, written as JSON.

    python -m nmpc_avoid_ros simulate --config config/van_der_pol.yaml --steps 50 \
        --x0 -5 0 --target 5 --mu 1e8 --plant euler --json out/run.json
    python -m nmpc_avoid_ros simulate --scene config/scenes/crossing_walker.yaml \
        --predict-obstacles off --json out/walker.json

With a scene (core/loop/scene.py: targets over time, moving obstacles) the JSON also holds the pose of
every obstacle at every sample (`obstacles`) and each obstacle's minimum clearance
(`min_clearance`, -g with g the region depth, > 0 outside).
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..core.config.settings import SOLVER_PATHS, ControllerSettings, default_config_path, load_params_file
from ..core.errors import NmpcError
from ..core.loop.closed_loop import PLANTS, ClosedLoopRun, run_closed_loop
from ..core.loop.intersample import clearance_between_samples
from ..core.loop.metrics import max_abs_product, outputs, tracking
from ..core.loop.scene import Scene, load_scene, obstacle_track
from ..core.problem.models import Model
from ..core.sample.controller import NmpcController
from ..core.sample.status import StepStatus


@dataclass
class Scenario:
    """A configuration plus the initial state [n], target [p] and number of steps of a run."""

    settings: ControllerSettings
    x0: list[float]
    target: list[float]
    steps: int
    plant: str
    config_path: Path
    scene: Scene | None = None


def load_scenario(config: str | Path | None, **overrides: Any) -> Scenario:
    """Read the params file; keyword overrides (None = keep the file's value) win.

    Controller fields (e.g. mu=0.0) go to the settings; x0, target, steps, plant to the run.
    """
    path = Path(config) if config else default_config_path()
    params = load_params_file(path)
    ctrl = params.section("controller")
    plant = params.section("plant")
    scen = params.section("scenario")
    run_keys = {"x0", "target", "steps", "plant"}
    for key, value in overrides.items():
        if value is not None and key not in run_keys:
            ctrl[key] = value
    # offline: the compiled solvers from the first solve (a live config's background compile is for a node)
    settings = ControllerSettings.from_params(ctrl).replace(codegen_background=False)
    pick = lambda key, default: overrides.get(key) if overrides.get(key) is not None else default  # noqa: E731
    return Scenario(
        settings=settings,
        x0=[float(v) for v in pick("x0", plant.get("initial_state", [0.0] * 2))],
        target=[float(v) for v in pick("target", scen.get("target", ctrl.get("target", [0.0])))],
        steps=int(pick("steps", scen.get("steps", 50))),
        plant=str(pick("plant", "euler")),
        config_path=path,
    )


def scene_scenario(scene: Scene, **overrides: Any) -> Scenario:
    """The scenario of a scene: its config with the scene's controller overrides, then `overrides` (None = keep)."""
    merged = {**scene.controller, **{k: v for k, v in overrides.items() if v is not None}}
    run = {"x0": list(scene.x0), "target": list(scene.target_at(0.0)), "steps": scene.steps, "plant": scene.plant}
    for key in run:
        merged.setdefault(key, run[key])
    scenario = load_scenario(scene.config, **merged)
    scenario.scene = scene
    return scenario


def summarize(run: ClosedLoopRun, target: list[float], model: Model) -> dict[str, Any]:
    """Settling step (|y - y_t| < 0.05 for good), final error, max |x1 x2|, solve times (core/loop/metrics.py)."""
    x = run.x
    quality = tracking(outputs(model, x, run.u), target, run.sample_time)
    summary: dict[str, Any] = {
        "steps": len(run.u),
        "settling_step": quality["settling_step"],
        "final_error": quality["final_error"],
        "solve_ms_median": float(np.median(run.solve_time) * 1e3),
        "solve_ms_max": float(np.max(run.solve_time) * 1e3),
        "fallbacks": sum(StepStatus(s).is_fallback for s in run.status),
        "failures": sum(s != StepStatus.OK for s in run.status),
        "nlp_builds": run.info.get("nlp_builds"),
    }
    if model.name == "van_der_pol":  # the paper's region |x1 x2| <= 2; meaningless for another model
        summary["max_abs_x1x2"] = max_abs_product(x)
    return summary


def simulate(scenario: Scenario) -> tuple[ClosedLoopRun, dict[str, Any]]:
    """Run the scenario's closed loop; returns the run and its summary.

    With a scene: its targets and obstacles at each sample time k Ts; run.info gains the obstacle
    poses per sample and the summary each obstacle's minimum clearance and the deepest penetration.
    """
    controller = NmpcController(scenario.settings)
    scene, ts = scenario.scene, scenario.settings.sample_time
    if scene is None:
        run = run_closed_loop(controller, scenario.x0, scenario.target, scenario.steps, scenario.plant)
        summary = summarize(run, scenario.target, controller.model)
        # the keep-in expressions (g > 0 outside) over the samples and the motion between them (10 points each)
        between = clearance_between_samples(controller.settings, controller.model, run.x, run.u, run.regions)
        summary["max_penetration_keep_in"] = between["max_penetration_keep_in"]
        return run, summary
    run = run_closed_loop(controller, scenario.x0, lambda k: scene.target_at(k * ts), scenario.steps, scenario.plant,
                          lambda k: scene.regions_at(k * ts))
    summary = summarize(run, list(run.targets[-1]), controller.model)
    poses, clearance = obstacle_track(scene, run.x, run.u, ts, controller.model, controller.settings)
    run.info["obstacles"] = poses
    known = [c for c in clearance.values() if c is not None]
    between = clearance_between_samples(controller.settings, controller.model, run.x, run.u, run.regions)
    summary.update({"min_clearance": clearance, "max_penetration": max(0.0, -min(known)) if known else 0.0,
                    "predict_obstacles": controller.settings.predict_obstacles,
                    # the continuous motion under each held command, 10 points per sample (core/loop/intersample.py)
                    "between_samples": {key: between[key] for key in (
                        "max_penetration_keep_in", "max_penetration_obstacles", "min_clearance_obstacles")}})
    return run, summary


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="simulate", description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", help="ROS 2 params file (default: the shipped config/van_der_pol.yaml)")
    ap.add_argument("--scene", help="scene YAML (config, x0, steps, plant, targets, moving obstacles); the other "
                                    "options override it")
    ap.add_argument("--predict-obstacles", choices=("on", "off"),
                    help="predict moving obstacles over the horizon (default: the config's, on)")
    ap.add_argument("--steps", type=int, help="number of samples K")
    ap.add_argument("--x0", type=float, nargs="+", help="initial state (n values)")
    ap.add_argument("--target", type=float, nargs="+", help="target output y_t (p values)")
    ap.add_argument("--mu", type=float, help="avoidance weight (0 disables avoidance)")
    ap.add_argument("--kappa", type=float, help="offset weight")
    ap.add_argument("--horizon", type=int, help="prediction horizon N")
    ap.add_argument("--escape-horizon", type=int, help="horizon of the passage mode's NLP (0: off; default: the "
                                                        "config's; it must exceed N)")
    ap.add_argument("--plant", choices=PLANTS, help="euler: the prediction model; continuous: ZOH + DOP853")
    ap.add_argument("--solver", help="solver path by name ('list' prints them and exits)")
    ap.add_argument("--codegen", action=argparse.BooleanOptionalAction, default=None,
                    help="generate, compile and cache the solver's functions as C (default: the config's)")
    ap.add_argument("--json", type=Path, help="write the run as one JSON object here")
    return ap


def print_solvers() -> None:
    """One line per solver path: name and what it is."""
    width = max(map(len, SOLVER_PATHS))
    for name, text in SOLVER_PATHS.items():
        print(f"{name:<{width}}  {text}")


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.solver == "list":
        print_solvers()
        return 0
    predict = None if args.predict_obstacles is None else args.predict_obstacles == "on"
    overrides = dict(x0=args.x0, target=args.target, steps=args.steps, plant=args.plant, mu=args.mu,
                     kappa=args.kappa, horizon=args.horizon, escape_horizon=args.escape_horizon, solver=args.solver,
                     codegen=args.codegen, predict_obstacles=predict)
    try:
        if args.scene:
            if args.config or args.target:
                raise NmpcError("--scene names its config and its targets: drop --config and --target")
            scenario = scene_scenario(load_scene(args.scene), **overrides)
        else:
            scenario = load_scenario(args.config, **overrides)
        run, summary = simulate(scenario)
    except NmpcError as exc:
        print(f"simulate: error: {exc}", file=sys.stderr)
        return 2
    if args.json:
        out = run.to_json()
        out["summary"] = summary
        out["config"] = str(scenario.config_path)
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(out))
    mx = f" max|x1x2|={summary['max_abs_x1x2']:.4f}" if "max_abs_x1x2" in summary and not scenario.scene else ""
    if scenario.scene is None and scenario.settings.keep_in:
        mx += f" keep-in penetration {summary['max_penetration_keep_in']:.1e}"
    if scenario.scene is not None:
        clear = ", ".join(f"{k} {'-' if v is None else format(v, '.4f')}" for k, v in summary["min_clearance"].items())
        gap = summary["between_samples"]["min_clearance_obstacles"]
        mx = (f" predict_obstacles={'on' if summary['predict_obstacles'] else 'off'} min clearance: {clear}"
              f" (between samples {'-' if gap is None else format(gap, '.4f')});")
    print(f"simulate: {summary['steps']} steps, plant={scenario.plant}, mu={scenario.settings.mu:g}, "
          f"solver={scenario.settings.solver}: "
          f"settled at step {summary['settling_step']}{mx} final error {summary['final_error']:.2e} "
          f"solve median {summary['solve_ms_median']:.1f} ms max {summary['solve_ms_max']:.1f} ms "
          f"fallbacks {summary['fallbacks']}")
    return 0
