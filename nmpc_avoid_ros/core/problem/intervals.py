"""Interval arithmetic over a CasADi SX Function: enclosures of every output over a box of inputs.

Used to bound second derivatives of a model over a box (core/problem/terminal.py certifies a terminal
set with them). The Function's algorithm is replayed instruction by instruction with each work value an
interval [lo, hi]; every operation returns an interval that contains the operation's value for every
point of its argument intervals (the natural interval extension), so each output's interval contains
its value over the whole box. Floating-point rounding is not directed; every result is widened by
ROUNDING_PAD relative (and absolute) to cover it. Operations without a rule here raise ValueError:
a bound is never guessed.
"""

from __future__ import annotations

import math

import casadi as ca
import numpy as np

#: every interval result is widened by this, relative to its magnitude (and absolute): rounding cover
ROUNDING_PAD = 1e-12

Interval = tuple[float, float]


def _pad(lo: float, hi: float) -> Interval:
    return lo - ROUNDING_PAD * (1.0 + abs(lo)), hi + ROUNDING_PAD * (1.0 + abs(hi))


def _mul(a: Interval, b: Interval) -> Interval:
    products = [a[0] * b[0], a[0] * b[1], a[1] * b[0], a[1] * b[1]]
    products = [0.0 if math.isnan(v) else v for v in products]  # 0 * inf: the factor 0 is exact
    return min(products), max(products)


def _div(a: Interval, b: Interval) -> Interval:
    if b[0] <= 0.0 <= b[1]:
        return -math.inf, math.inf
    return _mul(a, (1.0 / b[1], 1.0 / b[0]))


def _square(a: Interval) -> Interval:
    lo, hi = a
    if lo >= 0:
        return lo * lo, hi * hi
    if hi <= 0:
        return hi * hi, lo * lo
    return 0.0, max(lo * lo, hi * hi)


def _integer_power(a: Interval, k: int) -> Interval:
    if k == 0:
        return 1.0, 1.0
    if k < 0:
        return _div((1.0, 1.0), _integer_power(a, -k))
    if k % 2 == 0:
        s = _square(a)
        return s[0] ** (k // 2), s[1] ** (k // 2)
    return a[0] ** k, a[1] ** k  # odd powers are increasing


def _periodic(a: Interval, fn, phase: float) -> Interval:
    """sin or cos over a: the end values, and the values at the extrema inside (at phase + k pi: sin pi/2,
    cos 0)."""
    lo, hi = a
    if not (math.isfinite(lo) and math.isfinite(hi)) or hi - lo >= 2 * math.pi:
        return -1.0, 1.0
    values = [fn(lo), fn(hi)]
    first = math.ceil((lo - phase) / math.pi)
    for k in range(first, first + 3):
        t = phase + k * math.pi
        if lo <= t <= hi:
            values.append(fn(t))
    return min(values), max(values)


def _monotone(fn, a: Interval) -> Interval:
    return fn(a[0]), fn(a[1])


_UNARY = {
    ca.OP_NEG: lambda a: (-a[1], -a[0]),
    ca.OP_SQ: _square,
    ca.OP_TWICE: lambda a: (2 * a[0], 2 * a[1]),
    ca.OP_EXP: lambda a: _monotone(math.exp, a),
    ca.OP_SQRT: lambda a: _monotone(math.sqrt, (max(a[0], 0.0), max(a[1], 0.0))),
    ca.OP_TANH: lambda a: _monotone(math.tanh, a),
    ca.OP_ATAN: lambda a: _monotone(math.atan, a),
    ca.OP_SIN: lambda a: _periodic(a, math.sin, math.pi / 2),
    ca.OP_COS: lambda a: _periodic(a, math.cos, 0.0),
    ca.OP_FABS: lambda a: (0.0 if a[0] <= 0 <= a[1] else min(abs(a[0]), abs(a[1])), max(abs(a[0]), abs(a[1]))),
    ca.OP_INV: lambda a: _div((1.0, 1.0), a),
    ca.OP_ASSIGN: lambda a: a,
}
_BINARY = {
    ca.OP_ADD: lambda a, b: (a[0] + b[0], a[1] + b[1]),
    ca.OP_SUB: lambda a, b: (a[0] - b[1], a[1] - b[0]),
    ca.OP_MUL: _mul,
    ca.OP_DIV: _div,
    ca.OP_FMIN: lambda a, b: (min(a[0], b[0]), min(a[1], b[1])),
    ca.OP_FMAX: lambda a, b: (max(a[0], b[0]), max(a[1], b[1])),
}


def interval_evaluate(function: ca.Function, lower: list[np.ndarray], upper: list[np.ndarray]) -> list[np.ndarray]:
    """Enclosures of every output of an SX `function` over the box lower <= inputs <= upper.

    lower, upper: one array per input, of that input's number of nonzeros. Returns one array [nnz, 2] of
    (lo, hi) per output. ValueError for an operation without an interval rule (or an MX Function)."""
    if not function.is_a("SXFunction"):
        function = function.expand()
    outputs = [np.zeros((function.nnz_out(i), 2)) for i in range(function.n_out())]
    work: dict[int, Interval] = {}
    for k in range(function.n_instructions()):
        op = function.instruction_id(k)
        args = function.instruction_input(k)
        out = function.instruction_output(k)
        if op == ca.OP_INPUT:
            work[out[0]] = float(lower[args[0]][args[1]]), float(upper[args[0]][args[1]])
        elif op == ca.OP_OUTPUT:
            outputs[out[0]][out[1]] = work[args[0]]
        elif op == ca.OP_CONST:
            c = function.instruction_constant(k)
            work[out[0]] = c, c
        elif op == ca.OP_CONSTPOW or op == ca.OP_POW:
            base, exponent = work[args[0]], work[args[1]]
            if exponent[0] != exponent[1] or exponent[0] != round(exponent[0]):
                raise ValueError("interval power needs a constant whole exponent")
            work[out[0]] = _pad(*_integer_power(base, int(exponent[0])))
        elif op in _UNARY:
            work[out[0]] = _pad(*_UNARY[op](work[args[0]]))
        elif op in _BINARY:
            work[out[0]] = _pad(*_BINARY[op](work[args[0]], work[args[1]]))
        else:
            raise ValueError(f"no interval rule for CasADi operation {op} in {function.name()}")
    return outputs
