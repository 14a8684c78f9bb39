"""Tests of the safe algebraic-expression parser (nmpc_avoid_ros.core.problem.expressions)."""

from __future__ import annotations

import math
import time

import casadi as ca
import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from nmpc_avoid_ros.core.errors import ExpressionError
from nmpc_avoid_ros.core.problem.expressions import (
    MAX_DEPTH,
    MAX_EXPRESSION_LENGTH,
    KeepInConstraint,
    parse_expression,
    parse_keep_in,
)

NAMES = ("x1", "x2", "u")
POINTS = [(0.3, -1.2, 0.7), (3.0, 1.0, -2.0), (-0.5, 0.25, 1.5), (1.7, 2.2, 0.1)]


def sx_symbols() -> dict[str, ca.SX]:
    return {n: ca.SX.sym(n) for n in NAMES}


def evaluate(expr: ca.SX, syms: dict[str, ca.SX], point: tuple[float, ...]) -> float:
    f = ca.Function("f", [syms[n] for n in NAMES], [expr])
    return float(f(*point))


# (text, numpy reference over x1, x2, u)
VALID = [
    ("x1*x2 - 2", lambda a, b, u: a * b - 2),
    ("abs(x1*x2)", lambda a, b, u: abs(a * b)),
    ("(x1-1)**2 + (x2+0.5)**2", lambda a, b, u: (a - 1) ** 2 + (b + 0.5) ** 2),
    ("sqrt(x1**2 + x2**2)", lambda a, b, u: np.sqrt(a**2 + b**2)),
    ("hypot(x1, x2) - 1", lambda a, b, u: np.hypot(a, b) - 1),
    ("atan2(x2, x1) + tanh(u)", lambda a, b, u: np.arctan2(b, a) + np.tanh(u)),
    ("min(x1, x2) * max(x1, u)", lambda a, b, u: min(a, b) * max(a, u)),
    ("exp(-x1**2) + log(1 + x2**2)", lambda a, b, u: np.exp(-(a**2)) + np.log(1 + b**2)),
    ("sin(pi*x1) - cos(e*x2) + tan(0.1*u)",
     lambda a, b, u: np.sin(np.pi * a) - np.cos(np.e * b) + np.tan(0.1 * u)),
    ("x1 ** -2 + +u / 4 - -x2", lambda a, b, u: a**-2 + u / 4 + b),
    ("2 ** 3 * x1 / (x2 - 7)", lambda a, b, u: 8 * a / (b - 7)),
    ("abs(x1) ** 0.5", lambda a, b, u: abs(a) ** 0.5),
]


@pytest.mark.parametrize("point", POINTS)
@pytest.mark.parametrize(("text", "ref"), VALID, ids=[t for t, _ in VALID])
def test_valid_expressions_evaluate_like_numpy(text, ref, point) -> None:
    syms = sx_symbols()
    assert evaluate(parse_expression(text, syms), syms, point) == pytest.approx(ref(*point))


def test_mx_symbols_and_constant_only_expression() -> None:
    syms = {"x1": ca.MX.sym("x1")}
    g = parse_expression("2*x1 + pi", syms)
    assert isinstance(g, ca.MX)
    assert float(ca.Function("f", [syms["x1"]], [g])(1.5)) == pytest.approx(3 + math.pi)
    assert float(ca.evalf(parse_expression("1 + 2 * 3", {}))) == 7.0


def test_symbols_shadow_constants() -> None:
    syms = {"e": ca.SX.sym("e")}
    assert float(ca.Function("f", [syms["e"]], [parse_expression("e + 1", syms)])(5.0)) == 6.0


def test_keep_in_sign_convention() -> None:
    syms = sx_symbols()
    le = parse_keep_in("x1*x2 - 2 <= 0", syms)
    assert isinstance(le, KeepInConstraint) and le.text == "x1*x2 - 2 <= 0"
    assert evaluate(le.g, syms, (3.0, 1.0, 0.0)) == pytest.approx(1.0)  # outside: g > 0
    assert evaluate(le.g, syms, (1.0, 1.0, 0.0)) == pytest.approx(-1.0)  # inside: g < 0
    for text in ("x1*x2 - 2 >= 0", "0 <= x1*x2 - 2", "x1*x2 - 2 > 0"):
        ge = parse_keep_in(text, syms)
        assert evaluate(ge.g, syms, (3.0, 1.0, 0.0)) == pytest.approx(-1.0), text
        assert evaluate(ge.g, syms, (1.0, 1.0, 0.0)) == pytest.approx(1.0), text
    lt = parse_keep_in("x1*x2 < 2", syms)
    assert evaluate(lt.g, syms, (3.0, 1.0, 0.0)) == pytest.approx(1.0)


