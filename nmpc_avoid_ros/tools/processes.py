"""Child processes (nodes, tools, a Dask scheduler and workers) for the demo and the tests: own
process group, stopped by PID."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

#: s a finished loop's nodes keep running before they are stopped: the recorder, a process of its own,
#: may not have taken the loop's last messages yet, and they are lost once their publisher exits
#: (measured: a fresh-clone CI run on 2 loaded cores recorded 37 of 51 lockstep states; the loop's
#: last 14 samples took 4 ms and the plant was stopped at once)
RECORDER_SETTLE = 1.0


def settle(spin_once: Callable[[], None], seconds: float = RECORDER_SETTLE) -> None:
    """Keep spinning the caller's executor for `seconds` (see RECORDER_SETTLE) before the nodes are stopped."""
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        spin_once()


def isolated_env(domain_id: int, log_dir: Path) -> dict[str, str]:
    """Environment of child nodes: own ROS domain, localhost discovery only, logs in log_dir, unbuffered output."""
    env = dict(os.environ)
    env.update(ROS_DOMAIN_ID=str(domain_id), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", ROS_LOG_DIR=str(log_dir),
               PYTHONUNBUFFERED="1")
    return env


class NodeProcess:
    """`<program> <command> ...` in its own process group, output to a log file; the program is
    `python -m nmpc_avoid_ros` unless given (e.g. the `dask` command line)."""

    def __init__(self, command: str, args: list[str], env: dict[str, str], log_dir: Path,
                 preexec_fn: Callable[[], None] | None = None, program: list[str] | None = None) -> None:
        log_dir.mkdir(parents=True, exist_ok=True)
        self.command = command
        self.log_path = log_dir / f"{command}-{time.monotonic_ns()}.log"
        self._log = open(self.log_path, "w")  # noqa: SIM115 - closed in stop()
        program = program or [sys.executable, "-m", "nmpc_avoid_ros"]
        self.proc = subprocess.Popen([*program, command, *args], env=env,
                                     stdout=self._log, stderr=subprocess.STDOUT, start_new_session=True,
                                     preexec_fn=preexec_fn)

    @property
    def pid(self) -> int:
        return self.proc.pid

    def alive(self) -> bool:
        return self.proc.poll() is None

    def send(self, sig: int) -> None:
        """Send sig to this child's own process group (never to anything else)."""
        if self.alive():
            os.killpg(self.proc.pid, sig)

    def stop(self, sig: int = signal.SIGINT, timeout: float = 30.0) -> int:
        """Signal the group and wait; SIGKILL the group if it does not exit in time. Returns the exit code."""
        try:
            self.send(sig)
            return self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            os.killpg(self.proc.pid, signal.SIGKILL)
            return self.proc.wait(5)
        finally:
            self._log.close()

    def output(self) -> str:
        """Everything the process printed so far (also after stop)."""
        if not self._log.closed:
            self._log.flush()
        return self.log_path.read_text()
