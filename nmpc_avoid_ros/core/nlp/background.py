"""A first start in seconds: interpreted solvers serve while their libraries compile in the background.

With codegen, a problem structure with no library in the cache (core/nlp/codegen.py) used to generate
and compile the C code of every NLP before the controller could solve anything: ~80 s for a shipped
live config (6 NLPs). With the setting codegen_background: true, `make_solver` (core/nlp/tracking.py)
builds the same solver from the symbolic problem instead, as CasADi's virtual machine interprets it (all
NLPs of the van der Pol live config in 3 s; warm solves ~1.4x slower there), hands it out at once and
queues its library here:

* One daemon thread compiles the queue in order, one library at a time (the controller keeps the other
  core), each in a fresh Python process (`python -c ... compile_job`, niced) that reads the pickled
  problem and solver options from a file and runs `compiled_library`. In process, the C generation alone
  holds the GIL for ~1 s per NLP (a sample would wait for it); in a child, neither it nor gcc delays a
  sample. The child dies with the thread that waits for it (PR_SET_PDEATHSIG) and on SIGINT or
  SIGTERM (a node's stop signals its process group), removing its temporary folder and its compiler.
* `load_ready()` loads each library that landed as the compiled solver of the interpreted one it
  replaces (a few ms: nlpsol from a library does no symbolic work) and bumps `generation`. The solver
  worker calls it when a sample begins and forks a fresh child when the generation changed
  (core/nlp/worker.py): the swap happens between samples, never within one. A solve without a worker
  calls it before each solve (NlpBase.solve).
* `current(solver)`: the compiled solver once loaded, else `solver`; `SwappableCall` (what
  NlpBase._buffered returns for an interpreted solver) runs it, switching over at the start of a call.
* `wait_compiled()` blocks until every queued library is compiled and loaded (offline tools,
  benchmarks, tests that want the compiled solvers); codegen_background: false (the default: offline
  tools, benchmarks and tests time and cache the compiled solvers) compiles in the constructor instead.

The swap does not count as a solver build (NmpcController.nlp_builds): it is the same solver, compiled.
Log lines (the `logging` logger of this module; nodes pass them to the ROS log): once when the first
interpreted solver is handed out (codegen.announce_compile), at each swap and when all are in use.
"""

from __future__ import annotations

import logging
import os
import pickle
import queue
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import casadi as ca
import numpy as np

from .child_process import die_with_parent
from .codegen import announce_compile, compiled_library, library_path, prepare_folder

log = logging.getLogger(__name__)

#: the compile processes' niceness: the controller's own process comes first on a busy machine
COMPILE_NICENESS = 10


@dataclass(eq=False)
class Job:
    """One library to compile: its cache key and path, and the pickled (plugin, problem, options)."""

    key: str
    library: Path
    blob: bytes
    done: threading.Event = field(default_factory=threading.Event)
    error: str = ""
    seconds: float = 0.0


@dataclass(eq=False)
class _Tracked:
    """An interpreted solver handed out, its job and how to load its compiled twin."""

    interpreted: ca.Function
    job: Job
    load: Callable[[], ca.Function]
    compiled: ca.Function | None = None


_lock = threading.Lock()
_jobs: dict[Path, Job] = {}  # every job of this process, by library
_queue: queue.Queue[Job] = queue.Queue()
_thread: threading.Thread | None = None
_tracked: dict[int, _Tracked] = {}  # by id() of the interpreted solver (held, so the id stays its own)
_landed = False  # a job ended since the last load_ready()
_first_handed_out: float | None = None  # time.perf_counter() of the first interpreted solver
#: bumped by each load_ready() that loaded a compiled solver: a worker whose child was forked at
#: another generation forks a new one at its next sample
generation = 0