@pytest.mark.parametrize("point", POINTS + [(2.0, -3.0, 0.0), (-4.0, -1.0, 0.0)])
def test_abs_keep_in_equals_max_of_paper_constraints(point) -> None:
    syms = sx_symbols()
    g = evaluate(parse_keep_in("abs(x1*x2) <= 2", syms).g, syms, point)
    g1 = evaluate(parse_keep_in("x1*x2 - 2 <= 0", syms).g, syms, point)
    g2 = evaluate(parse_keep_in("-x1*x2 - 2 <= 0", syms).g, syms, point)
    assert g == pytest.approx(max(g1, g2))


def test_circle_keep_out() -> None:
    syms = {"px": ca.SX.sym("px"), "py": ca.SX.sym("py")}
    g = parse_keep_in("sqrt(px**2+py**2) >= 1", syms).g
    f = ca.Function("f", [syms["px"], syms["py"]], [g])
    assert float(f(0.0, 0.5)) == pytest.approx(0.5)
    assert float(f(3.0, 4.0)) == pytest.approx(-4.0)


# (input, parser, a fragment the message must contain)
HOSTILE = [
    ("__import__('os')", parse_expression, "function '__import__' is not allowed"),
    ("x1.__class__", parse_expression, "attribute access is not allowed"),
    ("open('f')", parse_expression, "function 'open' is not allowed (allowed: abs, sqrt"),
    ("[x for x in y]", parse_expression, "list comprehension is not allowed"),
    ("lambda: 1", parse_expression, "lambda is not allowed"),
    ("x1 if x1 else x2", parse_expression, "conditional expression is not allowed"),
    ("x1 and x2", parse_expression, "boolean operator"),
    ("not x1", parse_expression, "operator Not is not allowed"),
    ("'abc'", parse_expression, "string constant is not allowed"),
    ("b'abc'", parse_expression, "bytes constant is not allowed"),
    ("f'{x1}'", parse_expression, "f-string is not allowed"),
    ("True + x1", parse_expression, "boolean constant is not allowed"),
    ("1j * x1", parse_expression, "complex constant is not allowed"),
    ("x1[0]", parse_expression, "subscript is not allowed"),
    ("(y := 1)", parse_expression, "assignment expression"),
    ("max(*x1)", parse_expression, "starred argument"),
    ("abs(x=1)", parse_expression, "keyword argument"),
    ("f(x=1)", parse_expression, "function 'f' is not allowed"),
    ("x1.sin()", parse_expression, "bare name"),
    ("sqrt(x1, x2)", parse_expression, "takes 1 argument"),
    ("atan2(x1)", parse_expression, "takes 2 argument"),
    ("x1 // 2", parse_expression, "operator FloorDiv is not allowed"),
    ("x1 @ x2", parse_expression, "operator MatMult is not allowed"),
    ("2**10**10", parse_expression, "exponent must be a numeric constant with |p| <= 16"),
    ("x1**x2", parse_expression, "exponent must be a numeric constant"),
    ("x1**17", parse_expression, "exponent must be a numeric constant"),
    ("x1**--2", parse_expression, "exponent must be a numeric constant"),
    ("1e400", parse_expression, "not finite"),
    ("x1 * 2e12", parse_expression, "exceeds 1e+12"),
    ("x1 / 0", parse_expression, "division by constant zero"),
    ("x1 / (2 - 2.0)", parse_expression, "division by constant zero"),
    ("import os", parse_expression, "invalid syntax"),
    ("x1 +", parse_expression, "invalid syntax"),
    ("x1 <= 2", parse_expression, "comparison is not allowed"),
    ("x1 <= 2 <= 3", parse_keep_in, "chained comparison"),
    ("x1 == 2", parse_keep_in, "'==' and '!='"),
    ("x1 != 2", parse_keep_in, "'==' and '!='"),
    ("x1 + 2", parse_keep_in, "expected one comparison"),
    ("x1 <= open('f')", parse_keep_in, "function 'open' is not allowed"),
    ("x3 + 1", parse_expression, "unknown name 'x3' (known: x1, x2, u)"),
    ("x3 <= 1", parse_keep_in, "unknown name 'x3'"),
    ("", parse_expression, "empty"),
    ("   ", parse_keep_in, "empty"),
    (None, parse_expression, "must be a str"),
    (5, parse_keep_in, "must be a str"),
    ("x1 + 1" * 200, parse_expression, "too long"),
    ("-" * (MAX_DEPTH + 1) + "x1", parse_expression, "nested too deeply"),
    ("1," * 500, parse_expression, "too many nodes"),
    ("1<" * 499 + "1", parse_keep_in, "too many nodes"),
]


