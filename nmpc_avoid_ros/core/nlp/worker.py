"""Solver calls in a child process that can be abandoned at the sample's deadline.

Why: a solver call must end by the sample's deadline for every input that passes validation, and
FATROP cannot be bounded by its own options: on a state of [5e5, -3e5], or inside the state box
among validated obstacles of 1e6 m, its restoration phase loops for good inside one iteration
(measured: no return after 290 s with max_iterations 200; it does not poll signals either). A
thread cannot be stopped and would keep a core busy; a process can be killed.

How: the controller's NLPs are built first; the first solve forks a child that holds copies of
them. A call copies the guess and parameters into shared memory, writes one byte on a pipe and
waits on the answer pipe until the deadline. On time: the results are read back from shared
memory. Late: the child is killed (SIGKILL) and the call answers ABANDONED with a non-finite
iterate at once: the killed child is reaped by the next fork, not waited for now (its teardown
took 2-4 ms here, more on a loaded machine, and it would come out of the rest of the sample). The
next call forks a fresh child from the parent, whose copies were never used. The round trip costs
~20 microseconds (BENCHMARKS.md); a fork 2-3 ms, only after an abandoned call.

The child ignores SIGINT (the parent decides when it ends), dies with the parent (PR_SET_PDEATHSIG
where Linux offers it, and on end of file on its request pipe) and never runs the parent's
exit handlers (os._exit).

Interrupt: `interrupt()` (from a signal handler or another thread; it takes no lock) abandons the
call in progress at once and every later call until `resume()`. A node calls it on SIGINT or a
lifecycle transition so that neither waits for the deadline: Python retries a select() that a
signal interrupted (PEP 475) when the handler returns normally, so the wait also watches a wakeup
pipe that `interrupt()` writes to. Offline use never calls it.

Compiled solvers swapped in (core/nlp/background.py: a first start serves with interpreted solvers while
their libraries compile): the child holds copies of the NLPs as they were at its fork, so the first call
of each sample (a new deadline; every call outside a sample, whose deadline is infinite) first loads the
libraries that landed (`background.load_ready`) and, when the process's `background.generation` moved
since the child was forked, stops the child: the call forks a fresh one that runs the compiled solvers.
A sample's calls thus all run the same solvers; a swap costs the sample one fork and a few ms per library.
"""

from __future__ import annotations

import math
import mmap
import os
import select
import signal
import struct
import threading
import time
import warnings
import weakref
from collections.abc import Sequence
from typing import Any, Protocol

import numpy as np

from . import background
from .child_process import die_with_parent


class Solvable(Protocol):
    """What the worker needs of an NLP (core/nlp/tracking.py NlpBase): its sizes and a solve in this process."""

    layout: Any
    lbg: np.ndarray

    @property
    def parameter_count(self) -> int: ...

    def solve_here(self, w0: np.ndarray, par: np.ndarray, lam_x0: np.ndarray, lam_g0: np.ndarray,
                   cold: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict, float]: ...

#: solver status of a call that did not answer by its deadline (the child was killed)
ABANDONED = "Abandoned_At_Deadline"
#: bytes of the solver's return status kept in shared memory
_STATUS_BYTES = 64
#: header: iterations (int64), solve seconds (float64), status length (int64), status bytes
_HEADER = struct.Struct(f"qdq{_STATUS_BYTES}s")

#: a request: the NLP's index and whether the solve is cold
REQUEST = struct.Struct("<IB")
#: how long each side polls for the other before it sleeps, s: a wake-up of a sleeping process costs
#: ~0.1 ms on this VM, twice per call (BENCHMARKS.md); polling costs a core for at most this long
SPIN_SECONDS = 2e-3



