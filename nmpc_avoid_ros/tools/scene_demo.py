"""`demo --scene FILE`: a scene through ROS 2 between separate processes -> DIR.

    python -m nmpc_avoid_ros demo --scene config/scenes/crossing_walker.yaml --out out/walker \
        [--lockstep] [--max-solve-time S] [--predict-obstacles on|off] [--obstacle-rate 10] [--estimate-velocity]

Writes DIR/params.yaml (the scene's config with its controller overrides and predict_obstacles:
the one file every node and the analysis read), starts the recorder, the controller, the
`obstacles` node (the scene's obstacles as stamped markers) and then the plant from the scene's
x0, publishes the scene's targets at their times, stops after the scene's steps and analyses the
bag (DIR/scene.mcap) into DIR/metrics.json, phase_portrait.png (the obstacles at a few sample
times) and time_series.png. Scene time 0 is the plant's first state.

Real time (default): the continuous plant (a real-time plant integrates, so a scene's `plant:
euler` runs as continuous); how far the robot gets while an obstacle moves depends on how fast
the controller answers (load, a cold start, fallbacks), so two runs differ.

`--lockstep`: the plant advances one sample_time per command (the scene's plant, continuous or
euler) and publishes /clock; controller, obstacles node and recorder run on that simulated time
(`use_sim_time`), so stage times, marker stamps, poses and log times share one clock and the
obstacles move only as the loop advances: the encounter no longer depends on the controller's
speed, and the run follows the offline `simulate --scene` loop (crossing walker: to 1e-9). One
link to the machine's speed is left, the solver's wall-time budget `max_solve_time` (a solve cut
short is a fallback; the robot's cold start hits 0.2 s): `--max-solve-time 30` lifts it, and
repeated runs agree to 1e-12 under any load. The plant stops after `steps` samples (x(0..steps),
all answered). A target change at t > 0 is published as the state before its first sample
k Ts >= t arrives, so it is in force from sample k as offline (it has the controller's solve and
the plant's step to arrive).
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path
from typing import Any

import yaml

from ..core.config.settings import ControllerSettings, load_params_file
from ..core.errors import NmpcError
from ..core.loop.scene import Scene, load_scene
from .analyze import analyze
from .processes import NodeProcess, count_messages, recorder_counts, settle

#: `state` subscribers before the lockstep plant publishes x0: recorder, controller, obstacles, the demo
STATE_LISTENERS = 4
#: the recorder subscribes to these at once (before their publishers appear), so no sample is missed
RECORDED_TYPES = ["state=std_msgs/msg/Float64MultiArray", "command=std_msgs/msg/Float64MultiArray",
                  "target=std_msgs/msg/Float64MultiArray", "obstacles=visualization_msgs/msg/MarkerArray",
                  "/diagnostics=diagnostic_msgs/msg/DiagnosticArray", "controller/prediction=nav_msgs/msg/Path"]


def scene_params(scene: Scene, predict: bool | None, out: Path, overrides: dict[str, Any] | None = None,
                 lockstep: bool = False) -> Path:
    """DIR/params.yaml: the scene's config, its controller overrides, then `overrides` (None values
    skipped), predict_obstacles, and the plant's x0; lockstep: both nodes in lockstep on simulated
    time, the plant with the controller's sample time, the scene's plant and `steps` samples."""
    params = load_params_file(scene.config)
    controller = {**params.section("controller"), **scene.controller,
                  **{k: v for k, v in (overrides or {}).items() if v is not None}}
    if predict is not None:
        controller["predict_obstacles"] = predict
    plant = {**params.section("plant"), "initial_state": [float(v) for v in scene.x0], "integration": "continuous"}
    plant.pop("lockstep", None)
    if lockstep:
        controller.update(lockstep=True, use_sim_time=True)
        # the controller derives a state's time as one of its sample times after the last (nodes/controller.py)
        sample_time = float(controller.get("sample_time", ControllerSettings().sample_time))
        plant.update(lockstep=True, integration=scene.plant, sample_time=sample_time,
                     wait_for_subscribers=STATE_LISTENERS, max_steps=scene.steps)
    data = {name: {"ros__parameters": params.section(name)} for name in params.nodes}
    data["controller"] = {"ros__parameters": controller}
    data["plant"] = {"ros__parameters": plant}
    path = out / "params.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def run_scene_demo(scene_path: Path, out: Path, predict: bool | None = None, timeout: float = 300.0,
                   rate: float = 10.0, explicit_velocity: bool = True, overrides: dict[str, Any] | None = None,
                   lockstep: bool = False) -> dict:
    """Run the scene through DDS (real time, or lockstep on simulated time); returns the analysis
    report (metrics of the bag) with the scene's name."""
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from std_msgs.msg import Float64MultiArray
    from visualization_msgs.msg import MarkerArray

    from ..nodes.recorder import get_message
    from ..ros.parameters import LATCHED_QOS

    scene = load_scene(scene_path)
    out.mkdir(parents=True, exist_ok=True)
    params = scene_params(scene, predict, out, overrides, lockstep)
    sample_time = float(load_params_file(params).section("plant")["sample_time"]) if lockstep else 0.0
    bag = (out / "scene.mcap").resolve()
    env = dict(os.environ)
    env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    env.setdefault("ROS_LOG_DIR", str((out / "ros_logs").resolve()))
    os.environ.update({k: env[k] for k in ("ROS_AUTOMATIC_DISCOVERY_RANGE", "ROS_LOG_DIR")})
    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node("scene_demo", context=context)
    executor = rclpy.executors.SingleThreadedExecutor(context=context)
    executor.add_node(node)
    samples: list[dict[str, str]] = []
    heard = {"obstacles": 0, "state": 0}
    first_state: list[float] = []

    def on_diagnostics(msg: DiagnosticArray) -> None:
        for status in msg.status:
            values = {kv.key: kv.value for kv in status.values}
            if "solve_time_ms" in values:
                samples.append(values)

    def on_state(_msg: Float64MultiArray) -> None:
        heard["state"] += 1
        if not first_state:
            first_state.append(time.monotonic())
        # lockstep: a target of time t goes out as the state before its first sample k Ts >= t arrives
        while lockstep and pending and (heard["state"] - 1) * sample_time >= pending[0][0] - sample_time - 1e-9:
            publish_next_target()

    # the streams the recorder takes from the start, counted: in lockstep it must hold as many before
    # the nodes stop (settle)
    streams = dict(entry.split("=") for entry in RECORDED_TYPES)
    counted = count_messages(node, {topic: get_message(type_name) for topic, type_name in streams.items()
                                    if topic not in ("target", "obstacles")},
                             on={"state": on_state, "/diagnostics": on_diagnostics})
    recorded = recorder_counts(node)

    def on_obstacles(_msg: MarkerArray) -> None:
        heard["obstacles"] += 1

    node.create_subscription(MarkerArray, "obstacles", on_obstacles, LATCHED_QOS)
    target_pub = node.create_publisher(Float64MultiArray, "target", LATCHED_QOS)

    def publish_next_target() -> None:
        """The scene's next target change (`pending`: (t, y) in time order) goes out now."""
        target_pub.publish(Float64MultiArray(data=list(pending.pop(0)[1])))

    logs = out / "logs"
    ros_args = ["--ros-args", "--params-file", str(params)]
    sim_time = ["-p", f"use_sim_time:={str(lockstep).lower()}"]  # lockstep: log times and stamps on the plant's clock
    recorder = NodeProcess("recorder", ["--ros-args", "-p", f"output:={bag}", "-p", "overwrite:=true", "-p",
                                        f"types:={json.dumps(RECORDED_TYPES)}", *sim_time], env, logs)
    procs = [recorder, NodeProcess("controller", ros_args, env, logs),
             NodeProcess("obstacles", ["--ros-args", "-p", f"scene:={Path(scene_path).resolve()}", "-p",
                                       f"rate:={float(rate)}", "-p",
                                       f"explicit_velocity:={str(explicit_velocity).lower()}", *sim_time], env, logs)]
    pending = list(scene.targets)
    try:
        publish_next_target()
        while pending and pending[0][0] <= 1e-12:  # more than one at t = 0: the last is in force, as offline
            publish_next_target()
        deadline = time.monotonic() + timeout

        def ready() -> bool:
            return (node.count_publishers("/diagnostics") >= 1 and node.count_subscribers("/diagnostics") >= 2
                    and node.count_subscribers("command") >= 2 and node.count_subscribers("state") >= 3
                    and heard["obstacles"] > 0)

        while time.monotonic() < deadline and not ready():
            executor.spin_once(timeout_sec=0.05)
            _check_alive(procs)
        procs.append(NodeProcess("plant", ros_args, env, logs))
        # lockstep: x(0..steps) all answered, so the loop is quiet when the nodes are stopped
        needed = scene.steps + 1 if lockstep else scene.steps
        states_needed = needed if lockstep else 0
        while not (len(samples) >= needed and heard["state"] >= states_needed) and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.02)
            _check_alive(procs)
            while not lockstep and pending and first_state and time.monotonic() - first_state[0] >= pending[0][0]:
                publish_next_target()
        if len(samples) < needed:
            raise NmpcError(f"the scene did not complete {needed} samples in {timeout:.0f} s "
                            f"({heard['state']} states, {len(samples)} samples)")
        if lockstep:  # the loop is quiet: the recorder takes its last messages before the nodes stop
            settle(lambda: executor.spin_once(timeout_sec=0.02), counted, recorded)
    finally:
        codes = [p.stop() for p in reversed(procs)]  # plant first; the recorder finishes the bag last
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=context)
    if any(codes):
        names = [p.command for p in reversed(procs)]
        raise NmpcError(f"a node did not exit cleanly: exit codes {dict(zip(names, codes))}")
    label = f"{Path(scene_path).stem} (prediction {'off' if predict is False else 'on'}" \
        f"{', lockstep' if lockstep else ''})"
    report = analyze([bag], out, params, labels=[label], html=out / "report.html")
    report["scene"] = str(scene_path)
    (out / "metrics.json").write_text(json.dumps(report, indent=2))
    return report


def _check_alive(procs: list[NodeProcess]) -> None:
    for p in procs:
        if not p.alive():
            raise NmpcError(f"{p.command} exited early:\n{p.output()[-2000:]}")
