"""`python -m nmpc_avoid_ros bench [--quick] --json OUT`: every solver path and its peers, one process.

Variants run interleaved sample by sample (variant A's sample k, then B's sample k, ...), so a
burst of load on the shared machine hits every variant alike. Building a variant is not timed;
`solve_ms` is the wall time of the solver call alone (do-mpc: `make_step`). Scenarios:

- `paper/<mu>/<plant>`: the paper's example, x0 = [-5, 0], y_t = 5, 50 samples, the shipped
  config with no obstacle slots (the paper's problem exactly: the two keep-in regions).
- `vdp_4_ellipses`: the paper's run (N = 5) among 4 ellipses, one across the steady states on the way.
- `shipped/vdp_4_ellipses`, `shipped/robot_4_ellipses`, `shipped/bicycle_4_ellipses`: the same van der
  Pol run, the mobile robot and the car-like robot among 4 ellipses, with the shipped configs exactly as they
  are (region capacity, tiers): what a user of each solver path gets.
- `scaling/N=<N>`: the mobile robot (config/mobile_robot.yaml) among 4 ellipses, N = 5..100.
- `moving_obstacle`: the mobile robot at N = 20 while an ellipse moves every sample (the
  obstacle set changes every sample; no variant may rebuild).
- `crossing_walker`: the shipped scene config/scenes/crossing_walker.yaml at N = 20, the walker
  given with its velocity every sample; our paths predict it (`predict_obstacles`), and their
  `_no_prediction` twins (run in this scenario only) solve the same scene with it off.

Then, unless --no-node: the controller node's latency (state received -> command published)
through DDS, and its start-up time with a cold and a warm solver cache.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..core.config.settings import ControllerSettings, default_config_path, load_params_file
from ..core.errors import NmpcError
from ..core.loop.closed_loop import ClosedLoop, Stepper, Trajectory, make_plant
from ..core.loop.metrics import max_abs_product, outputs, penetration, time_stats, tracking
from ..core.loop.scene import load_scene
from ..core.problem.models import Model
from ..core.problem.regions import Ellipse, Region
from .variants import OursStepper, Sample

#: the reference all quality figures are compared with: the paper's formulation as written
REFERENCE = "opti_ipopt_paper"


def ours(solver: str, codegen: bool = True, **changes: Any) -> Callable[[ControllerSettings, Model], Stepper]:
    """Factory of our controller on a solver path (codegen on: the compiled, cached oracles)."""
    def make(settings: ControllerSettings, model: Model) -> Stepper:
        return OursStepper(settings.replace(solver=solver, codegen=codegen, **changes), model)
    return make


def variant_factories() -> dict[str, Callable[[ControllerSettings, Model], Stepper]]:
    """Every benchmarked variant by name (peers imported lazily: do-mpc is slow to import)."""
    from .peers import PEERS

    return {
        REFERENCE: PEERS["opti_ipopt_paper"],
        # the reference IPOPT path as the configs shipped it before the fast path: every escape guess in
        # one sample, no ellipse tiers (core/nlp/tiers.py)
        "ours_ipopt": ours("ipopt", codegen=False, **IPOPT_REFERENCE),
        "ours_fatrop": ours("fatrop"),
        "ours_ipopt_no_prediction": ours("ipopt", codegen=False, predict_obstacles=False, **IPOPT_REFERENCE),
        "ours_fatrop_no_prediction": ours("fatrop", predict_obstacles=False),
        "ours_sqp": ours("sqp"),
        "ours_sqp_hpipm": ours("sqp_hpipm"),
        "ours_sqp_rt": ours("sqp", max_iterations=REAL_TIME_ITERATIONS),
        "do_mpc": PEERS["do_mpc"],
        "do_mpc_unshifted": PEERS["do_mpc_unshifted"],
    }


#: what the reference IPOPT variants change in the shipped configs (the fast path's own settings)
IPOPT_REFERENCE = {"escape_guesses_per_sample": 0, "ellipse_tiers": ()}

#: the real-time variant's fixed work budget: SQP iterations per sample
REAL_TIME_ITERATIONS = 5


@dataclass
class Scenario:
    """One closed-loop case: settings, plant, start, target, and the regions of each sample."""

    name: str
    settings: ControllerSettings
    model: Model
    x0: np.ndarray
    target: np.ndarray
    steps: int
    plant: str
    regions: Callable[[int], Sequence[Region] | None] | None = None
    skip: frozenset[str] = field(default_factory=frozenset)


def _config(name: str) -> dict[str, Any]:
    path = default_config_path().parent / name
    return load_params_file(path).section("controller")


def paper_scenarios(steps: int) -> list[Scenario]:
    """The four paper runs (mu 0 / 1e8, Euler / continuous plant)."""
    base = with_capacity(ControllerSettings.from_params(_config("van_der_pol.yaml")), 0)
    model = base.build_model()
    return [Scenario(f"paper/mu={mu:g}/{plant}", base.replace(mu=mu), model, np.array([-5.0, 0.0]),
                     np.array([5.0]), steps, plant)
            for mu in (0.0, 1e8) for plant in ("euler", "continuous")]


ROBOT_ELLIPSES = (Ellipse((-4.0, -3.5), (1.2, 0.8), 0.3, "output"), Ellipse((0.0, 0.5), (1.0, 1.4), 0.0, "output"),
                  Ellipse((3.5, 2.0), (0.9, 0.9), 0.0, "output"), Ellipse((5.5, 5.0), (0.8, 1.2), -0.4, "output"))


#: four ellipses on the paper's way from x1 = -5 to 5 (one across x2 = 0 at x1 = 2.95-3.45, so the
#: steady states there are inside it and the loop needs the local-minimum escape to pass)
VDP_ELLIPSES = (Ellipse((-3.0, 0.75), (0.6, 0.25), 0.2), Ellipse((-0.5, 1.5), (0.8, 0.35), 0.0),
                Ellipse((1.5, -0.9), (0.7, 0.5), 0.4), Ellipse((3.2, -0.5), (0.6, 0.55), 0.0))


def vdp_ellipse_scenario(steps: int) -> Scenario:
    """The paper's van der Pol run (N = 5, mu = 1e8, Euler plant) among the 4 VDP_ELLIPSES."""
    s = with_capacity(ControllerSettings.from_params(_config("van_der_pol.yaml")), 4)
    return Scenario("vdp_4_ellipses", s, s.build_model(), np.array([-5.0, 0.0]), np.array([5.0]), steps,
                    "euler", lambda k: VDP_ELLIPSES if k == 0 else None)