class SolveWorker:
    """One child process serving the solver calls of a fixed list of NLPs."""

    def __init__(self, nlps: Sequence[Solvable]) -> None:
        self._nlps = list(nlps)
        self._index = {id(nlp): i for i, nlp in enumerate(self._nlps)}
        sizes = [(nlp.layout.n_w, nlp.parameter_count, nlp.lbg.size) for nlp in self._nlps]
        self._in_size = max(2 * n_w + n_p + n_g for n_w, n_p, n_g in sizes)
        self._out_size = max(2 * n_w + n_g for n_w, _, n_g in sizes)
        floats = self._in_size + self._out_size
        self._memory = mmap.mmap(-1, _HEADER.size + 8 * floats)  # anonymous and shared: survives fork
        self._inputs = np.frombuffer(self._memory, np.float64, self._in_size, _HEADER.size)
        self._outputs = np.frombuffer(self._memory, np.float64, self._out_size, _HEADER.size + 8 * self._in_size)
        self._child = _Child()
        self._lock = threading.Lock()  # one call at a time (a multi-threaded executor may call step)
        self._interrupted = False
        self._wakeup = list(os.pipe())  # [read, write]: a byte in it wakes the wait (interrupt); -1 once closed
        for fd in self._wakeup:
            os.set_blocking(fd, False)
        #: children forked so far (the first, then one after each abandoned call or swap of compiled solvers)
        self.forks = 0
        #: times the child was replaced because compiled solvers were swapped in (core/nlp/background.py)
        self.swaps = 0
        self._sample = math.nan  # the deadline of the sample of the last call
        self._generation = background.generation  # of the solvers the child holds
        #: the deadline (time.perf_counter s) of the calls of the current sample (NmpcController.step sets it)
        self.deadline = math.inf
        weakref.finalize(self, _release, self._child, self._wakeup)  # the child never outlives its worker

    def start(self) -> None:
        """Fork the child now rather than at the first call (a fork costs ~5 ms, which a first sample then spares)."""
        with self._lock:
            self._ensure_child()

    @property
    def interrupted(self) -> bool:
        """`interrupt()` was called and `resume()` not since: every call answers ABANDONED at once."""
        return self._interrupted

    def interrupt(self) -> None:
        """Abandon the call in progress now (its child is killed) and every later call until `resume()`.

        Safe from a signal handler and from another thread: sets a flag and writes one byte to the
        wakeup pipe (never blocks, takes no lock)."""
        self._interrupted = True
        fd = self._wakeup[1]
        if fd >= 0:
            try:
                os.write(fd, b"!")
            except OSError:  # full: a byte is already waiting
                pass

    def resume(self) -> None:
        """Serve calls again after `interrupt()` (call it when no call is in progress)."""
        self._interrupted = False
        self._drain_wakeup()

    def _drain_wakeup(self) -> None:
        fd = self._wakeup[0]
        try:
            while fd >= 0 and os.read(fd, 64):
                pass
        except OSError:  # empty (BlockingIOError)
            pass

    # -- the parent's side -----------------------------------------------------------------
    def solve(self, nlp: Solvable, w0: np.ndarray, par: np.ndarray, lam_x0: np.ndarray, lam_g0: np.ndarray,
              cold: bool, deadline: float, call_deadline: float = math.inf
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict, float]:
        """`nlp.solve_here` in the child, answered by `deadline` (time.perf_counter seconds: the sample's) or the
        call's own earlier `call_deadline`, or abandoned: then w, lam_x, lam_g are NaN and the stats say
        ABANDONED."""
        n_w, n_g = nlp.layout.n_w, nlp.lbg.size
        with self._lock:
            begin = time.perf_counter()
            if deadline - begin > 0 and not self._interrupted:
                if deadline != self._sample or math.isinf(deadline):  # a sample's first call: swaps go in here
                    self._sample = deadline
                    self._swap_compiled()
                self._ensure_child()
                n_p = par.size
                np.copyto(self._inputs[:n_w], w0)
                np.copyto(self._inputs[n_w:n_w + n_p], par)
                np.copyto(self._inputs[n_w + n_p:2 * n_w + n_p], lam_x0)
                np.copyto(self._inputs[2 * n_w + n_p:2 * n_w + n_p + n_g], lam_g0)
                os.write(self._child.request, REQUEST.pack(self._index[id(nlp)], int(cold)))
                if self._wait(min(deadline, call_deadline)):
                    iterations, seconds, length, raw = _HEADER.unpack_from(self._memory, 0)
                    out = self._outputs
                    stats = {"return_status": raw[:length].decode(), "iter_count": int(iterations)}
                    return (out[:n_w].copy(), out[n_w:2 * n_w].copy(), out[2 * n_w:2 * n_w + n_g].copy(), stats,
                            seconds)
                self._child.stop(reap=False)  # reaped by the next fork
        nan_w = np.full(n_w, np.nan)
        return nan_w, nan_w.copy(), np.full(n_g, np.nan), {"return_status": ABANDONED, "iter_count": 0}, \
            time.perf_counter() - begin

    def _wait(self, deadline: float) -> bool:
        """Whether the child answered before `deadline` (False also when it died or on `interrupt()`).

        First SPIN_SECONDS of polling reads (most fast-path solves answer within them: no wake-up of a
        sleeping parent), then a select() that sleeps until the answer, the deadline or an interrupt."""
        answer = self._child.answer
        spin_end = min(deadline, time.perf_counter() + SPIN_SECONDS)
        while not self._interrupted and time.perf_counter() < spin_end:
            reply = _poll(answer)
            if reply is not None:
                return reply == b"."
        watched = [answer, self._wakeup[0]]
        while not self._interrupted:
            left = deadline - time.perf_counter()
            if left <= 0:
                return False
            ready, _, _ = select.select(watched, [], [], None if math.isinf(left) else left)
            if answer in ready:
                reply = _poll(answer)
                if reply is not None:
                    return reply == b"."
            if self._wakeup[0] in ready and not self._interrupted:
                self._drain_wakeup()  # the byte of an interrupt() that a resume() overtook: keep waiting
        return False

    def _swap_compiled(self) -> None:
        """Load the compiled solvers that landed; stop a child that holds others (the next call forks)."""
        background.load_ready()
        if background.generation != self._generation:
            if self._child.pid:
                self._child.stop(reap=False)  # reaped by the next fork
                self.swaps += 1
            self._generation = background.generation

    def _ensure_child(self) -> None:
        if self._child.pid:
            return
        self._child.reap()
        request_read, request_write = os.pipe()
        answer_read, answer_write = os.pipe()
        with warnings.catch_warnings():
            # the child runs only solver code on memory it owns: no lock of another thread is needed
            warnings.simplefilter("ignore", DeprecationWarning)
            pid = os.fork()
        if pid == 0:  # the child
            os.close(request_write)
            os.close(answer_read)
            for fd in self._wakeup:
                os.close(fd)
            self._serve(request_read, answer_write)
        os.close(request_read)
        os.close(answer_write)
        os.set_blocking(answer_read, False)  # polled (see _wait)
        self._child.pid, self._child.request, self._child.answer = pid, request_write, answer_read
        self.forks += 1

    def close(self) -> None:
        """Stop the child (a later call forks a new one)."""
        with self._lock:
            self._child.stop()

    # -- the child's side ------------------------------------------------------------------
    def _serve(self, request: int, answer: int) -> None:
        """The child's loop: solve each request, answer with one byte; exit on end of file. After an
        answer it polls for the next request for SPIN_SECONDS (the next call of the same sample comes
        within them: no wake-up of a sleeping child), then sleeps in select()."""
        try:
            signal.signal(signal.SIGINT, signal.SIG_IGN)
            die_with_parent()
            os.set_blocking(request, False)
            while True:
                message = _next_request(request)
                if message is None:
                    break
                index, cold = REQUEST.unpack(message)
                self._solve_here(self._nlps[index], bool(cold))
                os.write(answer, b".")
        finally:
            os._exit(0)

    def _solve_here(self, nlp: Solvable, cold: bool) -> None:
        n_w, n_g, n_p = nlp.layout.n_w, nlp.lbg.size, nlp.parameter_count
        inputs = self._inputs
        w0, par = inputs[:n_w], inputs[n_w:n_w + n_p]
        lam_x0, lam_g0 = inputs[n_w + n_p:2 * n_w + n_p], inputs[2 * n_w + n_p:2 * n_w + n_p + n_g]
        w, lam_x, lam_g, stats, seconds = nlp.solve_here(w0, par, lam_x0, lam_g0, cold=cold)
        out = self._outputs
        out[:n_w], out[n_w:2 * n_w], out[2 * n_w:2 * n_w + n_g] = w, lam_x, lam_g
        status = str(stats.get("return_status", "unknown")).encode()[:_STATUS_BYTES]
        iterations = int(stats.get("iter_count", -1))
        _HEADER.pack_into(self._memory, 0, iterations, seconds if math.isfinite(seconds) else 0.0, len(status),
                          status)