def interpreted_until_compiled(key: str, library: Path, plugin: str, nlp: dict, opts: dict) -> ca.Function:
    """The solver of `nlp` interpreted now; its library `library` queued for the background compile
    (once per library and process), to be swapped in by `load_ready()`."""
    global _first_handed_out
    solver = ca.nlpsol("nmpc", plugin, nlp, opts)
    problem = ca.Function("nlp", [nlp["x"], nlp["p"]], [nlp["f"], nlp["g"]])
    with _lock:
        job = _jobs.get(library)
        if job is None:
            job = _jobs[library] = Job(key, library, pickle.dumps((key, str(library.parent), plugin, problem, opts)))
            _queue.put(job)
            _start_thread()
        _tracked[id(solver)] = _Tracked(solver, job, lambda: ca.nlpsol("nmpc", plugin, str(library), opts))
        if _first_handed_out is None:
            _first_handed_out = time.perf_counter()
    return solver


def interpreted_while_compiling(key: str, folder: Path, plugin: str, nlp: dict, opts: dict) -> ca.Function | None:
    """None when the library of `key` is cached; else the solver of `nlp`, interpreted, while its library
    compiles in a background process (core/nlp/background.py swaps it in between samples)."""
    library = library_path(key, folder)
    if library.exists():
        return None
    prepare_folder(folder)  # a missing compiler or cache folder is a configuration error now, not in the background
    announce_compile(folder, background=True)
    return interpreted_until_compiled(key, library, plugin, nlp, opts)


def pending(library: Path) -> Job | None:
    """The job of `library` queued in this process, if any (a synchronous build waits for it)."""
    return _jobs.get(library)


def current(solver: ca.Function) -> ca.Function:
    """What a call of `solver` runs: its compiled twin once `load_ready()` loaded it, else `solver` itself."""
    tracked = _tracked.get(id(solver))
    return solver if tracked is None or tracked.compiled is None else tracked.compiled


def is_tracked(solver: ca.Function) -> bool:
    """Whether `solver` is an interpreted one waiting for (or replaced by) a compiled library."""
    return id(solver) in _tracked


def load_ready() -> int:
    """Load the compiled solver of every interpreted one whose library landed; how many were loaded.

    Call it between samples (the worker does when a sample begins): a few ms per library. Bumps
    `generation` when it loaded any. Costs nothing when no library landed since the last call."""
    global _landed, generation
    if not _landed:
        return 0
    with _lock:
        _landed = False
        loaded = [t for t in _tracked.values() if t.compiled is None and t.job.done.is_set() and not t.job.error]
        for tracked in loaded:
            tracked.compiled = tracked.load()
        if loaded:
            generation += 1
            _log_swap(len(loaded))
    return len(loaded)


def wait_compiled(timeout: float | None = None) -> bool:
    """Wait until every library queued in this process is compiled (or failed), then load them: a
    worker swaps them in at its next sample, a solve without one at its next call. Whether all
    finished within `timeout` s (None: no limit)."""
    end = None if timeout is None else time.monotonic() + timeout
    for job in list(_jobs.values()):
        left = None if end is None else max(0.0, end - time.monotonic())
        if not job.done.wait(left):
            load_ready()
            return False
    load_ready()
    return True


def compiling() -> int:
    """Libraries queued in this process that are not compiled yet."""
    return sum(not job.done.is_set() for job in list(_jobs.values()))


def _log_swap(count: int) -> None:
    jobs = list(_jobs.values())
    done = sum(job.done.is_set() for job in jobs)
    waited = time.perf_counter() - (_first_handed_out or time.perf_counter())
    swapped = sum(t.compiled is not None for t in _tracked.values())
    left = len(_tracked) - swapped
    state = "all compiled solvers in use" if not left else f"{left} solver(s) still interpreted"
    log.info(f"compiled solver(s) swapped in between samples for {count} NLP solver(s), {waited:.1f} s after the "
             f"interpreted ones started ({done} of {len(jobs)} libraries compiled): {state}")


