"""Expectations: small expressions over the world, checked at their times.

An expression is parsed with Python's `ast` and checked against a whitelist before anything runs;
it never reaches `eval`. What it may hold:

- numbers (``0.05``, ``1e-3``, ``True``), strings (to compare a parameter with), ``t`` (the time in
  seconds) and ``pi``;
- a body's field: ``aa.x aa.y aa.z aa.pos aa.quat aa.vel aa.angvel aa.speed``;
- a module's port or parameter by name: ``meter.apexes``, ``core.friction``, ``core.floor_tilt.q``
  (a port whose name has dots);
- ``+ - * / // % **``, ``== != < <= > >=`` (chained too), ``and or not``, ``a if c else b``;
- indexing and slicing with whole numbers: ``aa.pos[2]``, ``meter.apexes[1:4]``;
- a list of numbers, which is an array: ``norm(crate.pos - [0, 0.23, 0.1])``;
- calls of ``abs min max sqrt norm all any round len isnan``.

Nothing else: no attribute of any other value, none starting with ``_``, no other call, no
comprehension, lambda, f-string, assignment or keyword argument. A refused piece is named with the
scenario's file:line. Whole numbers stay within `MAX_INT_BITS` (``10**10**10`` is refused, before the
run when it is written with constants, as is any constant part: ``sqrt(-1)``); an expression is at most
`MAX_LENGTH` characters.
"""

from __future__ import annotations

import ast
import math
import operator
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..kernel.errors import DynabrainError
from ..kernel.suggest import did_you_mean

MAX_LENGTH = 1000
"""The longest expression, in characters."""
MAX_DEPTH = 40
"""How deeply an expression's parts may nest."""
MAX_INT_BITS = 4096
"""The largest whole number an expression may compute, in bits (a float beyond 1e308 is inf anyway)."""


def _round(value: Any, ndigits: Any = None) -> Any:
    if ndigits is None:
        return round(value)
    if isinstance(ndigits, bool) or not isinstance(ndigits, (int, np.integer)) or abs(ndigits) > 100:
        raise ExpressionError(f"round() takes a whole number of digits up to 100, got {ndigits!r}")
    return round(value, int(ndigits))


FUNCTIONS: dict[str, Callable[..., Any]] = {
    "abs": abs, "min": min, "max": max, "sqrt": math.sqrt, "norm": np.linalg.norm, "all": all, "any": any,
    "round": _round, "len": len, "isnan": math.isnan,
}
CONSTANTS: dict[str, float] = {"pi": math.pi}
BODY_FIELDS = ("x", "y", "z", "pos", "quat", "vel", "angvel", "speed")
TIME = "t"

_BINARY = {ast.Add: operator.add, ast.Sub: operator.sub, ast.Mult: operator.mul, ast.Div: operator.truediv,
           ast.FloorDiv: operator.floordiv, ast.Mod: operator.mod, ast.Pow: operator.pow}
_COMPARE = {ast.Eq: operator.eq, ast.NotEq: operator.ne, ast.Lt: operator.lt, ast.LtE: operator.le,
            ast.Gt: operator.gt, ast.GtE: operator.ge}
_WORDS = {ast.Lambda: "a lambda", ast.ListComp: "a comprehension", ast.SetComp: "a comprehension",
          ast.DictComp: "a comprehension", ast.GeneratorExp: "a generator", ast.JoinedStr: "an f-string",
          ast.NamedExpr: "an assignment", ast.Dict: "a mapping", ast.Set: "a set", ast.Starred: "a starred value",
          ast.Await: "await", ast.Yield: "yield", ast.YieldFrom: "yield"}

Evaluator = Callable[["Reader"], Any]
_NODES: dict[type, str] = {
    ast.Constant: "_constant", ast.Name: "_name", ast.Attribute: "_attribute", ast.BinOp: "_bin_op",
    ast.UnaryOp: "_unary_op", ast.BoolOp: "_bool_op", ast.Compare: "_compare", ast.IfExp: "_if_exp",
    ast.Call: "_call", ast.List: "_list", ast.Subscript: "_subscript",
}
"""The method of `Expression` that turns each kind of node it allows into a function."""