#: four ellipses on the car-like robot's way from config/bicycle.yaml's start (-4, -3) to its goal (3, 2)
BICYCLE_ELLIPSES = (Ellipse((-2.0, -1.6), (0.6, 0.4), 0.3, "output"), Ellipse((0.0, 0.1), (0.5, 0.7), 0.0, "output"),
                    Ellipse((1.8, 0.7), (0.4, 0.4), 0.0, "output"), Ellipse((1.4, 2.7), (0.4, 0.6), -0.4, "output"))


def shipped_scenarios(steps: int) -> list[Scenario]:
    """The shipped configs as they are (their region capacities and ellipse tiers) among 4 ellipses; the car-like
    robot (config/bicycle.yaml, its own scenario's start and goal pose) for twice the samples, to come to rest."""
    vdp = ControllerSettings.from_params(_config("van_der_pol.yaml"))
    robot = ControllerSettings.from_params(_config("mobile_robot.yaml"))
    bicycle = ControllerSettings.from_params(_config("bicycle.yaml"))
    return [Scenario("shipped/vdp_4_ellipses", vdp, vdp.build_model(), np.array([-5.0, 0.0]), np.array([5.0]),
                     steps, "euler", lambda k: VDP_ELLIPSES if k == 0 else None),
            Scenario("shipped/robot_4_ellipses", robot, robot.build_model(), np.array([-8.0, -6.0, 0.0, 0.0]),
                     np.array([8.0, 6.0]), steps, "continuous", lambda k: ROBOT_ELLIPSES if k == 0 else None),
            Scenario("shipped/bicycle_4_ellipses", bicycle, bicycle.build_model(), np.array([-4.0, -3.0, 0.0]),
                     np.array([3.0, 2.0, 0.0]), 2 * steps, "continuous",
                     lambda k: BICYCLE_ELLIPSES if k == 0 else None)]


def robot_settings(horizon: int) -> ControllerSettings:
    """The mobile robot's config with room for exactly 4 ellipses and no polygons."""
    return with_capacity(ControllerSettings.from_params(_config("mobile_robot.yaml")).replace(horizon=horizon), 4)


def with_capacity(settings: ControllerSettings, ellipses: int) -> ControllerSettings:
    """Room for exactly `ellipses` ellipses and no polygons (the ellipse tiers below it kept)."""
    return settings.replace(max_ellipses=ellipses, max_polygons=0,
                            ellipse_tiers=tuple(k for k in settings.ellipse_tiers if k < ellipses))


