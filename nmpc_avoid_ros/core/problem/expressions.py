"""Safe parsing of algebraic region expressions into CasADi expressions.

Users write keep-in regions such as ``abs(x1*x2) <= 2`` or ``sqrt(px**2 + py**2) >= 1`` in
configuration files. The text is parsed with :mod:`ast` and translated node by node into CasADi
operations over a whitelist; nothing is ever evaluated or compiled by Python, so the text cannot
reach attributes, builtins or imports. Size, nesting and node-count limits bound the work done on
hostile input before and after ``ast.parse``.
"""

from __future__ import annotations

import ast
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass

import casadi as ca

from ..errors import ExpressionError

Expr = ca.SX | ca.MX

MAX_EXPRESSION_LENGTH = 1000  # characters
MAX_DEPTH = 32  # nesting depth of expression nodes
MAX_NODES = 500
MAX_EXPONENT = 16  # |p| of a constant exponent in x**p
MAX_CONSTANT = 1e12  # |c| of a numeric literal

ALLOWED_FUNCTIONS: dict[str, Callable[..., Expr]] = {
    "abs": ca.fabs,
    "sqrt": ca.sqrt,
    "exp": ca.exp,
    "log": ca.log,
    "sin": ca.sin,
    "cos": ca.cos,
    "tan": ca.tan,
    "atan": ca.atan,
    "atan2": ca.atan2,
    "tanh": ca.tanh,
    "min": ca.fmin,  # 2 arguments
    "max": ca.fmax,  # 2 arguments
    "hypot": lambda a, b: ca.sqrt(a**2 + b**2),
}
_ARITY = {"atan2": 2, "min": 2, "max": 2, "hypot": 2}  # every other function takes 1 argument
ALLOWED_CONSTANTS = {"pi": math.pi, "e": math.e}

_BINOPS: dict[type, Callable[[Expr, Expr], Expr]] = {
    ast.Add: lambda a, b: a + b,
    ast.Sub: lambda a, b: a - b,
    ast.Mult: lambda a, b: a * b,
    ast.Div: lambda a, b: a / b,
}
_KEEP_IN_OPS = (ast.Lt, ast.LtE, ast.Gt, ast.GtE)
# Operator/context tokens are shared singletons, not sub-expressions; they don't count as nodes.
_TOKENS = (ast.expr_context, ast.operator, ast.unaryop, ast.cmpop, ast.boolop)
_NAMES = {
    ast.Attribute: "attribute access", ast.Subscript: "subscript", ast.Lambda: "lambda",
    ast.ListComp: "list comprehension", ast.SetComp: "set comprehension",
    ast.DictComp: "dict comprehension", ast.GeneratorExp: "generator expression",
    ast.IfExp: "conditional expression", ast.BoolOp: "boolean operator ('and'/'or')",
    ast.JoinedStr: "f-string", ast.NamedExpr: "assignment expression (':=')",
    ast.Starred: "starred expression", ast.Compare: "comparison", ast.Tuple: "tuple",
    ast.List: "list", ast.Dict: "dict", ast.Set: "set", ast.Slice: "slice",
}


@dataclass(frozen=True, eq=False)  # eq=False: comparing CasADi expressions has no truth value
class KeepInConstraint:
    """A keep-in region ``g <= 0``; outside it ``g > 0`` and the penalty is ``max(0, g)**2``."""

    text: str
    g: Expr


def parse_expression(text: str, symbols: Mapping[str, Expr]) -> Expr:
    """Translate an arithmetic expression over ``symbols`` into a CasADi expression.

    Raises ExpressionError for anything outside the whitelist (the message names the offending
    part) and TypeError if ``symbols`` is not a mapping of names to scalar SX/MX of one kind.
    """
    source, tree = _parse(text)
    return _Translator(source, symbols).expr(tree.body)


