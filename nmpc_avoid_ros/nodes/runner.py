"""`main` of every node: ROS arguments, --help, clean exit 0 on SIGINT/SIGTERM, clear config errors."""

from __future__ import annotations

import gc
import signal
import sys
import threading
import traceback
from collections.abc import Callable

import rclpy
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions

from ..core.errors import NmpcError


def run_node(factory: Callable[[], Node], argv: list[str] | None, name: str, doc: str | None,
             on_stop: Callable[[Node], None] | None = None) -> int:
    """Init rclpy with argv (which may hold `--ros-args ...`), build the node, spin until a signal.

    SIGINT and SIGTERM end the spin between callbacks (never inside one, so no callback publishes
    into a context that is shutting down), then `on_stop(node)` runs and the node is destroyed.
    Returns 0 after a signal, 2 when the configuration is invalid (the reason is printed).
    """
    argv = sys.argv[1:] if argv is None else list(argv)
    user_args = argv[: argv.index("--ros-args")] if "--ros-args" in argv else argv
    if "-h" in user_args or "--help" in user_args:
        print(f"usage: {name} [--ros-args ...]\n\n{(doc or '').strip()}")
        return 0
    stop = threading.Event()
    previous = {sig: signal.signal(sig, lambda *_: stop.set()) for sig in (signal.SIGINT, signal.SIGTERM)}
    rclpy.init(args=[name, *argv], signal_handler_options=SignalHandlerOptions.NO)
    node = None
    try:
        try:
            node = factory()
        except (NmpcError, ValueError, ParameterException) as exc:
            # a bad parameter (ours, or out of a declared ROS range or type): say which and why, no traceback
            print(f"{name}: configuration error: {exc}", file=sys.stderr)
            return 2
        # everything built at start-up (CasADi functions, the NLP, imports) moves to the permanent
        # generation: the collector never scans it again, so its pauses inside callbacks stay short
        gc.collect()
        gc.freeze()
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        while not stop.is_set() and rclpy.ok():
            try:
                executor.spin_once(timeout_sec=0.05)
            except (KeyboardInterrupt, ExternalShutdownException):
                raise
            except Exception:  # a bug in one callback must not stop the node: log it loudly, go on
                node.get_logger().error(f"callback failed:\n{traceback.format_exc()}", throttle_duration_sec=1.0)
        if on_stop is not None:
            on_stop(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return 0