def scaling_scenarios(horizons: Sequence[int], steps: int) -> list[Scenario]:
    """The mobile robot from (-8, -6) to (8, 6) among 4 ellipses for each horizon N."""
    out = []
    for N in horizons:
        s = robot_settings(N)
        out.append(Scenario(f"scaling/N={N}", s, s.build_model(), np.array([-8.0, -6.0, 0.0, 0.0]),
                            np.array([8.0, 6.0]), steps, "continuous",
                            lambda k: ROBOT_ELLIPSES if k == 0 else None))
    return out


def moving_obstacle_scenario(steps: int) -> Scenario:
    """N = 20; an ellipse sweeps across the path, moved every sample (a new region set each sample)."""
    s = robot_settings(20)

    def regions(k: int) -> list[Region]:
        t = k * s.sample_time
        moving = Ellipse((2.0 * math.cos(0.4 * t), -1.0 + 0.25 * t), (0.8, 0.6), 0.2 * t, "output")
        return [*ROBOT_ELLIPSES[:3], moving]

    return Scenario("moving_obstacle", s, s.build_model(), np.array([-8.0, -6.0, 0.0, 0.0]),
                    np.array([8.0, 6.0]), steps, "continuous", regions)


#: the variants that switch prediction off: run in the prediction scenario only
NO_PREDICTION = frozenset({"ours_ipopt_no_prediction", "ours_fatrop_no_prediction"})


def crossing_walker_scenario(steps: int) -> Scenario:
    """The shipped crossing-walker scene at N = 20: the walker where it is, with its velocity, every sample."""
    scene = load_scene(default_config_path().parent / "scenes" / "crossing_walker.yaml")
    s = robot_settings(20)
    return Scenario("crossing_walker", s, s.build_model(), np.array(scene.x0), np.array(scene.target_at(0.0)),
                    steps, scene.plant, lambda k: scene.regions_at(k * s.sample_time))


def start_loop(stepper: Stepper, scenario: Scenario) -> ClosedLoop:
    """The scenario's closed loop for one variant (the one driver, core/loop/closed_loop.py)."""
    s = scenario.settings
    return ClosedLoop(stepper, make_plant(scenario.plant, scenario.model, s), scenario.x0, scenario.target,
                      s.sample_time, scenario.regions)


def quality(scenario: Scenario, run: Trajectory) -> dict[str, Any]:
    """Settling step, final error and the avoidance figure of one run (core/loop/metrics.py)."""
    y = outputs(scenario.model, run.x, run.u)
    track = tracking(y, scenario.target, scenario.settings.sample_time)
    out: dict[str, Any] = {"settling_step": track["settling_step"], "final_error": track["final_error"]}
    if scenario.model.name == "van_der_pol":
        out["max_abs_x1x2"] = max_abs_product(run.x)
    if scenario.model.name != "van_der_pol" or any(run.regions):
        out["max_penetration"] = penetration(scenario.settings, scenario.model, run.x, run.u, run.regions,
                                             y)["max_penetration"]
    return out


def record(name: str, scenario: Scenario, run: Trajectory, build_s: float) -> dict[str, Any]:
    """The JSON record of one variant on one scenario."""
    samples: list[Sample] = run.outcomes
    times = run.solve_time * 1e3
    iters = run.iterations
    sample_ms = scenario.settings.sample_time * 1e3
    return {
        "variant": name,
        "scenario": scenario.name,
        "horizon": scenario.settings.horizon,
        "samples": len(times),
        "build_s": round(build_s, 3),
        "solve_ms": {**time_stats(times, (90, 99)),
                     # sample 0 is a cold start (no previous plan): the tail of the warm samples alone
                     "p99_warm": float(np.percentile(times[1:], 99)) if times.size > 1 else float(times[0]),
                     "max_warm": float(np.max(times[1:])) if times.size > 1 else float(times[0]),
                     "cold_start": float(times[0])},
        # the worst whole step (our controller's bound: sample_budget() + TIME_BOUND_MARGIN; NaN for a peer)
        "step_ms_max": None if any(math.isnan(smp.step_time) for smp in samples) else
        float(np.max([smp.step_time for smp in samples])) * 1e3,
        "iterations": {"median": float(np.median(iters)), "max": int(np.max(iters))},
        "failures": int(sum(smp.failed for smp in samples)),
        "fallbacks": int(sum(smp.fallback for smp in samples)),
        "budget_cut": int(sum(smp.budget_exhausted for smp in samples)),
        "missed_samples": int(np.sum(times > sample_ms)),
        **quality(scenario, run),
    }