def parse_keep_in(text: str, symbols: Mapping[str, Expr]) -> KeepInConstraint:
    """Parse ``lhs <= rhs`` / ``lhs >= rhs`` (or ``<`` / ``>``) into ``g <= 0``.

    ``g = lhs - rhs`` for ``<=``/``<`` and ``g = rhs - lhs`` for ``>=``/``>`` (strictness is
    irrelevant for a penalty). Exactly one comparison is allowed: no chains, ``==`` or ``!=``.
    """
    source, tree = _parse(text)
    node = tree.body
    if not isinstance(node, ast.Compare):
        raise ExpressionError(f"expected one comparison 'lhs <= rhs' or 'lhs >= rhs' in {text!r}")
    if len(node.ops) != 1:
        raise ExpressionError(f"chained comparison is not allowed: {text!r}")
    if not isinstance(node.ops[0], _KEEP_IN_OPS):
        raise ExpressionError(
            f"comparison operator {type(node.ops[0]).__name__} is not allowed"
            " (use <=, <, >= or >; '==' and '!=' do not describe a region)"
        )
    tr = _Translator(source, symbols)
    lhs, rhs = tr.expr(node.left), tr.expr(node.comparators[0])
    g = lhs - rhs if isinstance(node.ops[0], (ast.Lt, ast.LtE)) else rhs - lhs
    return KeepInConstraint(text=text, g=g)


def _parse(text: object) -> tuple[str, ast.Expression]:
    """Check the raw text, parse it and bound the tree size before any recursive work."""
    if not isinstance(text, str):
        raise ExpressionError(f"expression must be a str, got {type(text).__name__}")
    # Length first: ast.parse itself is recursive and its cost grows with the input.
    if len(text) > MAX_EXPRESSION_LENGTH:
        raise ExpressionError(
            f"expression is too long ({len(text)} > {MAX_EXPRESSION_LENGTH} characters)"
        )
    source = text.strip()  # eval-mode parsing rejects leading indentation
    if not source:
        raise ExpressionError("expression is empty")
    try:
        tree = ast.parse(source, mode="eval")
    except SyntaxError as exc:  # also covers statements such as 'import os'
        raise ExpressionError(f"invalid syntax: {exc.msg} (column {exc.offset})") from None
    except (RecursionError, MemoryError, ValueError, OverflowError) as exc:
        raise ExpressionError(f"expression cannot be parsed: {type(exc).__name__}") from None
    # Iterative walk so that the later recursive translation is bounded by MAX_DEPTH.
    stack, count = [(tree.body, 1)], 0
    while stack:
        node, depth = stack.pop()
        count += 1
        if depth > MAX_DEPTH:
            raise ExpressionError(f"expression is nested too deeply (> {MAX_DEPTH} levels)")
        if count > MAX_NODES:
            raise ExpressionError(f"expression has too many nodes (> {MAX_NODES})")
        stack.extend(
            (child, depth + 1)
            for child in ast.iter_child_nodes(node)
            if not isinstance(child, _TOKENS)
        )
    return source, tree


