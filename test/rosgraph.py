"""Helpers for tests that start real nodes: an isolated DDS domain, processes in their own
process group stopped by PID, and an in-process probe node to publish and listen."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rcl_interfaces.srv import GetParameters
from rclpy.node import Node

from nmpc_avoid_ros.ros.parameters import STREAM_QOS
from nmpc_avoid_ros.tools.processes import NodeProcess, isolated_env  # noqa: F401 - NodeProcess re-exported

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "config" / "van_der_pol.yaml"
#: s between repeats of heard_by's request (Probe.heard_by)
REQUEST_RETRY = 2.0


def ros_env(domain_id: int, log_dir: Path) -> dict[str, str]:
    """The package's isolated node environment, with the source tree importable by the children."""
    env = isolated_env(domain_id, log_dir)
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    return env


class Probe:
    """An rclpy context + node in the test process on the test's domain."""

    def __init__(self, domain_id: int, name: str = "probe") -> None:
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=domain_id)
        self.node: Node = rclpy.create_node(name, context=self.context)
        self.executor = rclpy.executors.SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)

    def spin_until(self, done: Callable[[], bool], timeout: float) -> bool:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if done():
                return True
            self.executor.spin_once(timeout_sec=0.02)
        return done()

    def spin_for(self, seconds: float) -> None:
        self.spin_until(lambda: False, seconds)

    def diagnostics_of(self, hardware_id: str = "/controller") -> list[dict[str, str]]:
        """The key-value pairs of every /diagnostics status of `hardware_id` from now on, as the probe spins."""
        heard: list[dict[str, str]] = []
        self.node.create_subscription(
            DiagnosticArray, "/diagnostics",
            lambda m: heard.extend({kv.key: kv.value for kv in s.values} for s in m.status
                                   if s.hardware_id == hardware_id),
            STREAM_QOS)
        return heard

    def heard_by(self, node_name: str, timeout: float) -> bool:
        """True once `node_name` answered a get_parameters request from this probe. Matching is
        asymmetric: our reader seeing a node's writer does not mean that writer sees our reader, so a
        volatile message (a diagnostic) can be lost. A node answers only after it discovered our
        response reader, announced after every reader created before this call on the same ordered,
        reliable discovery channel: its writers then match all those readers too. The answer itself can
        still be dropped: rmw_fastrtps gives up on a response whose reader it has not matched in time
        ("failed to send response (timeout)", seen once in a CI-like run), so the request is repeated
        every REQUEST_RETRY s until one is answered."""
        client = self.node.create_client(GetParameters, f"/{node_name}/get_parameters")
        end = time.monotonic() + timeout
        try:
            if not client.wait_for_service(timeout_sec=timeout):
                return False
            while time.monotonic() < end:
                future = client.call_async(GetParameters.Request(names=[]))
                if self.spin_until(future.done, min(REQUEST_RETRY, max(0.0, end - time.monotonic()))):
                    return True
            return False
        finally:
            self.node.destroy_client(client)

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)


def run_send(env: dict[str, str], *args: str, timeout: float = 60.0) -> tuple[subprocess.CompletedProcess, float]:
    """`python -m nmpc_avoid_ros send ...` in the test's domain: (the finished process, its seconds)."""
    begin = time.monotonic()
    proc = subprocess.run([sys.executable, "-m", "nmpc_avoid_ros", "send", *args], env=env, capture_output=True,
                          text=True, timeout=timeout, start_new_session=True)
    return proc, time.monotonic() - begin