def run_scenario(scenario: Scenario, factories: dict[str, Callable], progress: Callable[[str], None]) -> list[dict]:
    """All variants on one scenario, interleaved per sample; records with the reference's quality."""
    loops: dict[str, ClosedLoop] = {}
    builds: dict[str, float] = {}
    for name, factory in factories.items():
        if name in scenario.skip:
            continue
        start = time.perf_counter()
        loops[name] = start_loop(factory(scenario.settings, scenario.model), scenario)
        builds[name] = time.perf_counter() - start
    for _ in range(scenario.steps):
        for loop in loops.values():
            loop.advance()
    records = [record(name, scenario, loop.trajectory(), builds[name]) for name, loop in loops.items()]
    ref = next((r for r in records if r["variant"] == REFERENCE), None)
    for r in records:
        if ref is not None:
            r["reference"] = {k: ref[k] for k in ("settling_step", "final_error", "max_abs_x1x2", "max_penetration")
                              if k in ref}
            r["speedup_vs_reference"] = {"median": ref["solve_ms"]["median"] / r["solve_ms"]["median"],
                                         "max": ref["solve_ms"]["max"] / r["solve_ms"]["max"]}
        progress(f"{scenario.name:24s} {r['variant']:18s} median {r['solve_ms']['median']:8.3f} ms "
                 f"p99 {r['solve_ms']['p99']:8.3f} max {r['solve_ms']['max']:8.3f} settle {r['settling_step']} "
                 f"fail {r['failures']} missed {r['missed_samples']}")
    return records


def machine() -> dict[str, Any]:
    """What the numbers were measured on."""
    import casadi

    info = {"python": platform.python_version(), "platform": platform.platform(), "cpus": os.cpu_count(),
            "casadi": casadi.__version__}
    try:
        info["load_average"] = os.getloadavg()
        info["cpu"] = next((line.split(":", 1)[1].strip() for line in Path("/proc/cpuinfo").read_text().splitlines()
                            if line.startswith("model name")), "unknown")
    except OSError:
        pass
    return info


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="bench", description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="fewer samples and horizons (under 2 minutes)")
    ap.add_argument("--json", type=Path, required=True, help="write the records here")
    ap.add_argument("--variants", help="comma-separated subset of the variants (default: all)")
    ap.add_argument("--scenarios", help="comma-separated name prefixes of the scenarios to run (default: all)")
    ap.add_argument("--no-node", action="store_true", help="skip the controller node's latency and start-up")
    ap.add_argument("--markdown", type=Path, help="also write the tables as markdown here")
    return ap


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    factories = variant_factories()
    if args.variants:
        wanted = args.variants.split(",")
        unknown = sorted(set(wanted) - set(factories))
        if unknown:
            print(f"bench: error: unknown variant(s) {', '.join(unknown)}; known: {', '.join(factories)}",
                  file=sys.stderr)
            return 2
        factories = {k: v for k, v in factories.items() if k in wanted}

    def progress(line: str) -> None:
        print(line, file=sys.stderr, flush=True)

    if args.quick:
        scenarios = [*paper_scenarios(50), vdp_ellipse_scenario(50), *shipped_scenarios(20),
                     *scaling_scenarios((5, 20, 50), 6), moving_obstacle_scenario(10), crossing_walker_scenario(40)]
    else:
        scenarios = [*paper_scenarios(50), vdp_ellipse_scenario(50), *shipped_scenarios(50),
                     *scaling_scenarios((5, 10, 20, 50, 100), 40), moving_obstacle_scenario(60),
                     crossing_walker_scenario(80)]
    if args.scenarios:
        prefixes = tuple(args.scenarios.split(","))
        scenarios = [sc for sc in scenarios if sc.name.startswith(prefixes)]
        if not scenarios:
            print(f"bench: error: no scenario starts with {args.scenarios!r}", file=sys.stderr)
            return 2
    # the Gauss-Newton SQP paths do not converge on the mobile robot from N = 20 on (measured:
    # line-search stalls, 0.1-1.5 s per sample, every sample a fallback): left out there rather
    # than timed out; the quick run also leaves the slow peers out of N >= 50
    sqp_paths = frozenset(name for name in factories if name.startswith("ours_sqp"))
    slow_peers = frozenset({"do_mpc", "do_mpc_unshifted", "ours_ipopt"})
    for sc in scenarios:
        if sc.model.name != "van_der_pol" and sc.settings.horizon >= 20:
            sc.skip = sqp_paths | (slow_peers if args.quick and sc.settings.horizon >= 50 else frozenset())
        if sc.name != "crossing_walker":
            sc.skip |= NO_PREDICTION
    started = time.perf_counter()
    records: list[dict] = []
    try:
        for sc in scenarios:
            records += run_scenario(sc, factories, progress)
        node = None if args.no_node else node_benchmark(quick=args.quick, progress=progress)
    except NmpcError as exc:
        print(f"bench: error: {exc}", file=sys.stderr)
        return 2
    out = {"command": "python -m nmpc_avoid_ros bench " + " ".join(argv if argv is not None else sys.argv[1:]),
           "machine": machine(), "seconds": round(time.perf_counter() - started, 1),
           "records": records, "node": node}
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(out, indent=1))
    if args.markdown:
        args.markdown.parent.mkdir(parents=True, exist_ok=True)
        args.markdown.write_text(markdown(out))
    progress(f"bench: {len(records)} records in {out['seconds']} s -> {args.json}")
    return 0


