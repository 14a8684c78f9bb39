"""Interval arithmetic over a CasADi SX Function: enclosures of every output over boxes of inputs.

Used to bound a model's derivatives over a box (core/problem/terminal.py certifies a terminal set with them).
The Function's algorithm is replayed instruction by instruction with each work value an interval [lo, hi],
for many boxes at once (numpy arrays, one entry per box); every operation returns an interval that contains
the operation's value for every point of its argument intervals (the natural interval extension), so each
output's interval contains its value over the whole box. Floating-point rounding is not directed; every result
is widened by ROUNDING_PAD relative (and absolute) to cover it. Operations without a rule here raise
ValueError: a bound is never guessed.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

#: every interval result is widened by this, relative to its magnitude (and absolute): rounding cover
ROUNDING_PAD = 1e-12

Interval = tuple[np.ndarray, np.ndarray]


def _pad(lo: np.ndarray, hi: np.ndarray) -> Interval:
    return lo - ROUNDING_PAD * (1.0 + np.abs(lo)), hi + ROUNDING_PAD * (1.0 + np.abs(hi))


def _mul(a: Interval, b: Interval) -> Interval:
    with np.errstate(invalid="ignore"):
        products = np.array([a[0] * b[0], a[0] * b[1], a[1] * b[0], a[1] * b[1]])
    products = np.where(np.isnan(products), 0.0, products)  # 0 * inf: the factor 0 is exact
    return products.min(axis=0), products.max(axis=0)


def _div(a: Interval, b: Interval) -> Interval:
    straddles = (b[0] <= 0.0) & (0.0 <= b[1])
    with np.errstate(divide="ignore", invalid="ignore"):
        lo, hi = _mul(a, (1.0 / b[1], 1.0 / b[0]))
    return np.where(straddles, -np.inf, lo), np.where(straddles, np.inf, hi)


def _square(a: Interval) -> Interval:
    lo, hi = a
    low_sq, high_sq = lo * lo, hi * hi
    straddles = (lo < 0) & (hi > 0)
    return (np.where(straddles, 0.0, np.minimum(low_sq, high_sq)), np.maximum(low_sq, high_sq))


def _integer_power(a: Interval, k: int) -> Interval:
    if k == 0:
        return np.ones_like(a[0]), np.ones_like(a[1])
    if k < 0:
        return _div((np.ones_like(a[0]), np.ones_like(a[1])), _integer_power(a, -k))
    if k % 2 == 0:
        s = _square(a)
        return s[0] ** (k // 2), s[1] ** (k // 2)
    return a[0] ** k, a[1] ** k  # odd powers are increasing


def _periodic(a: Interval, fn, peak: float) -> Interval:
    """sin (peak pi/2) or cos (peak 0) over a: the end values, widened to +1 where a maximum (peak + 2 k pi) lies
    inside, to -1 where a minimum (peak + pi + 2 k pi) does; [-1, 1] for intervals of 2 pi or more."""
    lo, hi = a
    ends = np.array([fn(lo), fn(hi)])
    low, high = ends.min(axis=0), ends.max(axis=0)
    top = peak + 2 * np.pi * np.ceil((lo - peak) / (2 * np.pi))
    bottom = peak + np.pi + 2 * np.pi * np.ceil((lo - peak - np.pi) / (2 * np.pi))
    wide = ~(np.isfinite(lo) & np.isfinite(hi)) | (hi - lo >= 2 * np.pi)
    return np.where(wide | (bottom <= hi), -1.0, low), np.where(wide | (top <= hi), 1.0, high)


def _monotone(fn, a: Interval) -> Interval:
    return fn(a[0]), fn(a[1])


def _fabs(a: Interval) -> Interval:
    lo, hi = a
    straddles = (lo <= 0) & (hi >= 0)
    return np.where(straddles, 0.0, np.minimum(np.abs(lo), np.abs(hi))), np.maximum(np.abs(lo), np.abs(hi))


_UNARY = {
    ca.OP_NEG: lambda a: (-a[1], -a[0]),
    ca.OP_SQ: _square,
    ca.OP_TWICE: lambda a: (2 * a[0], 2 * a[1]),
    ca.OP_EXP: lambda a: _monotone(np.exp, a),
    ca.OP_SQRT: lambda a: _monotone(np.sqrt, (np.maximum(a[0], 0.0), np.maximum(a[1], 0.0))),
    ca.OP_TANH: lambda a: _monotone(np.tanh, a),
    ca.OP_ATAN: lambda a: _monotone(np.arctan, a),
    ca.OP_SIN: lambda a: _periodic(a, np.sin, np.pi / 2),
    ca.OP_COS: lambda a: _periodic(a, np.cos, 0.0),
    ca.OP_FABS: _fabs,
    ca.OP_INV: lambda a: _div((np.ones_like(a[0]), np.ones_like(a[1])), a),
    ca.OP_ASSIGN: lambda a: a,
}
_BINARY = {
    ca.OP_ADD: lambda a, b: (a[0] + b[0], a[1] + b[1]),
    ca.OP_SUB: lambda a, b: (a[0] - b[1], a[1] - b[0]),
    ca.OP_MUL: _mul,
    ca.OP_DIV: _div,
    ca.OP_FMIN: lambda a, b: (np.minimum(a[0], b[0]), np.minimum(a[1], b[1])),
    ca.OP_FMAX: lambda a, b: (np.maximum(a[0], b[0]), np.maximum(a[1], b[1])),
}


def interval_evaluate_many(function: ca.Function, lower: list[np.ndarray], upper: list[np.ndarray]
                           ) -> list[tuple[np.ndarray, np.ndarray]]:
    """Enclosures of every output of an SX `function` over K boxes at once.

    lower, upper: one array [nnz_in, K] per input. Returns per output (lo [nnz_out, K], hi [nnz_out, K]).
    ValueError for an operation without an interval rule."""
    if not function.is_a("SXFunction"):
        function = function.expand()
    count = np.shape(lower[0])[1] if function.n_in() else 1
    outputs = [(np.zeros((function.nnz_out(i), count)), np.zeros((function.nnz_out(i), count)))
               for i in range(function.n_out())]
    work: dict[int, Interval] = {}
    for k in range(function.n_instructions()):
        op = function.instruction_id(k)
        args = function.instruction_input(k)
        out = function.instruction_output(k)
        if op == ca.OP_INPUT:
            work[out[0]] = (np.asarray(lower[args[0]][args[1]], float), np.asarray(upper[args[0]][args[1]], float))
        elif op == ca.OP_OUTPUT:
            outputs[out[0]][0][out[1]], outputs[out[0]][1][out[1]] = work[args[0]]
        elif op == ca.OP_CONST:
            c = np.full(count, function.instruction_constant(k))
            work[out[0]] = c, c
        elif op == ca.OP_CONSTPOW or op == ca.OP_POW:
            exponent = work[args[1]]
            whole = np.round(exponent[0])
            if np.any(exponent[0] != exponent[1]) or np.any(exponent[0] != whole) or np.unique(whole).size != 1:
                raise ValueError("interval power needs one constant whole exponent")
            work[out[0]] = _pad(*_integer_power(work[args[0]], int(whole.flat[0])))
        elif op in _UNARY:
            work[out[0]] = _pad(*_UNARY[op](work[args[0]]))
        elif op in _BINARY:
            work[out[0]] = _pad(*_BINARY[op](work[args[0]], work[args[1]]))
        else:
            raise ValueError(f"no interval rule for CasADi operation {op} in {function.name()}")
    return outputs


def interval_evaluate(function: ca.Function, lower: list[np.ndarray], upper: list[np.ndarray]) -> list[np.ndarray]:
    """Enclosures of every output of an SX `function` over one box lower <= inputs <= upper.

    lower, upper: one array per input, of that input's number of nonzeros. Returns one array [nnz, 2] of
    (lo, hi) per output."""
    many = interval_evaluate_many(function, [np.reshape(v, (-1, 1)) for v in lower],
                                  [np.reshape(v, (-1, 1)) for v in upper])
    return [np.hstack([lo, hi]) for lo, hi in many]
