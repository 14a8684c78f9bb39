"""Threads that run CasADi's native code beside the samples: symbolic derivatives, code generation, Function.save.

CasADi releases the interpreter lock inside its long calls, so a daemon thread may still be in one when the
interpreter finalises at exit, and the process dies of SIGSEGV (measured: a controller of the robot's live config
with a 40-sample passage NLP, stopped while that NLP's feedback law was being built, exited 139 instead of 0). These
threads are not daemons, so a process ends after them (their work is finite: seconds). A node does not wait that long
for a cache (the 40-sample law: 14 s): it waits a moment (`wait_native`), then `leave` runs the exit handlers and
ends the process without finalising the interpreter.
"""

from __future__ import annotations

import atexit
import contextlib
import os
import shutil
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

_started: list[threading.Thread] = []
_lock = threading.Lock()
#: files and folders being written now (a cache file's partial save, a compile's temporary folder): removed at exit
_scratch: set[Path] = set()


@contextlib.contextmanager
def scratch(path: Path) -> Iterator[Path]:
    """Within the block `path` (a file or folder being written) is removed by the exit handlers if the process ends
    meanwhile, so a cache keeps nothing half-written."""
    _scratch.add(path)
    try:
        yield path
    finally:
        _scratch.discard(path)


@atexit.register
def _remove_scratch() -> None:
    for path in list(_scratch):
        if path.is_dir():
            shutil.rmtree(path, ignore_errors=True)
        else:
            path.unlink(missing_ok=True)


def start_native(target: Callable[..., object], *args: object, name: str) -> threading.Thread:
    """Run target(*args) on a new non-daemon thread named `name` (its native work ends before the interpreter)."""
    thread = threading.Thread(target=target, args=args, name=name, daemon=False)
    with _lock:
        _started[:] = [t for t in _started if t.is_alive()]
        _started.append(thread)
    thread.start()
    return thread


def unfinished() -> list[str]:
    """The names of the native threads still running."""
    with _lock:
        return [t.name for t in _started if t.is_alive()]


def wait_native(timeout: float) -> list[str]:
    """Wait up to `timeout` s for the native threads; the names of those still running."""
    end = time.monotonic() + timeout
    with _lock:
        threads = list(_started)
    for thread in threads:
        thread.join(max(end - time.monotonic(), 0.0))
    return unfinished()


def leave(code: int) -> None:
    """End the process with `code` now: the exit handlers run (atexit: e.g. half-written cache files removed), the
    interpreter is not finalised (a native thread still runs in the objects it would free)."""
    atexit._run_exitfuncs()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)
