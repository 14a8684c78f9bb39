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

from ..core.errors import NmpcError

#: s a finished loop's nodes wait at most for the recorder to hold every message of it (see settle);
#: it takes them in well under a second; a recorder that falls this far behind is a failure
RECORDER_SETTLE_TIMEOUT = 15.0


def count_messages(node, topics: dict[str, type], on: dict[str, Callable] | None = None) -> dict[str, int]:
    """Subscribe `node` once to each topic (name -> message type; STREAM QoS), pass each message to the
    topic's callback in `on` if any, and count them: {resolved name: messages heard}, growing as the
    caller's executor spins. Subscribe before the publishers start."""
    from ..ros.parameters import STREAM_QOS

    heard: dict[str, int] = {}
    on = on or {}
    for name, msg_type in topics.items():
        resolved = node.resolve_topic_name(name)
        heard[resolved] = 0
        then = on.get(name)

        def on_message(msg, _name=resolved, _then=then) -> None:
            heard[_name] += 1
            if _then is not None:
                _then(msg)

        node.create_subscription(msg_type, resolved, on_message, STREAM_QOS)
    return heard


def recorder_counts(node, recorder: str = "recorder") -> dict[str, int]:
    """What the recorder node `recorder` (a name in `node`'s namespace) reports on its ~/counts:
    {topic: messages written}, updated as the caller's executor spins."""
    from diagnostic_msgs.msg import DiagnosticStatus

    from ..ros.parameters import LATCHED_QOS

    counts: dict[str, int] = {}

    def on_counts(msg: DiagnosticStatus) -> None:
        counts.update({kv.key: int(kv.value) for kv in msg.values})

    node.create_subscription(DiagnosticStatus, f"{recorder}/counts", on_counts, LATCHED_QOS)
    return counts


def settle(spin_once: Callable[[], None], heard: dict[str, int], recorded: dict[str, int],
           timeout: float = RECORDER_SETTLE_TIMEOUT) -> float:
    """Before a finished loop's nodes are stopped: spin the caller's executor until the recorder holds
    as many messages of each topic as the caller heard (`heard`: count_messages, `recorded`:
    recorder_counts); a message still on its way is lost once its publisher exits (a fresh-clone CI
    run on 2 loaded cores recorded 37 of 51 lockstep states when the plant was stopped at once).
    Returns the seconds waited; NmpcError naming the missing messages after `timeout` s."""
    start = time.monotonic()

    def missing() -> dict[str, tuple[int, int]]:
        return {t: (recorded.get(t, 0), n) for t, n in heard.items() if recorded.get(t, 0) < n}

    while missing() and time.monotonic() - start < timeout:
        spin_once()
    if short := missing():
        detail = ", ".join(f"{t} {got} of {n}" for t, (got, n) in short.items())
        raise NmpcError(f"the recorder did not take the loop's last messages in {timeout:g} s: it holds {detail}")
    return time.monotonic() - start


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
