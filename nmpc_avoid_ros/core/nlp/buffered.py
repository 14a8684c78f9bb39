"""CasADi Functions called through `Function.buffer()`: arrays bound once, no conversion per call."""

from __future__ import annotations

import time

import casadi as ca
import numpy as np


class Buffered:
    """A CasADi Function called through `Function.buffer()`: arrays bound once, no conversion per call.

    `f(*args)` copies the inputs that are not `fixed` (in order) into the bound arrays, evaluates,
    and returns the output arrays (1-d; dense unless `densify` is False, for a Function whose
    outputs already are, such as a solver). They are overwritten by the next call: copy what you
    keep. `seconds` is the wall time of the last evaluation alone. A dict call of a small Function
    costs ~0.1 ms in conversions; this costs a few microseconds.
    """

    def __init__(self, function: ca.Function, fixed: dict[int, np.ndarray] | None = None,
                 densify: bool = True) -> None:
        if densify:
            symbols = [ca.SX.sym(f"in{i}", function.sparsity_in(i)) for i in range(function.n_in())]
            function = ca.Function(function.name(), symbols, [ca.densify(out) for out in function.call(symbols)])
        self.function = function
        fixed = fixed or {}
        args = [np.zeros(function.nnz_in(i)) for i in range(function.n_in())]
        for i, value in fixed.items():
            np.copyto(args[i], value)
        self._args = args  # the buffer holds raw pointers into these: they must live as long as it
        self._free = [arr for i, arr in enumerate(args) if i not in fixed]
        self._results = [np.zeros(function.nnz_out(i)) for i in range(function.n_out())]
        buffer, self._trigger = function.buffer()
        for i, arr in enumerate(args):
            buffer.set_arg(i, memoryview(arr))
        for i, arr in enumerate(self._results):
            buffer.set_res(i, memoryview(arr))
        self._buffer = buffer
        self.seconds = 0.0

    def bind(self, index: int, value: np.ndarray) -> None:
        """Replace the fixed input `index` [its nnz, column-major for a matrix] (e.g. a prepared law's data, bound once
        and then read by every call)."""
        np.copyto(self._args[index], np.ravel(value, order="F"))

    def __call__(self, *args: np.ndarray) -> list[np.ndarray]:
        for target, value in zip(self._free, args, strict=True):
            np.copyto(target, np.ravel(value))
        start = time.perf_counter()
        self._trigger()
        self.seconds = time.perf_counter() - start
        return self._results

    def stats(self) -> dict:
        """The Function's statistics of the last call (a solver's iterations and return status)."""
        return self._buffer.stats()