class ExpressionError(DynabrainError):
    """An expression that is refused (before the run) or that cannot be evaluated (during it)."""


class Reader:
    """What an expression reads from one world: the time, body fields, module ports and parameters.
    A read is resolved the first time it is made, then served by a getter of its own."""

    def __init__(self, world: Any):
        self.world = world
        self._getters: dict[tuple[str, tuple[str, ...]], Callable[[], Any]] = {}

    @property
    def time(self) -> float:
        return self.world.time

    def read(self, base: str, chain: tuple[str, ...]) -> Any:
        getter = self._getters.get((base, chain))
        if getter is None:
            getter = self._getters[(base, chain)] = self._resolve(base, chain)
        return getter()

    def _resolve(self, base: str, chain: tuple[str, ...]) -> Callable[[], Any]:
        world, core = self.world, self.world.core
        if base in world.modules:
            name = ".".join((base, *chain))
            return lambda: world.get(name)
        if core is not None and base in core.bodies():
            if len(chain) != 1 or chain[0] not in BODY_FIELDS:
                raise ExpressionError(f"body {base!r} has no field {'.'.join(chain)!r}; fields: "
                                      + " ".join(BODY_FIELDS))
            return _body_getter(core, base, chain[0])
        raise ExpressionError(f"unknown name {base!r}")


def _body_getter(core: Any, body: str, key: str) -> Callable[[], Any]:
    if key in ("x", "y", "z"):
        i = "xyz".index(key)
        return lambda: float(core.body_pose(body)[0][i])
    if key in ("pos", "quat"):
        i = ("pos", "quat").index(key)
        return lambda: core.body_pose(body)[i]
    if key in ("vel", "angvel"):
        i = ("vel", "angvel").index(key)
        return lambda: core.body_velocity(body)[i]
    return lambda: float(np.linalg.norm(core.body_velocity(body)[0]))


@dataclass(frozen=True)
class Read:
    """A value an expression reads: ``base`` (a body or a module) and the attribute chain after it."""

    base: str
    chain: tuple[str, ...]

    def __str__(self) -> str:
        return ".".join((self.base, *self.chain))


