"""The controller node through real DDS: latency per sample and start-up with a cold/warm cache.

A probe node in this process plays the plant (the paper's Euler map): it publishes a state,
waits for the command, integrates one sample and publishes the next state. Measured:

- `step_latency_ms`: inside the node, from the start of the solve to the command published
  (the node's own diagnostics, one value per sample);
- `round_trip_ms`: at the probe, from publishing the state to its Python callback of the command (two DDS
  hops plus the node's work plus the probe's own executor: an upper bound of "state received -> command
  published");
- `dds_round_trip_ms`: from the state's publication (the probe's system clock just before `publish`) to the
  command's arrival at the probe, as its middleware stamped the reception (`received_timestamp`): state
  publication to command arrival at an outside subscriber, without the probe's executor;
- `startup_s`: from starting the node's process to its first command (imports, DDS discovery,
  the solver build and the first, cold-start solve), with an empty solver cache (cold: generate
  and compile) and again with the cache it left (warm); `ready_s`: from starting the process
  to the node's "controller ready" line (imports, parameters, solver build); `build_s`: the
  solver build alone. Both from the node's diagnostics (solver_build_s, ready_time), else its log.

The graph is isolated: its own ROS_DOMAIN_ID, localhost discovery, logs in a temp folder; the
node runs in its own process group and is stopped by PID.
"""

from __future__ import annotations

import os
import re
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from ..core.config.settings import ControllerSettings, default_config_path, load_params_file
from ..tools.processes import NodeProcess, isolated_env

#: node parameters of the measured controller: the fast path, compiled, solving on each state
NODE_PARAMETERS = {"solver": "sqp", "codegen": "true", "lockstep": "true", "max_ellipses": "0",
                   "max_polygons": "0", "ellipse_tiers": "[]", "target": "[5.0]"}


def _stats(values: list[float]) -> dict[str, float]:
    arr = np.asarray(values, float)
    if arr.size == 0:
        return {"count": 0}
    return {"count": int(arr.size), "median": float(np.median(arr)), "p90": float(np.percentile(arr, 90)),
            "p99": float(np.percentile(arr, 99)), "max": float(arr.max())}