class _Translator:
    """Recursive whitelist translation of an already size-checked AST into CasADi."""

    def __init__(self, source: str, symbols: Mapping[str, Expr]) -> None:
        if not isinstance(symbols, Mapping):
            raise TypeError("symbols must be a mapping of names to CasADi SX/MX")
        kinds = {type(v) for v in symbols.values()}
        if not kinds <= {ca.SX, ca.MX} or len(kinds) > 1:
            raise TypeError("symbols must all be CasADi SX or all MX")
        if any(not v.is_scalar() for v in symbols.values()):
            raise TypeError("symbols must be scalar")
        self.source, self.symbols = source, symbols
        self.kind = kinds.pop() if kinds else ca.SX  # constants are lifted to the same kind

    def _seg(self, node: ast.AST) -> str:
        seg = ast.get_source_segment(self.source, node) or type(node).__name__
        return seg if len(seg) <= 60 else seg[:57] + "..."

    def _refuse(self, what: str, node: ast.AST) -> ExpressionError:
        return ExpressionError(f"{what} is not allowed: {self._seg(node)!r}")

    def _number(self, node: ast.AST) -> float | None:
        """Value of a numeric literal, optionally signed; None for anything else."""
        sign = 1.0
        if isinstance(node, ast.UnaryOp) and isinstance(node.op, (ast.UAdd, ast.USub)):
            sign, node = (-1.0 if isinstance(node.op, ast.USub) else 1.0), node.operand
        if not isinstance(node, ast.Constant):
            return None
        v = node.value
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            return None
        return sign * self._check_constant(v, node)

    def _check_constant(self, v: object, node: ast.Constant) -> float:
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            kind = {str: "string", bytes: "bytes", bool: "boolean", complex: "complex"}
            raise self._refuse(f"{kind.get(type(v), type(v).__name__)} constant", node)
        if isinstance(v, float) and not math.isfinite(v):
            raise ExpressionError(f"constant {self._seg(node)!r} is not finite")
        if abs(v) > MAX_CONSTANT:  # compare before float() so huge ints cannot overflow
            raise ExpressionError(f"constant {self._seg(node)!r} exceeds {MAX_CONSTANT:g}")
        return float(v)

    def expr(self, node: ast.AST) -> Expr:
        if isinstance(node, ast.Constant):
            return self.kind(self._check_constant(node.value, node))
        if isinstance(node, ast.Name):
            if node.id in self.symbols:  # symbols shadow constants of the same name
                return self.symbols[node.id]
            if node.id in ALLOWED_CONSTANTS:
                return self.kind(ALLOWED_CONSTANTS[node.id])
            known = ", ".join(self.symbols) or "none"
            raise ExpressionError(f"unknown name {node.id!r} (known: {known})")
        if isinstance(node, ast.UnaryOp) and isinstance(node.op, (ast.UAdd, ast.USub)):
            operand = self.expr(node.operand)
            return -operand if isinstance(node.op, ast.USub) else operand
        if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Pow):
            p = self._number(node.right)  # a symbolic or huge exponent could explode the value
            if p is None or abs(p) > MAX_EXPONENT:
                raise ExpressionError(
                    f"exponent must be a numeric constant with |p| <= {MAX_EXPONENT}:"
                    f" {self._seg(node)!r}"
                )
            return self.expr(node.left) ** p
        if isinstance(node, ast.BinOp) and type(node.op) in _BINOPS:
            left, right = self.expr(node.left), self.expr(node.right)
            if isinstance(node.op, ast.Div) and right.is_zero():
                raise ExpressionError(f"division by constant zero: {self._seg(node)!r}")
            return _BINOPS[type(node.op)](left, right)
        if isinstance(node, (ast.BinOp, ast.UnaryOp)):  # //, %, @, bit ops, 'not', '~'
            raise self._refuse(f"operator {type(node.op).__name__}", node)
        if isinstance(node, ast.Call):
            return self._call(node)
        raise self._refuse(_NAMES.get(type(node), type(node).__name__), node)

    def _call(self, node: ast.Call) -> Expr:
        allowed = ", ".join(ALLOWED_FUNCTIONS)
        if not isinstance(node.func, ast.Name):
            raise ExpressionError(
                f"only allowed functions called by bare name may be called (allowed: {allowed}):"
                f" {self._seg(node)!r}"
            )
        name = node.func.id
        if name not in ALLOWED_FUNCTIONS:
            raise ExpressionError(f"function {name!r} is not allowed (allowed: {allowed})")
        if node.keywords:
            raise self._refuse(f"keyword argument to {name!r}", node)
        if any(isinstance(a, ast.Starred) for a in node.args):
            raise self._refuse(f"starred argument to {name!r}", node)
        arity = _ARITY.get(name, 1)
        if len(node.args) != arity:
            raise ExpressionError(
                f"function {name!r} takes {arity} argument(s), got {len(node.args)}"
            )
        return ALLOWED_FUNCTIONS[name](*(self.expr(a) for a in node.args))