def node_benchmark(quick: bool, progress: Callable[[str], None]) -> dict[str, Any]:
    """Latency and start-up of the controller node through DDS (see bench/node.py)."""
    from .node import measure_node

    result = measure_node(samples=60 if quick else 300, progress=progress)
    return result


def _fmt(value: Any, digits: int = 3) -> str:
    if value is None:
        return "never"
    if isinstance(value, float):
        return f"{value:.{digits}g}" if abs(value) < 1e4 else f"{value:.3g}"
    return str(value)


def markdown(report: dict[str, Any]) -> str:
    """The records as markdown tables (one per scenario family) plus the node's figures."""
    lines = [f"Command: `{report['command']}` ({report['seconds']} s)", "",
             f"Machine: {report['machine'].get('cpu', '?')}, {report['machine']['cpus']} CPUs, "
             f"Python {report['machine']['python']}, CasADi {report['machine']['casadi']}, "
             f"load average at the end {tuple(round(v, 2) for v in report['machine'].get('load_average', ()))}", ""]
    header = ("| scenario | variant | median ms | p90 | p99 | max | p99 warm | max warm | cold start | iters med/max | "
              "fail | fallback | cut | missed | worst step ms | settle (ref) | quality (ref) | final error | "
              "speed-up median / max |")
    lines += [header, "|" + "---|" * (header.count("|") - 1)]
    for r in report["records"]:
        t = r["solve_ms"]
        quality_key = "max_abs_x1x2" if "max_abs_x1x2" in r else "max_penetration"
        label = r"max\|x1x2\|" if quality_key == "max_abs_x1x2" else "penetration"
        ref = r.get("reference", {})
        speed = r.get("speedup_vs_reference", {})
        worst_step = "-" if r.get("step_ms_max") is None else _fmt(r["step_ms_max"])
        lines.append(
            f"| {r['scenario']} | {r['variant']} | {_fmt(t['median'])} | {_fmt(t['p90'])} | {_fmt(t['p99'])} | "
            f"{_fmt(t['max'])} | {_fmt(t.get('p99_warm'))} | {_fmt(t.get('max_warm'))} | {_fmt(t.get('cold_start'))} | "
            f"{_fmt(r['iterations']['median'])}/{r['iterations']['max']} | "
            f"{r['failures']} | {r['fallbacks']} | {r['budget_cut']} | {r['missed_samples']} | "
            f"{worst_step} | {_fmt(r['settling_step'])} ({_fmt(ref.get('settling_step'))}) | "
            f"{label} {_fmt(r[quality_key], 5)} ({_fmt(ref.get(quality_key), 5)}) | {_fmt(r['final_error'])} | "
            f"{_fmt(speed.get('median'))} / {_fmt(speed.get('max'))} |")
    node = report.get("node")
    if node:
        lines += ["", "Controller node through DDS (parameters: " +
                  ", ".join(f"{k}={v}" for k, v in node["parameters"].items()) + "):", "",
                  "| figure | count | median | p90 | p99 | max |", "|---|---|---|---|---|---|"]
        for key in ("step_latency_ms", "round_trip_ms"):
            st = node[key]
            lines.append(f"| {key} | {st.get('count')} | {_fmt(st.get('median'))} | {_fmt(st.get('p90'))} | "
                         f"{_fmt(st.get('p99'))} | {_fmt(st.get('max'))} |")
        lines += ["", f"Start-up to the first command: cold cache {node['startup_s']['cold']} s, "
                      f"warm cache {node['startup_s']['warm']} s (including DDS discovery); node ready "
                      f"{node['ready_s']['cold']} s cold, {node['ready_s']['warm']} s warm (solver build alone: "
                      f"{node['build_s']['cold']} s cold, {node['build_s']['warm']} s warm); "
                      f"missed samples {node['missed_samples']} of {node['samples']}."]
    return "\n".join(lines) + "\n"