@pytest.mark.parametrize(
    ("text", "parser", "reason"), HOSTILE, ids=[repr(h[0])[:40] for h in HOSTILE]
)
def test_hostile_input_refused_with_reason(text, parser, reason) -> None:
    with pytest.raises(ExpressionError) as info:
        parser(text, sx_symbols())
    assert reason in str(info.value)


def test_limits_are_inclusive() -> None:
    syms = sx_symbols()
    parse_expression("-" * (MAX_DEPTH - 1) + "x1", syms)  # exactly MAX_DEPTH levels
    parse_expression("x1**-16 + x1**16.0", syms)
    parse_expression("x1 + " + " " * (MAX_EXPRESSION_LENGTH - 6) + "1", syms)
    parse_expression("x1 * 1e12", syms)


def test_bad_symbols_mapping_is_a_type_error() -> None:
    with pytest.raises(TypeError):
        parse_expression("x", {"x": 1.0})
    with pytest.raises(TypeError):
        parse_expression("x + y", {"x": ca.SX.sym("x"), "y": ca.MX.sym("y")})


WORST_CASES = {
    "parens_1e5": "(" * 100_000 + "x1" + ")" * 100_000,
    "parens_below_limit": "(" * 499 + "x1" + ")" * 499,
    "unary_1e5": "-" * 100_000 + "x1",
    "unary_below_limit": "-" * 998 + "x1",
    "not_chain": "not " * 249 + "x1",
    "power_chain": "x1" + "**2" * 332,
    "sum_10k": " + ".join(["x1"] * 10_000),
    "sum_below_limit": "+".join(["1"] * 500),
    "string_1e6": "x" * 1_000_000,
    "calls_below_limit": "abs(" * 200 + "x1" + ")" * 200,
}


@pytest.mark.parametrize("text", WORST_CASES.values(), ids=WORST_CASES.keys())
@pytest.mark.parametrize("parser", [parse_expression, parse_keep_in])
def test_worst_case_refused_quickly(text, parser) -> None:
    start = time.perf_counter()
    with pytest.raises(ExpressionError):
        parser(text, sx_symbols())
    assert time.perf_counter() - start < 0.2


@settings(max_examples=300, deadline=None)
@given(st.one_of(st.text(), st.text(alphabet="x12u()+-*/<=>.,e abspqrtin_[]'\"0369")))
def test_arbitrary_text_only_raises_expression_error(text) -> None:
    for parser in (parse_expression, parse_keep_in):
        try:
            parser(text, sx_symbols())
        except ExpressionError:
            pass


# --- random valid arithmetic trees vs. a tiny reference evaluator ---------------------------
LEAVES = st.one_of(
    st.tuples(st.just("sym"), st.sampled_from(NAMES)),
    st.tuples(st.just("num"), st.integers(0, 9) | st.sampled_from([0.5, 1.25, 2.75])),
)
TREES = st.recursive(
    LEAVES,
    lambda sub: st.one_of(
        st.tuples(st.sampled_from(["+", "-", "*"]), sub, sub),
        st.tuples(st.just("neg"), sub),
    ),
    max_leaves=16,
)


def render(t) -> str:
    if t[0] in ("sym", "num"):
        return str(t[1])
    if t[0] == "neg":
        return f"-({render(t[1])})"
    return f"({render(t[1])} {t[0]} {render(t[2])})"


def reference(t, env: dict[str, float]) -> tuple[float, float]:
    """(value, magnitude): magnitude bounds |intermediates| and so the rounding error."""
    kind = t[0]
    if kind in ("sym", "num"):
        v = env[t[1]] if kind == "sym" else float(t[1])
        return v, abs(v)
    if kind == "neg":
        v, m = reference(t[1], env)
        return -v, m
    (a, ma), (b, mb) = reference(t[1], env), reference(t[2], env)
    if kind == "*":
        return a * b, ma * mb
    return (a + b if kind == "+" else a - b), ma + mb


def depth(t) -> int:
    return 1 if t[0] in ("sym", "num") else 1 + max(depth(c) for c in t[1:])


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(TREES, st.tuples(*[st.floats(-3, 3, allow_nan=False)] * 3))
def test_random_trees_match_reference(tree, point) -> None:
    assume(depth(tree) <= MAX_DEPTH)
    syms = sx_symbols()
    got = evaluate(parse_expression(render(tree), syms), syms, point)
    want, magnitude = reference(tree, dict(zip(NAMES, point)))
    assert abs(got - want) <= 1e-12 * (1.0 + magnitude)