class _Child:
    """The child process and its two pipe ends (pid 0: none running)."""

    def __init__(self) -> None:
        self.pid, self.request, self.answer = 0, -1, -1
        self.killed: list[int] = []  # killed children not reaped yet

    def stop(self, reap: bool = True) -> None:
        """Kill the child and close the pipes (idempotent); reap it (and every child killed before)
        now, or with `reap=False` at the next `reap()`."""
        if self.pid:
            for fd in (self.request, self.answer):
                try:
                    os.close(fd)
                except OSError:
                    pass
            try:
                os.kill(self.pid, signal.SIGKILL)
                self.killed.append(self.pid)
            except ProcessLookupError:
                pass
            self.pid, self.request, self.answer = 0, -1, -1
        if reap:
            self.reap()

    def reap(self) -> None:
        """Wait for the killed children (SIGKILL cannot be ignored: each is gone or about to be)."""
        while self.killed:
            try:
                os.waitpid(self.killed[-1], 0)
            except ChildProcessError:
                pass
            self.killed.pop()


def _release(child: _Child, wakeup: list[int]) -> None:
    """The worker's finaliser: stop its child, close its wakeup pipe (marked closed: -1)."""
    child.stop()
    for i, fd in enumerate(wakeup):
        wakeup[i] = -1
        try:
            os.close(fd)
        except OSError:
            pass


def _poll(fd: int) -> bytes | None:
    """One byte from the non-blocking pipe end `fd`: b"" at end of file, None when none is there yet."""
    try:
        return os.read(fd, 1)
    except BlockingIOError:
        return None


def _next_request(fd: int) -> bytes | None:
    """The next REQUEST.size-byte request from the non-blocking pipe end `fd` (polled for SPIN_SECONDS,
    then waited for), or None at end of file. A request is written whole (below PIPE_BUF: atomic)."""
    spin_end = time.perf_counter() + SPIN_SECONDS
    while True:
        try:
            data = os.read(fd, REQUEST.size)
        except BlockingIOError:
            if time.perf_counter() >= spin_end:
                select.select([fd], [], [])
            continue
        return data if len(data) == REQUEST.size else None