class Expression:
    """A checked expression, turned into nested Python functions of a `Reader`.

    Raises `ExpressionError` naming the first piece that is not allowed."""

    def __init__(self, text: str):
        if not isinstance(text, str):
            raise ExpressionError(f"an expression is a string, got {type(text).__name__}")
        if len(text) > MAX_LENGTH:
            raise ExpressionError(f"the expression is longer than {MAX_LENGTH} characters (MAX_LENGTH)")
        self.text = text
        try:
            tree = ast.parse(text.strip(), mode="eval")
        except SyntaxError as exc:
            raise ExpressionError(f"expression {text!r} is not valid: {exc.msg}") from None
        except (ValueError, RecursionError, MemoryError) as exc:
            raise ExpressionError(f"expression {text!r} is not valid: {exc}") from None
        self.reads: list[Read] = []
        self.names: list[str] = []
        """Bare names other than ``t`` and the constants (each one is a problem for `check_names`)."""
        self._source = text.strip()
        _check_depth(tree.body)
        self._fn = self._compile(tree.body)

    def evaluate(self, reader: Reader) -> Any:
        return self._fn(reader)

    # -- the whitelist, turned into functions ---------------------------------------------------------
    def _refuse(self, node: ast.AST, why: str) -> ExpressionError:
        piece = ast.get_source_segment(self._source, node) or type(node).__name__
        return ExpressionError(f"in {self.text!r}: {piece!r}: {why}")

    def _compile(self, node: ast.AST) -> Evaluator:
        method_name = _NODES.get(type(node))
        if method_name is None:
            what = _WORDS.get(type(node), f"{type(node).__name__} is not part of the expression language")
            raise self._refuse(node, f"{what} is not allowed" if type(node) in _WORDS else what)
        fn = getattr(self, method_name)(node)
        if not isinstance(node, (ast.Constant, ast.Name)) and _is_constant(node):
            try:  # constants only: computed once, so that 10**10**10 is refused before the run
                value = fn(None)  # type: ignore[arg-type]
            except Exception as exc:
                raise self._refuse(node, f"{type(exc).__name__}: {exc}") from None
            if isinstance(value, np.ndarray):
                value.setflags(write=False)
            return lambda r: value
        return fn

    def _constant(self, node: ast.Constant) -> Evaluator:
        value = node.value
        if isinstance(value, (bool, int, float)):
            if isinstance(value, int) and value.bit_length() > MAX_INT_BITS:
                raise self._refuse(node, f"a whole number of more than {MAX_INT_BITS} bits")
            return lambda r: value
        if isinstance(value, str):
            return lambda r: value
        raise self._refuse(node, f"a {type(value).__name__} constant is not allowed (numbers and strings are)")

    def _name(self, node: ast.Name) -> Evaluator:
        name = node.id
        if name == TIME:
            return lambda r: r.time
        if name in CONSTANTS:
            value = CONSTANTS[name]
            return lambda r: value
        if name.startswith("_"):
            raise self._refuse(node, "names starting with _ are not allowed")
        if name in FUNCTIONS:
            raise self._refuse(node, f"{name} is a function: call it, {name}(...)")
        self.names.append(name)

        def bare(r: Reader) -> Any:
            raise ExpressionError(f"{name!r} is not a value")

        return bare

    def _attribute(self, node: ast.Attribute) -> Evaluator:
        chain: list[str] = []
        base: ast.AST = node
        while isinstance(base, ast.Attribute):
            if base.attr.startswith("_"):
                raise self._refuse(base, f"attribute {base.attr!r}: names starting with _ are not allowed")
            chain.append(base.attr)
            base = base.value
        if not isinstance(base, ast.Name):
            raise self._refuse(node, "only bodies and modules have attributes (aa.z, meter.count)")
        if base.id.startswith("_"):
            raise self._refuse(base, "names starting with _ are not allowed")
        if base.id == TIME or base.id in CONSTANTS or base.id in FUNCTIONS:
            raise self._refuse(node, f"{base.id} has no attributes; only bodies and modules do")
        read = Read(base.id, tuple(reversed(chain)))
        if read not in self.reads:
            self.reads.append(read)
        key_base, key_chain = read.base, read.chain
        return lambda r: r.read(key_base, key_chain)

    def _bin_op(self, node: ast.BinOp) -> Evaluator:
        op = _BINARY.get(type(node.op))
        if op is None:
            raise self._refuse(node, f"the operator {type(node.op).__name__} is not allowed (+ - * / // % ** are)")
        left, right = self._compile(node.left), self._compile(node.right)
        guard = _pow_guard if isinstance(node.op, ast.Pow) else _mul_guard if isinstance(node.op, ast.Mult) else None

        def binary(r: Reader) -> Any:
            a, b = left(r), right(r)
            _numeric(a)
            _numeric(b)
            if guard is not None and type(a) in (int, bool) and type(b) in (int, bool):
                guard(a, b)
            return op(a, b)

        return binary

    def _unary_op(self, node: ast.UnaryOp) -> Evaluator:
        operand = self._compile(node.operand)
        if isinstance(node.op, ast.Not):
            return lambda r: not operand(r)
        if isinstance(node.op, (ast.USub, ast.UAdd)):
            op = operator.neg if isinstance(node.op, ast.USub) else operator.pos

            def unary(r: Reader) -> Any:
                value = operand(r)
                _numeric(value)
                return op(value)

            return unary
        raise self._refuse(node, "the operator ~ is not allowed")

    def _bool_op(self, node: ast.BoolOp) -> Evaluator:
        """``and`` / ``or`` as Python has them: the first operand that decides is the value, and the last
        one is returned without a truth test of its own."""
        *heads, last = [self._compile(v) for v in node.values]
        if isinstance(node.op, ast.And):
            def both(r: Reader) -> Any:
                for part in heads:
                    value = part(r)
                    if not value:
                        return value
                return last(r)

            return both

        def either(r: Reader) -> Any:
            for part in heads:
                value = part(r)
                if value:
                    return value
            return last(r)

        return either

    def _compare(self, node: ast.Compare) -> Evaluator:
        ops = []
        for op in node.ops:
            fn = _COMPARE.get(type(op))
            if fn is None:
                raise self._refuse(node, f"the comparison {type(op).__name__} is not allowed (== != < <= > >= are)")
            ops.append(fn)
        first = self._compile(node.left)
        rest = [self._compile(c) for c in node.comparators]
        if len(ops) == 1:
            (op,), (second,) = ops, rest
            return lambda r: op(first(r), second(r))

        def chained(r: Reader) -> Any:
            a = first(r)
            result: Any = True
            for op, nxt in zip(ops, rest, strict=True):
                b = nxt(r)
                result = op(a, b)
                if not result:
                    return result
                a = b
            return result

        return chained

    def _if_exp(self, node: ast.IfExp) -> Evaluator:
        test, body, orelse = self._compile(node.test), self._compile(node.body), self._compile(node.orelse)
        return lambda r: body(r) if test(r) else orelse(r)

    def _call(self, node: ast.Call) -> Evaluator:
        func = node.func
        if not isinstance(func, ast.Name) or func.id not in FUNCTIONS:
            raise self._refuse(func, "only these functions may be called: " + " ".join(FUNCTIONS))
        if node.keywords:
            raise self._refuse(node, "keyword arguments are not allowed")
        fn = FUNCTIONS[func.id]
        args = [self._compile(a) for a in node.args]
        return lambda r: fn(*[a(r) for a in args])

    def _list(self, node: ast.List) -> Evaluator:
        items = [self._compile(e) for e in node.elts]

        def array(r: Reader) -> np.ndarray:
            values = [item(r) for item in items]
            for value in values:
                _numeric(value)
            return np.asarray(values, dtype=np.float64)

        return array

    def _subscript(self, node: ast.Subscript) -> Evaluator:
        value = self._compile(node.value)
        index = self._index(node.slice)
        return lambda r: value(r)[index(r)]

    def _index(self, node: ast.AST) -> Evaluator:
        if isinstance(node, ast.Slice):
            parts = [None if p is None else self._whole(p) for p in (node.lower, node.upper, node.step)]
            lower, upper, step = (p or (lambda r: None) for p in parts)
            return lambda r: slice(lower(r), upper(r), step(r))
        if isinstance(node, ast.Tuple):
            items = [self._index(e) for e in node.elts]
            return lambda r: tuple(i(r) for i in items)
        return self._whole(node)

    def _whole(self, node: ast.AST) -> Evaluator:
        fn = self._compile(node)

        def whole(r: Reader) -> int:
            value = fn(r)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
                raise ExpressionError(f"an index is a whole number, got {value!r}")
            return int(value)

        return whole