def measure_node(samples: int = 300, progress: Callable[[str], None] = print, domain: int | None = None,
                 timeout: float = 120.0, config: Path | None = None, parameters: dict[str, str] | None = None,
                 starts: tuple[str, ...] = ("cold", "warm"), pause: float = 0.0) -> dict[str, Any]:
    """Start the controller (cold, then warm cache); returns latency and start-up statistics of the last start.

    config: the params file (default: the paper's); parameters: node parameters over it (default
    NODE_PARAMETERS); starts: "cold" uses an empty cache folder, "warm" the one the cold start left (or, alone,
    the user's cache: its libraries already compiled); pause: s the probe waits after each command before it
    publishes the next state (a controller that prepares the next sample after its command needs that time)."""
    domain = domain if domain is not None else 150 + os.getpid() % 60
    os.environ.update(ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    with tempfile.TemporaryDirectory(prefix="nmpc_bench_") as tmp:
        tmp_path = Path(tmp)
        os.environ.setdefault("ROS_LOG_DIR", str(tmp_path / "ros_logs"))
        cache = tmp_path / "cache"
        import rclpy

        context = rclpy.Context()
        rclpy.init(context=context, domain_id=domain)
        try:
            probe = _PlantProbe(context)
            runs = {}
            user_cache = starts == ("warm",)
            for label in starts:
                runs[label] = _one_start(probe, label, None if user_cache else cache, domain, tmp_path,
                                         samples if label == starts[-1] else 20, timeout, progress,
                                         config or default_config_path(), parameters or NODE_PARAMETERS, pause)
        finally:
            probe.close()
            rclpy.try_shutdown(context=context)
    warm = runs[starts[-1]]
    return {"parameters": parameters or NODE_PARAMETERS, "startup_s": {k: v["startup_s"] for k, v in runs.items()},
            "build_s": {k: v["build_s"] for k, v in runs.items()},
            "ready_s": {k: v["ready_s"] for k, v in runs.items()},
            "step_latency_ms": _stats(warm["step_latency_ms"]), "round_trip_ms": _stats(warm["round_trip_ms"]),
            "dds_round_trip_ms": _stats(warm["dds_round_trip_ms"]),
            "missed_samples": warm["missed"], "samples": warm["samples"]}


def measure_echo(samples: int = 200, progress: Callable[[str], None] = print, domain: int | None = None,
                 timeout: float = 30.0) -> dict[str, Any]:
    """The same round trips through bench/echo.py's node, which answers each state at once: the floor of rclpy's
    own path on this machine (two DDS hops, one executor wake-up, one publish)."""
    domain = domain if domain is not None else 150 + (os.getpid() + 1) % 60
    os.environ.update(ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    with tempfile.TemporaryDirectory(prefix="nmpc_bench_echo_") as tmp:
        tmp_path = Path(tmp)
        os.environ.setdefault("ROS_LOG_DIR", str(tmp_path / "ros_logs"))
        import rclpy

        context = rclpy.Context()
        rclpy.init(context=context, domain_id=domain)
        probe = _PlantProbe(context)
        proc = NodeProcess("nmpc_avoid_ros.bench.echo", [], isolated_env(domain, tmp_path / "ros_logs"),
                           tmp_path / "logs", program=[sys.executable, "-m"])
        try:
            started = time.perf_counter()
            while not probe.wait_command(1, 0.05):
                probe.publish(np.zeros(1))
                if not proc.alive() or time.perf_counter() - started > timeout:
                    raise RuntimeError(f"the echo node gave no answer:\n{proc.output()[-2000:]}")
            _drain(probe, 1.0)
            round_trips, dds_round_trips = [], []
            for _ in range(samples):
                _round_trip(probe, np.zeros(1), round_trips, dds_round_trips)
                _idle(probe, 0.01)
        finally:
            proc.stop()
            probe.close()
            rclpy.try_shutdown(context=context)
    result = {"round_trip_ms": _stats(round_trips), "dds_round_trip_ms": _stats(dds_round_trips)}
    progress(f"echo node: {result}")
    return result


class _PlantProbe:
    """Publishes states, receives commands and the controller's diagnostics."""

    def __init__(self, context) -> None:
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from std_msgs.msg import Float64MultiArray

        from ..ros.parameters import STREAM_QOS

        self.node = rclpy.create_node("bench_plant_probe", context=context)
        self.executor = rclpy.executors.SingleThreadedExecutor(context=context)
        self.executor.add_node(self.node)
        self.msg_type = Float64MultiArray
        self.state_pub = self.node.create_publisher(Float64MultiArray, "state", STREAM_QOS)
        #: (perf_counter at the callback, the middleware's reception stamp in system-clock ns, the command)
        self.commands: list[tuple[float, int, np.ndarray]] = []
        self.latencies: list[float] = []
        #: the node's start-up values from its diagnostics (solver_build_s, ready_time); empty from an older node
        self.startup: dict[str, float] = {}
        self.node.create_subscription(Float64MultiArray, "command", self._on_command, STREAM_QOS)
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diagnostics, STREAM_QOS)

    def _on_command(self, msg, info: dict) -> None:
        """Two parameters, so that rclpy hands over the message info (its reception stamp)."""
        self.commands.append((time.perf_counter(), int(info.get("received_timestamp", 0)), np.array(msg.data)))

    def _on_diagnostics(self, msg) -> None:
        for status in msg.status:
            values = {kv.key: kv.value for kv in status.values}
            if "step_latency_ms" in values and values.get("status") not in (None, ""):
                self.latencies.append(float(values["step_latency_ms"]))
            self.startup.update({k: float(values[k]) for k in ("solver_build_s", "ready_time") if k in values})

    def publish(self, x: np.ndarray) -> tuple[float, int]:
        """Publish the state x; (perf_counter, system clock ns) just before."""
        msg = self.msg_type()
        msg.data = [float(v) for v in x]
        sent, sent_ns = time.perf_counter(), time.time_ns()
        self.state_pub.publish(msg)
        return sent, sent_ns

    def wait_command(self, count: int, timeout: float) -> bool:
        end = time.monotonic() + timeout
        while len(self.commands) < count and time.monotonic() < end:
            self.executor.spin_once(timeout_sec=0.001)
        return len(self.commands) >= count

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()


def _one_start(probe: _PlantProbe, label: str, cache: Path | None, domain: int, tmp: Path, samples: int,
               timeout: float, progress: Callable[[str], None], config: Path, parameters: dict[str, str],
               pause: float) -> dict[str, Any]:
    """Start the node, time its first command, then run `samples` lockstep samples."""
    args = ["--ros-args", "--params-file", str(config)] + ([] if cache is None else ["-p", f"cache_dir:={cache}"])
    for key, value in parameters.items():
        args += ["-p", f"{key}:={value}"]
    # the plant: the config's own prediction model, so that the controller's prediction holds
    settings = ControllerSettings.from_params({**load_params_file(config).section("controller"), **{
        k: v for k, v in parameters.items() if k in ("model", "discretization", "integration_steps")}})
    model = settings.build_model()
    step = model.discrete(settings.sample_time, settings.discretization, settings.integration_steps)
    x = np.array([-5.0, 0.0])
    started = time.perf_counter()
    spawned = time.time()
    probe.startup.clear()  # this node's start-up only
    proc = NodeProcess("controller", args, isolated_env(domain, tmp / "ros_logs"), tmp / "logs")
    try:
        # re-send x0 until the first command: discovery and the solver build happen meanwhile
        first = None
        while first is None:
            if not proc.alive():
                raise RuntimeError(f"controller exited during start-up:\n{proc.output()[-2000:]}")
            if time.perf_counter() - started > timeout:
                raise RuntimeError(f"controller gave no command within {timeout} s")
            probe.publish(x)
            if probe.wait_command(1, 0.05):
                first = probe.commands[0][0] - started
        _drain(probe, 1.0)  # the answers to the repeated x0 messages (and the node's log is flushed)
        build_s, ready = _startup(probe, proc.output())
        ready = None if ready is None else ready - spawned
        progress(f"node start-up ({label} cache): solver built in {build_s} s, ready after {ready} s, "
                 f"{first:.2f} s to the first command")
        round_trips, dds_round_trips, missed = [], [], 0
        x = np.array([-5.0, 0.0])
        for k in range(samples):
            if k % 50 == 0:
                x = np.array([-5.0, 0.0])  # restart the paper run: a new transient every 50 samples
            u = _round_trip(probe, x, round_trips, dds_round_trips)
            if u is None:
                missed += 1
                continue
            x = np.asarray(step(x, u)).ravel()
            if pause > 0:
                _idle(probe, pause)
        probe.executor.spin_once(timeout_sec=0.2)
        latencies = list(probe.latencies[-len(round_trips):]) if round_trips else []
        return {"startup_s": round(first, 3), "build_s": None if build_s is None else round(build_s, 3),
                "ready_s": None if ready is None else round(ready, 3), "round_trip_ms": round_trips,
                "dds_round_trip_ms": dds_round_trips,
                "step_latency_ms": latencies,
                "missed": missed, "samples": samples}
    finally:
        proc.stop()
        _drain(probe, 0.5)  # nothing of this node may count for the next start


def _round_trip(probe: _PlantProbe, x: np.ndarray, round_trips: list[float], dds_round_trips: list[float],
                timeout: float = 0.5) -> np.ndarray | None:
    """Publish the state x and wait for the command; its round trip (ms) to the probe's callback is appended to
    `round_trips`, to its reception stamp to `dds_round_trips`. Returns the command, None if none came in time."""
    count = len(probe.commands) + 1
    sent, sent_ns = probe.publish(x)
    if not probe.wait_command(count, timeout):
        return None
    received, received_ns, u = probe.commands[-1]
    round_trips.append((received - sent) * 1e3)
    if received_ns:
        dds_round_trips.append((received_ns - sent_ns) * 1e-6)
    return u


def _startup(probe: _PlantProbe, log: str) -> tuple[float | None, float | None]:
    """(solver build s, wall-clock time.time() of "controller ready") from the node's diagnostics; from its
    log lines ("solver built in X s", the stamp of "controller ready") for a node that does not publish them."""
    build_s, ready = probe.startup.get("solver_build_s"), probe.startup.get("ready_time")
    if build_s is None:
        built = re.search(r"solver built in ([0-9.]+) s", log)
        build_s = float(built.group(1)) if built else None
    if ready is None:
        stamp = re.search(r"\[(\d+\.\d+)\] \[[^\]]*\]: controller ready", log)
        ready = float(stamp.group(1)) if stamp else None
    return build_s, ready


def _idle(probe: _PlantProbe, seconds: float) -> None:
    """Spin for `seconds`, keeping what arrives."""
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        probe.executor.spin_once(timeout_sec=0.01)


def _drain(probe: _PlantProbe, seconds: float) -> None:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        probe.executor.spin_once(timeout_sec=0.01)
    probe.commands.clear()
    probe.latencies.clear()
