"""`demo`: the paper's example through ROS 2 topics, with and without avoidance -> DIR.

    python -m nmpc_avoid_ros demo --out out [--lockstep] [--config FILE] [--steps 50]
    python -m nmpc_avoid_ros demo --scene config/scenes/crossing_walker.yaml --out out/walker \
        [--lockstep [--max-solve-time 30]]   (tools/scene_demo.py; --lockstep: every node on the plant's
        simulated time, so the encounter does not depend on the controller's speed)

Starts plant and controller as separate processes for each run, publishes the target and the
(empty) obstacle set on their topics, collects what the nodes publish, and writes
a bag per run (`with_avoidance.mcap`, `without_avoidance.mcap`), then analyses the bags into
`metrics.json`, `phase_portrait.png`, `time_series.png`, next to the offline reference: the same
loop offline, on the same plant (the lockstep plant's euler step, or in real time the config's
plant integration, continuous in the shipped files) and how far the two differ; one JSON per run
as the demo saw it.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from ..core.config.settings import default_config_path, load_params_file
from ..core.errors import NmpcError
from ..core.loop.closed_loop import ClosedLoopRun, run_closed_loop
from ..core.loop.metrics import max_abs_product, outputs, tracking
from ..core.sample.controller import NmpcController
from ..core.sample.status import StepStatus
from ..evaluation.counterfactual import PlantChoice
from .analyze import analyze
from .processes import NodeProcess, count_messages, recorder_counts, settle
from .simulate import Scenario, load_scenario, summarize

RUNS = (("with_avoidance", None), ("without_avoidance", 0.0))
#: the lockstep plant's integration (the paper's Euler loop, exactly the offline one)
LOCKSTEP_INTEGRATION = "euler"
#: s the demo waits at most for the recorder to hold the plant's and the controller's parameters
PARAMETERS_TIMEOUT = 10.0
#: the recorder subscribes to these at once (before their publishers appear), so no sample is missed
RECORDED_TYPES = ["state=std_msgs/msg/Float64MultiArray", "command=std_msgs/msg/Float64MultiArray",
                  "target=std_msgs/msg/Float64MultiArray", "obstacles=visualization_msgs/msg/MarkerArray",
                  "/diagnostics=diagnostic_msgs/msg/DiagnosticArray", "controller/prediction=nav_msgs/msg/Path",
                  "controller/certificate=std_msgs/msg/Float64MultiArray", "/clock=rosgraph_msgs/msg/Clock"]


def _collect_run(config: Path, mu: float | None, steps: int, lockstep: bool, env: dict[str, str], log_dir: Path,
                 timeout: float, bag: Path) -> dict:
    """One closed loop through DDS, recorded into `bag`; returns x [K+1, n], u [K, m], y_a, solve times, statuses."""
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from std_msgs.msg import Float64MultiArray
    from visualization_msgs.msg import MarkerArray

    from ..nodes.recorder import get_message
    from ..ros.markers import delete_all_marker
    from ..ros.parameters import LATCHED_QOS

    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node("demo", context=context)
    executor = rclpy.executors.SingleThreadedExecutor(context=context)
    executor.add_node(node)
    states: list[list[float]] = []
    samples: list[dict[str, str]] = []

    def on_diagnostics(msg: DiagnosticArray) -> None:
        for status in msg.status:
            values = {kv.key: kv.value for kv in status.values}
            if "solve_time_ms" in values and status.name.startswith(node.get_namespace().rstrip("/") + "/controller"):
                samples.append(values)

    # every recorded topic but the latched inputs, counted: in lockstep the recorder must hold as many
    # before the nodes stop (settle)
    streams = dict(entry.split("=") for entry in RECORDED_TYPES)
    heard = count_messages(node, {topic: get_message(type_name) for topic, type_name in streams.items()
                                  if topic not in ("target", "obstacles")},
                           on={"state": lambda m: states.append(list(m.data)), "/diagnostics": on_diagnostics})
    recorded = recorder_counts(node)
    target_pub = node.create_publisher(Float64MultiArray, "target", LATCHED_QOS)
    obstacles_pub = node.create_publisher(MarkerArray, "obstacles", LATCHED_QOS)
    scenario = load_scenario(config)
    obstacles_pub.publish(MarkerArray(markers=[delete_all_marker()]))  # the run's regions: none besides keep_in

    ros_args = ["--ros-args", "--params-file", str(config)]
    ctrl_args = [*ros_args, "-p", f"lockstep:={str(lockstep).lower()}"]
    if mu is not None:
        ctrl_args += ["-p", f"mu:={mu}"]
    plant_args = [*ros_args, "-p", f"lockstep:={str(lockstep).lower()}"]
    if lockstep:
        # x0 once the controller, this demo and the recorder listen
        # and exactly `steps` samples: the loop then falls quiet, so no clock/state pair is in flight
        # when the nodes are stopped (the bag holds x(0..steps) and a clock tick for each)
        plant_args += ["-p", f"integration:={LOCKSTEP_INTEGRATION}", "-p", "wait_for_subscribers:=3", "-p",
                       f"max_steps:={steps}"]
    recorder_args = ["--ros-args", "-p", f"output:={bag}", "-p", "overwrite:=true", "-p",
                     f"types:={json.dumps(RECORDED_TYPES)}"]
    recorder = NodeProcess("recorder", recorder_args, env, log_dir)
    procs = [recorder, NodeProcess("controller", ctrl_args, env, log_dir)]
    try:
        target_pub.publish(Float64MultiArray(data=[float(v) for v in scenario.target]))
        deadline = time.monotonic() + timeout
        # start the plant once the controller is heard and the recorder listens (as this demo does on
        # each topic), so nothing is missed
        while time.monotonic() < deadline and not (
                node.count_publishers("/diagnostics") >= 1 and node.count_subscribers("/diagnostics") >= 2
                and node.count_subscribers("command") >= 2 and node.count_subscribers("state") >= 2):
            executor.spin_once(timeout_sec=0.05)
            if not recorder.alive():
                raise NmpcError(f"the recorder exited:\n{recorder.output()[-2000:]}")
        procs.append(NodeProcess("plant", plant_args, env, log_dir))
        if lockstep:
            # the controller has also answered x(steps): every node is idle when they are stopped
            needed = lambda: len(states) >= steps + 1 and len(samples) >= steps + 1  # noqa: E731
        else:
            needed = lambda: len(samples) >= steps + 1  # noqa: E731
        while not needed() and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
            for p in procs:
                if not p.alive():
                    raise NmpcError(f"{p.command} exited early:\n{p.output()[-2000:]}")
        if not needed():
            raise NmpcError(f"the loop did not complete {steps} steps in {timeout:.0f} s "
                            f"({len(states)} states, {len(samples)} samples)")
        if lockstep:  # the loop is quiet: the recorder takes its last messages before the nodes stop
            settle(lambda: executor.spin_once(timeout_sec=0.02), heard, recorded)
        # the plant's and the controller's parameters in the bag, so that `replay` reruns it as it ran
        wanted = [f"parameters:{node.get_namespace().rstrip('/')}/{name}" for name in ("plant", "controller")]
        end = time.monotonic() + PARAMETERS_TIMEOUT
        while not all(key in recorded for key in wanted) and time.monotonic() < end:
            executor.spin_once(timeout_sec=0.05)
        if missing := [key.partition(":")[2] for key in wanted if key not in recorded]:
            print(f"demo: warning: the bag lacks the parameters of {', '.join(missing)} (the recorder did not get "
                  f"them in {PARAMETERS_TIMEOUT:g} s); replay will assume them", file=sys.stderr)
    finally:
        codes = [p.stop() for p in reversed(procs)]  # plant, controller, then the recorder finishes the bag
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=context)
    if any(codes):
        raise NmpcError(f"a node did not exit cleanly: exit codes {codes}")
    solved = samples[:steps]
    if lockstep:
        x = np.array(states[: steps + 1])
    else:  # the state each sample solved on, and the one after the last
        x = np.array([json.loads(s["state"]) for s in samples[: steps + 1]])
    return {
        "x": x.tolist(),
        "u": [json.loads(s["command"]) for s in solved],
        "y_a": [json.loads(s["y_a"]) for s in solved],
        "solve_ms": [float(s["solve_time_ms"]) for s in solved],
        "status": [s["status"] for s in solved],
        "sample_time": scenario.settings.sample_time,
    }


def run_demo(out: Path, config: Path, steps: int, lockstep: bool, timeout: float) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ)
    env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")  # keep the demo's traffic on this host
    env.setdefault("ROS_LOG_DIR", str((out / "ros_logs").resolve()))
    os.environ.update({k: env[k] for k in ("ROS_AUTOMATIC_DISCOVERY_RANGE", "ROS_LOG_DIR")})
    scenario = load_scenario(config, steps=steps)
    metrics: dict = {"config": str(config), "mode": "lockstep" if lockstep else "real time", "steps": steps,
                     "target": scenario.target, "runs": {}}
    labels = []
    for name, mu in RUNS:
        run_mu = scenario.settings.mu if mu is None else mu
        print(f"demo: {name} (mu={run_mu:g}), {'lockstep' if lockstep else 'real time'} ...", flush=True)
        data = _collect_run(config, mu, steps, lockstep, env, out / "logs", timeout, (out / f"{name}.mcap").resolve())
        x = np.array(data["x"])
        plant = run_plant(config, lockstep)
        offline, offline_summary = offline_reference(load_scenario(config, steps=steps, mu=run_mu), plant)
        model = scenario.settings.build_model()
        quality = tracking(outputs(model, x, np.array(data["u"])), scenario.target, scenario.settings.sample_time)
        summary = {
            "mu": run_mu,
            "settling_step": quality["settling_step"],
            "final_error": quality["final_error"],
            # the paper's region |x1 x2| <= 2 (simulate's summary has it for van der Pol only)
            **({"max_abs_x1x2": max_abs_product(x)} if "max_abs_x1x2" in offline_summary else {}),
            "solve_ms_median": float(np.median(data["solve_ms"])),
            "solve_ms_max": float(np.max(data["solve_ms"])),
            "fallbacks": sum(StepStatus(s).is_fallback for s in data["status"]),
            "offline_reference": {"plant": plant.integration, **{
                k: v for k, v in offline_summary.items() if k in ("settling_step", "max_abs_x1x2")}},
            # lockstep: the same loop, to rounding; real time: also the loop's timing (the plant's own steps,
            # commands a step late), which `replay --closed-loop` reproduces and this reference does not
            "max_deviation_from_offline": float(np.max(np.abs(x - offline.x[:len(x)]))),
        }
        metrics["runs"][name] = summary
        (out / f"{name}.json").write_text(json.dumps({**data, "summary": summary}))
        labels.append(f"{name.replace('_', ' ')} (mu={run_mu:g})")
        product = f", max|x1x2| = {summary['max_abs_x1x2']:.4f}" if "max_abs_x1x2" in summary else ""
        print(f"demo: {name}: settled at step {summary['settling_step']}{product}, "
              f"solve median {summary['solve_ms_median']:.1f} ms", flush=True)
    # the figures and metrics come from the bags, as a user would make them
    bags = [out / f"{name}.mcap" for name, _ in RUNS]
    report = analyze(bags, out, config, labels=labels, html=out / "report.html")
    metrics["bags"] = report["bags"]
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2))
    return metrics


def run_plant(config: Path, lockstep: bool) -> PlantChoice:
    """The plant node's simulation in the demo: in lockstep LOCKSTEP_INTEGRATION, else the config's plant
    integration (the node's default: continuous), of the config's plant model."""
    plant = load_params_file(config).section("plant")
    integration = LOCKSTEP_INTEGRATION if lockstep else str(plant.get("integration", "continuous"))
    step = float(plant["sample_time"]) if lockstep and "sample_time" in plant else None
    return PlantChoice(integration, str(plant.get("model", "van_der_pol")), f"the demo's plant ({config.name})", step)


def offline_reference(scenario: Scenario, plant: PlantChoice) -> tuple[ClosedLoopRun, dict[str, Any]]:
    """The scenario's loop offline on `plant`, the run's own: (ClosedLoopRun, simulate's summary)."""
    controller = NmpcController(scenario.settings)
    run = run_closed_loop(controller, scenario.x0, scenario.target, scenario.steps, plant.build(scenario.settings))
    return run, summarize(run, scenario.target, controller.model)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="demo", description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=Path("out"), help="output directory")
    ap.add_argument("--config", type=Path, help="ROS 2 params file (default: the shipped van_der_pol.yaml)")
    ap.add_argument("--steps", type=int, default=50)
    ap.add_argument("--lockstep", action="store_true", help="plant advances per command (fast, deterministic); "
                    "with --scene every node on the plant's simulated time")
    ap.add_argument("--timeout", type=float, default=180.0, help="seconds allowed per run")
    ap.add_argument("--scene", type=Path, help="run a scene file instead (real time, or --lockstep; see "
                    "tools/scene_demo.py)")
    ap.add_argument("--predict-obstacles", choices=("on", "off"), help="with --scene: predict moving obstacles")
    ap.add_argument("--obstacle-rate", type=float, default=10.0, help="with --scene: markers per second")
    ap.add_argument("--mu", type=float, help="with --scene: avoidance weight override")
    ap.add_argument("--solver", help="with --scene: solver path override")
    ap.add_argument("--max-solve-time", type=float, help="with --scene: the solver's wall-time budget override, s "
                    "(with --lockstep a large one leaves nothing that depends on the machine's speed)")
    ap.add_argument("--estimate-velocity", action="store_true",
                    help="with --scene: markers without velocity, the controller estimates it from their stamps")
    args = ap.parse_args(argv)
    if args.scene:
        return _scene_main(args)
    started = time.time()
    try:
        run_demo(args.out, args.config or default_config_path(), args.steps, args.lockstep, args.timeout)
    except NmpcError as exc:
        print(f"demo: error: {exc}", file=sys.stderr)
        return 1
    print(f"demo: wrote {', '.join(written_since(Path(args.out), started))} in {args.out}/")
    return 0


def written_since(folder: Path, started: float) -> list[str]:
    """The names of the files in `folder` written since `started` (time.time() s), sorted."""
    return sorted(f.name for f in folder.iterdir() if f.is_file() and f.stat().st_mtime >= started - 1.0)


def _scene_main(args: argparse.Namespace) -> int:
    from .scene_demo import run_scene_demo

    if args.config:
        print("demo: error: --scene names its config: drop --config", file=sys.stderr)
        return 2
    predict = None if args.predict_obstacles is None else args.predict_obstacles == "on"
    overrides = {"mu": args.mu, "solver": args.solver, "max_solve_time": args.max_solve_time}
    try:
        report = run_scene_demo(args.scene, args.out, predict, max(args.timeout, 60.0), args.obstacle_rate,
                                not args.estimate_velocity, overrides, args.lockstep)
    except NmpcError as exc:
        print(f"demo: error: {exc}", file=sys.stderr)
        return 1
    print(f"demo: {args.scene}: {scene_summary(report)}; wrote {args.out}/scene.mcap, metrics.json, "
          "phase_portrait.png, time_series.png")
    return 0


def scene_summary(report: dict) -> str:
    """One line on a scene demo's bag (run_scene_demo's report): clearance and penetration of every recorded
    plant state, not only the sampled ones, and the solve time."""
    (bag,) = report["bags"]
    truth = bag["clearance"]["recorded_states"]
    clearance = truth["min_clearance_obstacles"]
    return (f"obstacle clearance {'n/a' if clearance is None else format(clearance, '.4g')} "
            f"(penetration {truth['max_penetration_obstacles']:.4g}; keep-in {truth['max_penetration_keep_in']:.4g}), "
            f"solve median {bag['solve_ms']['median']:.1f} ms")