def _is_constant(node: ast.AST) -> bool:
    """Whether ``node`` reads nothing from the world: numbers, ``pi``, operators and calls of `FUNCTIONS`
    on them (``sqrt(-1)`` and ``round(1e308*10)`` are then computed, and refused, before the run)."""
    return all(not isinstance(n, ast.Attribute) and (not isinstance(n, ast.Name) or n.id in FUNCTIONS
                                                     or n.id in CONSTANTS) for n in ast.walk(node))


def _check_depth(root: ast.AST) -> None:
    stack = [(root, 1)]
    while stack:
        node, depth = stack.pop()
        if depth > MAX_DEPTH:
            raise ExpressionError(f"the expression nests deeper than {MAX_DEPTH} levels (MAX_DEPTH)")
        stack.extend((child, depth + 1) for child in ast.iter_child_nodes(node))


def _numeric(value: Any) -> None:
    """Arithmetic takes numbers and arrays of numbers, nothing else (no string or list repetition)."""
    if isinstance(value, (int, float)):
        return
    if isinstance(value, (np.ndarray, np.generic)) and value.dtype.kind in "biuf":
        return
    raise ExpressionError(f"arithmetic takes numbers and arrays of numbers, got {type(value).__name__}")


def _pow_guard(base: int, exponent: int) -> None:
    if exponent > 0 and abs(base) > 1 and exponent * base.bit_length() > MAX_INT_BITS:
        raise ExpressionError(f"{base}**{exponent} is larger than {MAX_INT_BITS} bits (MAX_INT_BITS)")