# -- the background thread -----------------------------------------------------------------
def _start_thread() -> None:
    global _thread
    if _thread is None or not _thread.is_alive():
        _thread = threading.Thread(target=_compile_queue, name="nmpc-compile", daemon=True)
        _thread.start()


def _compile_queue() -> None:
    """The thread: compile each queued job in a child process, in order; never ends (daemon)."""
    global _landed
    while True:
        job = _queue.get()
        begin = time.perf_counter()
        try:
            job.error = "" if job.library.exists() else _compile_in_child(job)
        except Exception as exc:  # noqa: BLE001 - any failure leaves the interpreted solver in use
            job.error = f"{type(exc).__name__}: {exc}"
        job.seconds = time.perf_counter() - begin
        job.blob = b""
        if job.error:
            log.warning(f"compiling the solver library {job.library.name} in the background failed: the "
                        f"interpreted solver stays in use. {job.error}")
        job.done.set()
        _landed = True


def _compile_in_child(job: Job) -> str:
    """Run `compile_job` in a fresh Python process on the job's file; its error ('' on success).

    The job goes through a file, not the child's stdin: a solver worker forked meanwhile would hold the
    pipe's write end (core/nlp/worker.py), and the child would wait for its end of file for good."""
    package_root = str(Path(__file__).resolve().parents[3])
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, (package_root, os.environ.get("PYTHONPATH"))))}
    fd, path = tempfile.mkstemp(dir=job.library.parent, prefix=f".{job.key}.", suffix=".job")
    try:
        with os.fdopen(fd, "wb") as file:
            file.write(job.blob)
        code = f"from nmpc_avoid_ros.core.nlp.background import compile_job; compile_job({path!r}, {os.getpid()})"
        result = subprocess.run([sys.executable, "-c", code], stdin=subprocess.DEVNULL, capture_output=True, env=env)
    finally:
        Path(path).unlink(missing_ok=True)  # the child removes it once read
    if result.returncode == 0:
        return ""
    return f"exit status {result.returncode}: {result.stderr.decode(errors='replace').strip()[-500:]}"


def compile_job(path: str, parent: int) -> None:
    """The compile process: read (key, folder, plugin, problem, options) from `path`, compile the library."""
    def stop(signum: int, frame: object) -> None:
        raise SystemExit(128 + signum)  # unwinds: the compiler is killed, the temporary folder removed

    signal.signal(signal.SIGINT, stop)
    signal.signal(signal.SIGTERM, stop)
    die_with_parent(signal.SIGTERM)
    if os.getppid() != parent:  # the parent ended before the line above
        raise SystemExit(1)
    os.nice(COMPILE_NICENESS)
    with open(path, "rb") as file:
        key, folder, plugin, problem, opts = pickle.load(file)
    os.unlink(path)
    x, p = ca.SX.sym("x", problem.sparsity_in(0)), ca.SX.sym("p", problem.sparsity_in(1))
    f, g = problem(x, p)
    nlp = {"x": x, "p": p, "f": f, "g": g}
    compiled_library(key, Path(folder), lambda: ca.nlpsol("nmpc", plugin, nlp, opts), own_group=True)


class SwappableCall:
    """A solver call (a Buffered, core/nlp/buffered.py) that runs `current(solver)`: the interpreted
    solver until its compiled twin is loaded, then that one. It switches at the start of a call, never
    within one; `make` builds the Buffered call of a solver (the NLP's bounds bound once)."""

    def __init__(self, solver: ca.Function, make: Callable[[ca.Function], object]) -> None:
        self._solver, self._make = solver, make
        self._call = make(current(solver))

    def __call__(self, *args: np.ndarray) -> list[np.ndarray]:
        solver = current(self._solver)
        if solver is not self._call.function:
            self._call = self._make(solver)
        return self._call(*args)

    @property
    def function(self) -> ca.Function:
        """The solver the last (or next) call runs."""
        return self._call.function

    @property
    def seconds(self) -> float:
        return self._call.seconds

    def stats(self) -> dict:
        return self._call.stats()
