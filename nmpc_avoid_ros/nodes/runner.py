"""`main` of every node: ROS arguments, --help, clean exit 0 on SIGINT/SIGTERM, clear config errors,
and core's `logging` records (a first start's compile, core/nlp/codegen.py) in the node's ROS log."""

from __future__ import annotations

import concurrent.futures
import gc
import logging
import signal
import sys
import threading
import traceback
from collections.abc import Callable

import rclpy
from rclpy.exceptions import InvalidHandle, ParameterException
from rclpy.executors import (
    ConditionReachedException,
    Executor,
    ExternalShutdownException,
    ShutdownException,
    SingleThreadedExecutor,
    TimeoutException,
)
from rclpy.logging import get_logger
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions

from ..core.errors import NmpcError
from ..core.nlp.native_threads import leave, wait_native


class PoolExecutor(Executor):
    """Callbacks on `threads` worker threads; the callback groups decide which may run together.

    rclpy's MultiThreadedExecutor without its gap: its shutdown (rclpy 7.1) returns while callbacks
    still run, so a node could be destroyed under one. Here `shutdown` waits for them. The calling
    thread only waits for work and hands it out, so it stays free to run signal handlers.
    """

    def __init__(self, threads: int = 2, *, context=None) -> None:
        super().__init__(context=context)
        self._pool = concurrent.futures.ThreadPoolExecutor(threads, thread_name_prefix="callbacks")
        #: (rclpy Task, the pool's future of its run) handed out and not yet checked
        self._running: list[tuple[object, concurrent.futures.Future]] = []

    def spin_once(self, timeout_sec: float | None = None) -> None:
        try:
            handler, _, _ = self.wait_for_ready_callbacks(timeout_sec=timeout_sec)
        except (TimeoutException, ShutdownException, ConditionReachedException):
            pass
        except InvalidHandle:
            # a callback on a pool thread (the lifecycle's cleanup or shutdown) destroyed an entity while this
            # thread built the wait set: rclpy skips destroyed timers and subscriptions there but not waitables
            # (a publisher's QoS event handler). The next wait is built from what is left (fresh clone make test:
            # a Traceback logged after "controller released its solver, publishers and subscriptions")
            pass
        else:
            self._running.append((handler, self._pool.submit(handler)))
        for entry in [e for e in self._running if e[1].done()]:
            self._running.remove(entry)
            entry[0].result()  # a callback's exception is raised here, in the spinning thread

    def shutdown(self, timeout_sec: float | None = None) -> bool:
        """Wait up to `timeout_sec` (None: for ever) for the callbacks handed out, then stop. Call it
        from the spinning thread once it stopped spinning (then nothing new is handed out). The
        waiting comes first: rclpy's shutdown destroys the guard condition a running handler
        triggers when it ends."""
        _, not_done = concurrent.futures.wait([f for _, f in self._running], timeout_sec)
        super().shutdown(timeout_sec=0)
        self._pool.shutdown(wait=False)
        return not not_done


class RosLogHandler(logging.Handler):
    """Passes the package's Python `logging` records (INFO and up) to an rclpy logger: core logs
    without ROS, the node's log shows it, also while the node is still being built."""

    def __init__(self, logger) -> None:
        super().__init__(logging.INFO)
        self.logger = logger

    def emit(self, record: logging.LogRecord) -> None:
        text = record.getMessage()
        if record.levelno >= logging.ERROR:
            self.logger.error(text)
        elif record.levelno >= logging.WARNING:
            self.logger.warning(text)
        else:
            self.logger.info(text)


#: s a stopped node waits for the threads in CasADi's native code (a cache file being saved; a law still being built,
#: up to 14 s, is abandoned: core/nlp/native_threads.py)
NATIVE_EXIT_WAIT = 2.0


def run_node(factory: Callable[[], Node], argv: list[str] | None, name: str, doc: str | None,
             on_stop: Callable[[Node], None] | None = None, on_signal: Callable[[Node], None] | None = None,
             executor_factory: Callable[[], Executor] = SingleThreadedExecutor) -> int:
    """`spin_node`, then the end of the process: a thread still in CasADi's native code (a first start's feedback law
    or compile) would crash the interpreter's finalisation (exit 134/139 after a clean stop), so after
    NATIVE_EXIT_WAIT the process ends without it (`leave`), with the same exit code."""
    code = spin_node(factory, argv, name, doc, on_stop, on_signal, executor_factory)
    running = wait_native(NATIVE_EXIT_WAIT)
    if running:
        print(f"{name}: leaving without {', '.join(running)} (a first start's cache, built again by the next start)",
              file=sys.stderr)
        leave(code)
    return code


def spin_node(factory: Callable[[], Node], argv: list[str] | None, name: str, doc: str | None,
              on_stop: Callable[[Node], None] | None = None, on_signal: Callable[[Node], None] | None = None,
              executor_factory: Callable[[], Executor] = SingleThreadedExecutor) -> int:
    """Init rclpy with argv (which may hold `--ros-args ...`), build the node, spin until a signal.

    SIGINT and SIGTERM end the spin between callbacks (never inside one, so no callback publishes
    into a context that is shutting down), then `on_stop(node)` runs and the node is destroyed.
    `on_signal(node)` runs in the signal handler (it must not block or take locks): a node whose
    callback may wait long (a solve) uses it to cut the wait short. `executor_factory`: the
    executor (a PoolExecutor lets a node serve some callbacks while another runs).
    Returns 0 after a signal, 2 when the configuration is invalid (the reason is printed).
    """
    argv = sys.argv[1:] if argv is None else list(argv)
    user_args = argv[: argv.index("--ros-args")] if "--ros-args" in argv else argv
    if "-h" in user_args or "--help" in user_args:
        print(f"usage: {name} [--ros-args ...]\n\n{(doc or '').strip()}")
        return 0
    stop = threading.Event()
    node = None

    def on_stop_signal(*_) -> None:
        stop.set()
        if on_signal is not None and node is not None:
            on_signal(node)

    previous = {sig: signal.signal(sig, on_stop_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    rclpy.init(args=[name, *argv], signal_handler_options=SignalHandlerOptions.NO)
    package_log = logging.getLogger(__name__.split(".")[0])
    ros_log = RosLogHandler(get_logger(name))
    package_log.addHandler(ros_log)
    package_log.setLevel(logging.INFO)
    executor = None
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
        executor = executor_factory()
        executor.add_node(node)
        while not stop.is_set() and rclpy.ok():
            try:
                executor.spin_once(timeout_sec=0.05)
            except (KeyboardInterrupt, ExternalShutdownException):
                raise
            except Exception:  # a bug in one callback must not stop the node: log it loudly, go on
                node.get_logger().error(f"callback failed:\n{traceback.format_exc()}", throttle_duration_sec=1.0)
        executor.shutdown()  # waits for a callback still running (a PoolExecutor's)
        if on_stop is not None:
            on_stop(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if executor is not None:
            executor.shutdown()
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
        package_log.removeHandler(ros_log)
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return 0