def _mul_guard(a: int, b: int) -> None:
    if a.bit_length() + b.bit_length() > MAX_INT_BITS:
        raise ExpressionError(f"a product larger than {MAX_INT_BITS} bits (MAX_INT_BITS)")


@dataclass
class Expectation:
    """``that`` must hold at tick ``tick`` (or every tick in ``[start, end]``)."""

    that: str
    start: int
    end: int
    label: str
    line: int | None = None
    passed: bool | None = None
    detail: str = ""
    expression: Expression = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.expression = Expression(self.that)

    def names(self) -> list[tuple[str, str | None]]:
        """(name, dotted attribute chain or None) pairs the expression reads: ``core.floor_tilt.q``
        gives ("core", "floor_tilt.q")."""
        return ([(r.base, ".".join(r.chain)) for r in self.expression.reads]
                + [(n, None) for n in dict.fromkeys(self.expression.names)])

    def check(self, world: Any, namespace: Reader) -> bool:
        try:
            value = self.expression.evaluate(namespace)
            ok = bool(np.all(value))
        except Exception as exc:
            self.passed, self.detail = False, f"error evaluating: {type(exc).__name__}: {exc}"
            return False
        if not ok:
            self.detail = f"false at t={world.time:.6g}s ({_explain(self.expression, namespace)})"
            self.passed = False
        elif self.passed is None and world.tick_count >= self.end:
            self.passed = True
        return ok


def _explain(expression: Expression, reader: Reader) -> str:
    """Values of the reads in ``expression``, to show why it failed."""
    parts = []
    for read in expression.reads:
        try:
            value = reader.read(read.base, read.chain)
        except Exception:
            continue
        parts.append(f"{read} = {np.round(value, 6) if isinstance(value, np.ndarray) else _fmt(value)}")
    return ", ".join(parts) or "no values"


def _fmt(value: Any) -> str:
    return f"{value:.6g}" if isinstance(value, float) else repr(value)


def namespace_for(world: Any) -> Reader:
    """What the expectations of ``world`` read through (one per run: it keeps resolved reads)."""
    return Reader(world)


def check_names(exp: Expectation, world: Any, later: set[str] = frozenset()) -> list[str]:
    """Problems with the names an expectation reads (unknown bodies, modules, ports, params).
    ``later`` names modules the scenario's events add: their ports are checked when they exist."""
    bodies = set(world.core.bodies()) if world.core is not None else set()
    known = [*world.modules, *bodies, *later, TIME, *CONSTANTS]
    problems = []
    for name in dict.fromkeys(exp.expression.names):
        if name in world.modules or name in bodies or name in later:
            kind = "a body" if name in bodies and name not in world.modules else "a module"
            hint = f"one of its fields ({name}.z; {' '.join(BODY_FIELDS)})" if kind == "a body" else \
                f"one of its ports or parameters ({name}.<port>)"
            problems.append(f"in {exp.that!r}: {name!r} is {kind}; read {hint}")
        else:
            problems.append(f"unknown name {name!r} in {exp.that!r}" + did_you_mean(name, known))
    for read in exp.expression.reads:
        if read.base in world.modules:
            problem = _check_signal(world, str(read))
            if problem:
                problems.append(f"in {exp.that!r}: {problem}")
        elif read.base in bodies:
            if len(read.chain) != 1 or read.chain[0] not in BODY_FIELDS:
                problems.append(f"body {read.base!r} has no field {'.'.join(read.chain)!r}"
                                + did_you_mean(read.chain[0], BODY_FIELDS) + f"; fields: {' '.join(BODY_FIELDS)}")
        elif read.base not in later:
            problems.append(f"unknown name {read.base!r} in {exp.that!r}" + did_you_mean(read.base, known))
    return problems


def _check_signal(world: Any, name: str) -> str | None:
    """None when ``name`` (``module.port``, ``core.floor_tilt.q``, ``servo.kp``) can be read."""
    try:
        world.get(name)
    except DynabrainError as exc:
        return str(exc)
    return None
