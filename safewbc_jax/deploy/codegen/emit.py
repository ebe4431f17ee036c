"""A closed jaxpr -> one C99 function.

    src = emit_function("prepare", closed_jaxpr)      # a ``CFunction``
    src.code                                          # the definitions, static buffers
    src.prototype                                     # void prepare(const double *in0, ...)

Every array of the jaxpr is a static buffer of its dtype (``double``, ``float``, ``int32_t``,
``int64_t``, ``uint8_t`` for booleans), given back to a pool after its last use and taken
again by a later array of the same C type (buffers are reused by liveness). The model's
constants (the jaxpr's consts) are ``static const`` arrays written as hexadecimal floats, so
they are exact. ``jit`` and the custom-derivative calls are inlined; ``scan`` and
``while`` become C loops, ``cond`` a ``switch``; ``cholesky``, ``lu`` and
``triangular_solve`` small C routines (``RUNTIME``). A primitive without a rule is refused
by name (``UnsupportedPrimitive``) before anything is written.

The C follows XLA's semantics where they differ from C's: ``max``/``min`` propagate NaN,
integer division truncates, gathers clamp their start indices (or fill, in
``FILL_OR_DROP`` mode), sorts put NaN last. Two exceptions, both for sparse operands whose
zeros are known only at run time: the triangular solve skips the zero entries of its
triangle (a tree-sparse Cholesky factor has about half), and a product in row form skips
the zero entries of its lhs (``ZERO_SKIP_MIN``; the contact and chain rows have about
three quarters). A non-finite entry of the other operand then does not spread through
those zeros as a dense product would; finite values give the same numbers (up to the sign
of an exact zero).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np


CUT = "\x00cut"          # a split point of a function's body (``Emitter.cut``)
PART_LINES = 400        # lines of C per part function


class UnsupportedPrimitive(ValueError):
    """A primitive the C emitter has no rule for (its name, and where it came from)."""


CTYPES = {np.dtype(np.float64): "double", np.dtype(np.float32): "float",
          np.dtype(np.int32): "int32_t", np.dtype(np.int64): "int64_t",
          np.dtype(np.uint32): "uint32_t", np.dtype(np.uint8): "uint8_t",
          np.dtype(np.bool_): "uint8_t", np.dtype(np.int8): "int8_t",
          np.dtype(np.int16): "int16_t", np.dtype(np.uint64): "uint64_t"}


def ctype(dtype) -> str:
    dt = np.dtype(dtype)
    if dt not in CTYPES:
        raise UnsupportedPrimitive(f"dtype {dt} has no C type here")
    return CTYPES[dt]


def c_literal(value, dtype) -> str:
    """An exact C literal of ``value`` in ``dtype`` (hexadecimal for floats)."""
    dt = np.dtype(dtype)
    if dt.kind == "f":
        x = float(value)
        if math.isnan(x):
            return "NAN"
        if math.isinf(x):
            return "INFINITY" if x > 0 else "(-INFINITY)"
        lit = x.hex()
        return f"({lit}f)" if dt == np.float32 else f"({lit})"
    if dt.kind == "b":
        return "1" if bool(value) else "0"
    v = int(value)
    if dt.itemsize == 8:
        return f"INT64_C({v})" if dt.kind == "i" else f"UINT64_C({v})"
    return f"({v})"


@dataclass
class Buf:
    """An array: its C name, C type, shape; ``const`` for the jaxpr's constants and the
    function's inputs (never written, never pooled)."""

    name: str
    ctype: str
    shape: tuple
    dtype: Any
    const: bool = False
    value: Any = field(default=None, repr=False, compare=False)  # a constant's numbers

    @property
    def size(self) -> int:
        return int(math.prod(self.shape))

    def at(self, idx: str) -> str:
        return f"{self.name}[{idx}]"


@dataclass
class Lit:
    """A scalar literal of the jaxpr."""

    text: str
    shape: tuple = ()
    dtype: Any = None
    value: Any = field(default=None, repr=False, compare=False)

    @property
    def size(self) -> int:
        return 1

    def at(self, idx: str) -> str:
        return self.text


def strides(shape) -> list[int]:
    out, s = [], 1
    for d in reversed(shape):
        out.append(s)
        s *= int(d)
    return out[::-1]


def flat_index(idx: list[str], shape) -> str:
    """The row-major flat index of the multi-index ``idx`` into ``shape``."""
    terms = [f"({i})*{s}" if s != 1 else f"({i})" for i, s, n in zip(idx, strides(shape), shape)
             if n != 1]
    return " + ".join(terms) if terms else "0"


@dataclass
class CFunction:
    """One emitted function: its name, the C code of its buffers and body, its prototype,
    the shapes and dtypes of its inputs and outputs."""

    name: str
    code: str
    prototype: str
    in_avals: list
    out_avals: list
    buffer_bytes: int


GROW = True
"""Where no free buffer of the type is large enough, the largest free one grows to the
size (its declaration is written last) instead of a new buffer being made: fewer buffers,
less memory for the step to bring back into cache (benchmarks/README.md, "A leaner
output")."""


@dataclass
class _Pool:
    free: dict = field(default_factory=dict)       # ctype -> [(size, name)]
    decls: list = field(default_factory=list)      # (ctype, name, size)
    count: int = 0

    def take(self, prefix: str, ct: str, size: int) -> str:
        free = self.free.setdefault(ct, [])
        best = None
        for k, (s, _name) in enumerate(free):
            if s >= size and (best is None or s < free[best][0]):
                best = k
        if best is not None:
            return free.pop(best)[1]
        if free and GROW:      # none large enough: the largest free one grows to the size
            k = max(range(len(free)), key=lambda i: free[i][0])
            name = free.pop(k)[1]
            self.decls = [(c, n, max(s, size) if n == name else s) for c, n, s in self.decls]
            return name
        self.count += 1
        name = f"{prefix}_b{self.count}"
        self.decls.append((ct, name, max(size, 1)))
        return name

    def give(self, ct: str, name: str) -> None:
        size = next(s for c, n, s in self.decls if n == name)
        self.free.setdefault(ct, []).append((size, name))


class Emitter:
    """Writes one function's body (``emit_function``)."""

    def __init__(self, prefix: str):
        self.prefix = prefix
        self.lines: list[str] = []
        self.consts: list[str] = []
        self.pool = _Pool()
        self.depth = 1
        self.n_tmp = 0
        self.pooled: dict[str, str] = {}         # buffer name -> its ctype, for the pool
        self.refs: dict[str, int] = {}           # buffer name -> the arrays it holds
        self.direct: dict = {}                   # top-level var -> the output it is written to
        self.dying: frozenset = frozenset()      # positions of the equation's inputs it may take

    # -- output
    def w(self, line: str) -> None:
        self.lines.append("    " * self.depth + line)

    def cut(self) -> None:
        """A place between two top-level equations where the body may be split into
        functions (small functions keep the C compiler's time linear in their number)."""
        if self.depth == 1:
            self.lines.append(CUT)

    def tmp(self, prefix: str = "t") -> str:
        self.n_tmp += 1
        return f"{prefix}{self.n_tmp}"

    def new_buf(self, aval) -> Buf:
        ct = ctype(aval.dtype)
        shape = tuple(int(d) for d in aval.shape)
        name = self.pool.take(self.prefix, ct, math.prod(shape))
        self.pooled[name] = ct
        self.refs[name] = 1
        return Buf(name, ct, shape, np.dtype(aval.dtype))

    def alias(self, b: Buf, aval) -> Buf:
        """Another array on ``b``'s storage (a reshape: same elements, same order)."""
        if b.name in self.pooled:
            self.refs[b.name] += 1
        return Buf(b.name, b.ctype, tuple(int(d) for d in aval.shape), np.dtype(aval.dtype),
                   const=b.const)

    def release(self, b) -> None:
        """One array less on ``b``'s storage; the last gives the buffer back to the pool."""
        if isinstance(b, Buf) and not b.const and b.name in self.pooled:
            self.refs[b.name] -= 1
            if self.refs[b.name] == 0:
                self.pool.give(self.pooled.pop(b.name), b.name)

    def const_buf(self, value) -> Buf:
        a = np.asarray(value)
        ct = ctype(a.dtype)
        self.n_tmp += 1
        name = f"{self.prefix}_c{self.n_tmp}"
        vals = ", ".join(c_literal(x, a.dtype) for x in a.ravel()) or "0"
        self.consts.append(f"static const {ct} {name}[{max(a.size, 1)}] = {{{vals}}};")
        return Buf(name, ct, tuple(a.shape), a.dtype, const=True, value=a)

    # -- loops
    def loops(self, shape) -> list[str]:
        """Open one loop per dimension of ``shape``; returns the index names."""
        idx = []
        for n in shape:
            i = self.tmp("i")
            self.w(f"for (int64_t {i} = 0; {i} < {int(n)}; ++{i}) {{")
            self.depth += 1
            idx.append(i)
        return idx

    def close(self, n: int) -> None:
        for _ in range(n):
            self.depth -= 1
            self.w("}")

    def copy(self, dst: Buf, src, n: int | None = None) -> None:
        n = dst.size if n is None else n
        if isinstance(src, Lit) or src.size == 1 and n > 1:
            i = self.tmp("i")
            self.w(f"for (int64_t {i} = 0; {i} < {n}; ++{i}) {dst.name}[{i}] = "
                   f"({dst.ctype})({src.at('0')});")
        elif src.name != dst.name:
            self.w(f"memcpy({dst.name}, {src.name}, sizeof({dst.ctype}) * {n});")

    # -- jaxprs
    def run(self, jaxpr, args: list, consts: list | None = None, dedupe: bool = True) -> list:
        """Emit ``jaxpr`` (a Jaxpr) with its invars bound to ``args`` (Buf or Lit) and its
        constvars to ``consts``; returns its outputs. Temporaries are pooled after their
        last use; ``args`` and outputs are not released here."""
        import jax.extend.core as jcore

        if dedupe:
            jaxpr = _deduplicate(jaxpr)
        env: dict = {}
        for v, a in zip(jaxpr.constvars, consts or []):
            env[v] = a
        for v, a in zip(jaxpr.invars, args):
            env[v] = a
        last: dict = {}
        for k, e in enumerate(jaxpr.eqns):
            for v in e.invars:
                if not isinstance(v, jcore.Literal):
                    last[v] = k
        keep = {v for v in jaxpr.outvars if not isinstance(v, jcore.Literal)}
        owned = set()

        def read(v):
            if isinstance(v, jcore.Literal):
                return Lit(c_literal(v.val, v.aval.dtype), (), np.dtype(v.aval.dtype),
                           np.asarray(v.val, v.aval.dtype))
            return env[v]

        for k, e in enumerate(jaxpr.eqns):
            self.cut()
            ins = [read(v) for v in e.invars]
            outs = _fold(self, e, ins)
            if outs is None:
                # inputs read for the last time here, from storage nothing else holds
                self.dying = frozenset(
                    p for p, v in enumerate(e.invars)
                    if not isinstance(v, jcore.Literal) and last.get(v) == k and v in owned
                    and v not in keep and e.invars.count(v) == 1
                    and self.refs.get(env[v].name) == 1)
                outs = RULES[e.primitive.name](self, e, ins)  # emit_function checked them
            for v, o in zip(e.outvars, outs):
                env[v] = o
                if isinstance(o, Buf) and o.name in self.pooled:
                    owned.add(v)      # each holds one reference to its storage
            for v in dict.fromkeys(x for x in e.invars if not isinstance(x, jcore.Literal)):
                if last.get(v) == k and v in owned and v not in keep:
                    self.release(env[v])
                    owned.discard(v)
            for v, o in zip(e.outvars, outs):    # results nobody reads
                if v in owned and v not in last and v not in keep:
                    self.release(o)
                    owned.discard(v)
        return [read(v) for v in jaxpr.outvars]


# ------------------------------------------------------------------- constant folding

FOLD_MAX = 1 << 14
"""The largest result (elements) a constant equation is folded into: above, it is
computed at run time (a big broadcast of a literal costs less to fill than to store)."""


def _bcast(x, shape, dims):
    s = [1] * len(shape)
    for j, d in enumerate(dims):
        s[d] = x.shape[j]
    return np.broadcast_to(x.reshape(s), shape)


def _iota_np(dtype, shape, dimension, **_):
    s = [1] * len(shape)
    s[dimension] = shape[dimension]
    return np.broadcast_to(np.arange(shape[dimension]).reshape(s), shape).astype(dtype)


def _select_np(which, *cases):
    shape = np.broadcast_shapes(np.shape(which), *(np.shape(c) for c in cases))
    w = np.broadcast_to(np.asarray(which).astype(np.int64), shape)
    return np.choose(w, [np.broadcast_to(c, shape) for c in cases])


_FOLD: dict[str, Callable] = {
    "broadcast_in_dim": lambda x, shape, broadcast_dimensions, **_: _bcast(
        x, shape, broadcast_dimensions),
    "slice": lambda x, start_indices, limit_indices, strides, **_: x[tuple(
        slice(a, b, c) for a, b, c in zip(start_indices, limit_indices,
                                           strides or (1,) * x.ndim))],
    "squeeze": lambda x, dimensions, **_: np.squeeze(x, axis=tuple(dimensions)),
    "reshape": lambda x, new_sizes, dimensions=None, **_: (
        x.reshape(new_sizes) if dimensions is None else None),
    "transpose": lambda x, permutation, **_: np.transpose(x, permutation),
    "concatenate": lambda *xs, dimension, **_: np.concatenate(xs, axis=dimension),
    "iota": lambda dtype, shape, dimension, **_: _iota_np(dtype, shape, dimension),
    "select_n": lambda *xs, **_: _select_np(*xs),
    "add": lambda a, b, **_: a + b, "sub": lambda a, b, **_: a - b,
    "mul": lambda a, b, **_: a * b, "neg": lambda a, **_: -a,
    "max": lambda a, b, **_: np.maximum(a, b), "min": lambda a, b, **_: np.minimum(a, b),
    "eq": lambda a, b, **_: a == b, "ne": lambda a, b, **_: a != b,
    "lt": lambda a, b, **_: a < b, "le": lambda a, b, **_: a <= b,
    "gt": lambda a, b, **_: a > b, "ge": lambda a, b, **_: a >= b,
    "and": lambda a, b, **_: np.bitwise_and(a, b), "or": lambda a, b, **_: np.bitwise_or(a, b),
    "not": lambda a, **_: np.invert(a),
}
"""Primitives evaluated at generation time where every operand is a constant, in numpy:
the same IEEE operations, in the jaxpr's dtypes (ints wrap in both; ``convert`` below)."""


def _fold(em: "Emitter", e, ins) -> list | None:
    """The results of ``e`` as constants where all its operands are constants with known
    numbers and its primitive folds (``_FOLD``, or a conversion that is exact in C's
    sense too: not float to integer); else None (emitted as code)."""
    name = e.primitive.name
    if (name not in _FOLD and name != "convert_element_type") or any(
            getattr(x, "value", None) is None for x in ins):
        return None
    out = e.outvars[0].aval
    if len(e.outvars) != 1 or math.prod(out.shape) > FOLD_MAX:
        return None
    vals = [np.asarray(x.value) for x in ins]
    if name == "convert_element_type":
        dst = np.dtype(e.params["new_dtype"])
        if vals[0].dtype.kind == "f" and dst.kind in "iu":
            return None
        got = vals[0].astype(dst) if dst != np.bool_ else vals[0] != 0
    else:
        with np.errstate(all="ignore"):
            got = _FOLD[name](*vals, **e.params)
    if got is None:
        return None
    got = np.asarray(got)
    if got.shape != tuple(out.shape):
        return None
    return [em.const_buf(np.ascontiguousarray(got.astype(out.dtype)))]


def _where(eqn) -> str:
    info: Any = getattr(eqn, "source_info", None)
    try:
        from jax._src import source_info_util

        return source_info_util.summarize(info)
    except Exception:  # noqa: BLE001 - a location is a courtesy
        return ""


# ----------------------------------------------------------------------------------- rules

RULES: dict[str, Callable] = {}


def rule(*names):
    def deco(fn):
        for n in names:
            RULES[n] = fn
        return fn
    return deco


def _out(em: Emitter, e, k: int = 0) -> Buf:
    direct = em.direct.get(e.outvars[k])
    return direct if direct is not None else em.new_buf(e.outvars[k].aval)


def _out_in_place(em: Emitter, e, ins, pos: int) -> Buf:
    """The result array of an equation that copies input ``pos`` and then updates it
    (a triangular solve, a scatter): that input's own storage where the equation reads
    it for the last time and nothing else holds it (``Emitter.dying``), so the copy is
    not made; else ``_out``."""
    if pos in em.dying and e.outvars[0] not in em.direct:
        return em.alias(ins[pos], e.outvars[0].aval)
    return _out(em, e)


def _elementwise(em: Emitter, e, ins, expr: Callable[..., str]) -> list:
    """out = expr(inputs) element by element; an input of size 1 is broadcast, and so is
    any dimension of size 1 of an input of the output's rank (lax's implicit broadcast)."""
    out = _out(em, e)
    if all(x.size == 1 or tuple(x.shape) == out.shape for x in ins):
        i = em.tmp("i")
        args = [x.at(i) if x.size == out.size and out.size > 1 else x.at("0") for x in ins]
        em.w(f"for (int64_t {i} = 0; {i} < {max(out.size, 1)}; ++{i}) "
             f"{out.name}[{i}] = ({out.ctype})({expr(*args)});")
        return [out]
    idx = em.loops(out.shape)
    args = []
    for x in ins:
        if x.size == 1:
            args.append(x.at("0"))
        else:
            src = [i if n != 1 else "0" for i, n in zip(idx, x.shape)]
            args.append(x.at(flat_index(src, x.shape)))
    em.w(f"{out.at(flat_index(idx, out.shape))} = ({out.ctype})({expr(*args)});")
    em.close(len(idx))
    return [out]


def _is_float(e) -> bool:
    return np.dtype(e.invars[0].aval.dtype).kind == "f"


_UNARY = {"neg": "-({0})", "sin": "sin({0})", "cos": "cos({0})", "tan": "tan({0})",
          "asin": "asin({0})", "acos": "acos({0})", "atan": "atan({0})", "exp": "exp({0})",
          "exp2": "exp2({0})", "log": "log({0})", "log1p": "log1p({0})", "expm1": "expm1({0})",
          "sqrt": "sqrt({0})", "rsqrt": "(1.0 / sqrt({0}))", "cbrt": "cbrt({0})",
          "tanh": "tanh({0})", "sinh": "sinh({0})", "cosh": "cosh({0})",
          "asinh": "asinh({0})", "acosh": "acosh({0})", "atanh": "atanh({0})",
          "floor": "floor({0})", "ceil": "ceil({0})", "is_finite": "(isfinite({0}) != 0)",
          "logistic": "(1.0 / (1.0 + exp(-({0}))))", "erf": "erf({0})",
          "sign": "(({0}) > 0 ? 1 : (({0}) < 0 ? -1 : ({0})))", "square": "(({0}) * ({0}))",
          "stop_gradient": "({0})", "copy": "({0})", "copy_p": "({0})",
          "real": "({0})", "reduce_precision": "({0})"}


for _name, _fmt in _UNARY.items():
    RULES[_name] = (lambda fmt: lambda em, e, ins: _elementwise(em, e, ins, fmt.format))(_fmt)


@rule("abs")
def _abs(em, e, ins):
    return _elementwise(em, e, ins, (lambda a: f"fabs({a})") if _is_float(e)
                        else (lambda a: f"(({a}) < 0 ? -({a}) : ({a}))"))


@rule("not")
def _not(em, e, ins):
    b = np.dtype(e.invars[0].aval.dtype) == np.bool_
    return _elementwise(em, e, ins, (lambda a: f"!({a})") if b else (lambda a: f"~({a})"))


@rule("round")
def _round(em, e, ins):
    even = int(e.params.get("rounding_method", 0)) == 1
    return _elementwise(em, e, ins, (lambda a: f"rint({a})") if even
                        else (lambda a: f"round({a})"))


@rule("integer_pow")
def _integer_pow(em, e, ins):
    y = int(e.params["y"])

    def expr(a):
        if y == 0:
            return "1"
        body = " * ".join([f"({a})"] * abs(y))
        return body if y > 0 else f"1.0 / ({body})"
    return _elementwise(em, e, ins, expr)


_BINARY = {"add": "({0}) + ({1})", "add_any": "({0}) + ({1})", "sub": "({0}) - ({1})",
           "mul": "({0}) * ({1})", "atan2": "atan2({0}, {1})", "pow": "pow({0}, {1})",
           "eq": "({0}) == ({1})", "ne": "({0}) != ({1})", "lt": "({0}) < ({1})",
           "le": "({0}) <= ({1})", "gt": "({0}) > ({1})", "ge": "({0}) >= ({1})",
           "nextafter": "nextafter({0}, {1})"}
for _name, _fmt in _BINARY.items():
    RULES[_name] = (lambda fmt: lambda em, e, ins: _elementwise(em, e, ins, fmt.format))(_fmt)


@rule("div")
def _div(em, e, ins):
    return _elementwise(em, e, ins, lambda a, b: f"({a}) / ({b})")   # C truncates like XLA


@rule("rem")
def _rem(em, e, ins):
    return _elementwise(em, e, ins, (lambda a, b: f"fmod({a}, {b})") if _is_float(e)
                        else (lambda a, b: f"({a}) % ({b})"))


@rule("max", "min")
def _maxmin(em, e, ins):
    op = ">" if e.primitive.name == "max" else "<"
    if _is_float(e):      # XLA: NaN in, NaN out
        return _elementwise(em, e, ins,
                            lambda a, b: f"(isnan({a}) || ({a}) {op} ({b})) ? ({a}) : ({b})")
    return _elementwise(em, e, ins, lambda a, b: f"(({a}) {op} ({b})) ? ({a}) : ({b})")


@rule("and", "or", "xor")
def _logic(em, e, ins):
    op = {"and": "&", "or": "|", "xor": "^"}[e.primitive.name]
    return _elementwise(em, e, ins, lambda a, b: f"({a}) {op} ({b})")


@rule("clamp")
def _clamp(em, e, ins):
    return _elementwise(em, e, ins, lambda lo, x, hi: f"(({x}) < ({lo}) ? ({lo}) : "
                        f"(({x}) > ({hi}) ? ({hi}) : ({x})))")


@rule("select_n")
def _select_n(em, e, ins):
    def expr(p, *cs):
        if len(cs) == 1:
            return cs[0]
        if len(cs) == 2:
            return f"({p}) ? ({cs[1]}) : ({cs[0]})"
        out = f"({cs[-1]})"
        for k in range(len(cs) - 2, -1, -1):
            out = f"(({p}) == {k} ? ({cs[k]}) : {out})"
        return out
    return _elementwise(em, e, ins, expr)


@rule("convert_element_type")
def _convert(em, e, ins):
    dst = np.dtype(e.params["new_dtype"])
    if isinstance(ins[0], Buf) and ctype(dst) == ins[0].ctype and dst.kind == ins[0].dtype.kind:
        return [em.alias(ins[0], e.outvars[0].aval)]
    if dst == np.bool_:
        return _elementwise(em, e, ins, lambda a: f"({a}) != 0")
    return _elementwise(em, e, ins, lambda a: a)


def _alias_copy(em, e, ins):
    if isinstance(ins[0], Buf):      # no copy: the same elements in the same order
        return [em.alias(ins[0], e.outvars[0].aval)]
    out = _out(em, e)
    em.copy(out, ins[0])
    return [out]


for _name in ("reshape", "squeeze", "expand_dims"):
    RULES[_name] = _alias_copy


@rule("broadcast_in_dim")
def _broadcast(em, e, ins):
    out, x = _out(em, e), ins[0]
    if x.size == 1:
        em.copy(out, x)
        return [out]
    bd = e.params["broadcast_dimensions"]
    idx = em.loops(out.shape)
    src = [idx[bd[j]] if x.shape[j] != 1 else "0" for j in range(len(x.shape))]
    em.w(f"{out.at(flat_index(idx, out.shape))} = {x.at(flat_index(src, x.shape))};")
    em.close(len(idx))
    return [out]


@rule("transpose")
def _transpose(em, e, ins):
    out, x = _out(em, e), ins[0]
    perm = e.params["permutation"]
    idx = em.loops(out.shape)
    src = [""] * len(perm)
    for d, p in enumerate(perm):
        src[p] = idx[d]
    em.w(f"{out.at(flat_index(idx, out.shape))} = {x.at(flat_index(src, x.shape))};")
    em.close(len(idx))
    return [out]


def _contiguous_offset(shape, start, out_shape) -> int | None:
    """The flat offset of a unit-stride slice of a row-major array where its elements are
    one contiguous run (every dim before the last partial one of size 1), else None."""
    partial = [d for d in range(len(shape)) if out_shape[d] != shape[d]]
    if partial and any(out_shape[d] != 1 for d in range(partial[-1])):
        return None
    return sum(int(a) * k for a, k in zip(start, strides(shape)))


@rule("slice")
def _slice(em, e, ins):
    x = ins[0]
    start = e.params["start_indices"]
    st = e.params["strides"] or (1,) * len(start)
    shape = tuple(int(d) for d in e.outvars[0].aval.shape)
    if isinstance(x, Buf) and x.const and all(k == 1 for k in st):
        # a read-only array (an input, a constant): a contiguous slice is a view of it
        off = _contiguous_offset(x.shape, start, shape)
        if off is not None:
            return [Buf(f"({x.name} + {off})" if off else x.name, x.ctype, shape, x.dtype,
                        const=True)]
    out = _out(em, e)
    idx = em.loops(out.shape)
    src = [f"{s} + {i}*{k}" for s, i, k in zip(start, idx, st)]
    em.w(f"{out.at(flat_index(idx, out.shape))} = {x.at(flat_index(src, x.shape))};")
    em.close(len(idx))
    return [out]


def _clamped_starts(em, starts, op_shape, sizes) -> list[str]:
    names = []
    for s, n, k in zip(starts, op_shape, sizes):
        t = em.tmp("s")
        hi = int(n) - int(k)
        em.w(f"int64_t {t} = (int64_t)({s.at('0')});")
        em.w(f"{t} = {t} < 0 ? 0 : ({t} > {hi} ? {hi} : {t});")
        names.append(t)
    return names


@rule("dynamic_slice")
def _dynamic_slice(em, e, ins):
    out, x = _out(em, e), ins[0]
    starts = _clamped_starts(em, ins[1:], x.shape, e.params["slice_sizes"])
    em.w("{")
    em.depth += 1
    idx = em.loops(out.shape)
    src = [f"{s} + {i}" for s, i in zip(starts, idx)]
    em.w(f"{out.at(flat_index(idx, out.shape))} = {x.at(flat_index(src, x.shape))};")
    em.close(len(idx) + 1)
    return [out]


@rule("dynamic_update_slice")
def _dynamic_update_slice(em, e, ins):
    out, x, upd = _out_in_place(em, e, ins, 0), ins[0], ins[1]
    em.copy(out, x)
    starts = _clamped_starts(em, ins[2:], x.shape, upd.shape)
    em.w("{")
    em.depth += 1
    idx = em.loops(upd.shape)
    dst = [f"{s} + {i}" for s, i in zip(starts, idx)]
    em.w(f"{out.at(flat_index(dst, out.shape))} = {upd.at(flat_index(idx, upd.shape))};")
    em.close(len(idx) + 1)
    return [out]


@rule("concatenate")
def _concatenate(em, e, ins):
    out = _out(em, e)
    dim = e.params["dimension"]
    off = 0
    for x in ins:
        if x.size:
            idx = em.loops(x.shape)
            dst = [f"{i} + {off}" if d == dim else i for d, i in enumerate(idx)]
            em.w(f"{out.at(flat_index(dst, out.shape))} = {x.at(flat_index(idx, x.shape))};")
            em.close(len(idx))
        off += x.shape[dim]
    return [out]


@rule("split")
def _split(em, e, ins):
    x, axis = ins[0], e.params["axis"]
    outs, off = [], 0
    for k, n in enumerate(e.params["sizes"]):
        out = _out(em, e, k)
        idx = em.loops(out.shape)
        src = [f"{i} + {off}" if d == axis else i for d, i in enumerate(idx)]
        em.w(f"{out.at(flat_index(idx, out.shape))} = {x.at(flat_index(src, x.shape))};")
        em.close(len(idx))
        outs.append(out)
        off += int(n)
    return outs


@rule("stack")
def _stack(em, e, ins):
    out = _out(em, e)
    axis = e.params["axis"]
    for k, x in enumerate(ins):
        idx = em.loops(x.shape)
        dst = idx[:axis] + [str(k)] + idx[axis:]
        em.w(f"{out.at(flat_index(dst, out.shape))} = {x.at(flat_index(idx, x.shape))};")
        em.close(len(idx))
    return [out]


@rule("pad")
def _pad(em, e, ins):
    out, x, fill = _out(em, e), ins[0], ins[1]
    em.copy(out, fill)
    cfg = e.params["padding_config"]
    idx = em.loops(x.shape)
    pos = []
    for (lo, _hi, interior), i in zip(cfg, idx):
        p = em.tmp("p")
        em.w(f"int64_t {p} = {lo} + {i}*{interior + 1};")
        pos.append(p)
    cond = " && ".join(f"{p} >= 0 && {p} < {n}" for p, n in zip(pos, out.shape)) or "1"
    em.w(f"if ({cond}) {out.at(flat_index(pos, out.shape))} = "
         f"{x.at(flat_index(idx, x.shape))};")
    em.close(len(idx))
    return [out]


@rule("iota")
def _iota(em, e, ins):
    out = _out(em, e)
    dim = e.params["dimension"]
    idx = em.loops(out.shape)
    em.w(f"{out.at(flat_index(idx, out.shape))} = ({out.ctype})({idx[dim]});")
    em.close(len(idx))
    return [out]


@rule("rev")
def _rev(em, e, ins):
    out, x = _out(em, e), ins[0]
    dims = set(e.params["dimensions"])
    idx = em.loops(out.shape)
    src = [f"{n - 1} - {i}" if d in dims else i for d, (i, n) in enumerate(zip(idx, x.shape))]
    em.w(f"{out.at(flat_index(idx, out.shape))} = {x.at(flat_index(src, x.shape))};")
    em.close(len(idx))
    return [out]


_REDUCE = {"reduce_sum": ("0", "{a} + {x}"), "reduce_prod": ("1", "{a} * {x}"),
           "reduce_and": ("1", "{a} && {x}"), "reduce_or": ("0", "{a} || {x}"),
           "reduce_max": ("-INFINITY", "(isnan({a}) || {a} > {x}) ? {a} : {x}"),
           "reduce_min": ("INFINITY", "(isnan({a}) || {a} < {x}) ? {a} : {x}")}


@rule(*_REDUCE)
def _reduce(em, e, ins):
    out, x = _out(em, e), ins[0]
    axes = set(e.params["axes"])
    init, step = _REDUCE[e.primitive.name]
    if e.primitive.name in ("reduce_max", "reduce_min") and not _is_float(e):
        info = np.iinfo(x.dtype)
        init = str(info.min if e.primitive.name == "reduce_max" else info.max)
        step = step.replace("isnan({a}) || ", "")
    em.copy(out, Lit(init))
    idx = em.loops(x.shape)
    keep = [i for d, i in enumerate(idx) if d not in axes]
    a = out.at(flat_index(keep, out.shape))
    em.w(f"{a} = ({out.ctype})({step.format(a=a, x=x.at(flat_index(idx, x.shape)))});")
    em.close(len(idx))
    return [out]


@rule("argmax", "argmin")
def _argmax(em, e, ins):
    out, x = _out(em, e), ins[0]
    (axis,) = e.params["axes"]
    op = ">" if e.primitive.name == "argmax" else "<"
    other = [n for d, n in enumerate(x.shape) if d != axis]
    idx = em.loops(other)
    best, arg, j = em.tmp("v"), em.tmp("a"), em.tmp("j")
    em.w(f"{x.ctype} {best} = 0; int64_t {arg} = -1;")
    em.w(f"for (int64_t {j} = 0; {j} < {x.shape[axis]}; ++{j}) {{")
    full = idx[:axis] + [j] + idx[axis:]
    val = x.at(flat_index(full, x.shape))
    nan = f"isnan({val})" if np.dtype(x.dtype).kind == "f" else "0"
    bnan = f"isnan({best})" if np.dtype(x.dtype).kind == "f" else "0"
    em.w(f"    if ({arg} < 0 || (!{bnan} && ({nan} || {val} {op} {best}))) "
         f"{{ {best} = {val}; {arg} = {j}; }}")
    em.w("}")
    em.w(f"{out.at(flat_index(idx, out.shape))} = ({out.ctype}){arg};")
    em.close(len(idx))
    return [out]


def _sparse_rows(em, e, a, lf, lc, lb) -> tuple[Buf, Buf, Buf] | None:
    """For a constant lhs at most half nonzero, contracted along one dim, with no batch
    dims: its nonzeros row by row (CSR: row starts, contraction indices, values; a row is
    a flat index over the lhs's free dims), as constants; else None."""
    if a.value is None or lb or len(lc) != 1 or a.dtype != np.float64:
        return None
    m = np.moveaxis(np.asarray(a.value, np.float64), lc[0], -1).reshape(-1, a.shape[lc[0]])
    nz = m != 0
    if nz.sum() > 0.5 * m.size:
        return None
    rows, cols = np.nonzero(nz)
    start = np.concatenate([[0], np.cumsum(nz.sum(axis=1))]).astype(np.int64)
    return (em.const_buf(start), em.const_buf(cols.astype(np.int64)),
            em.const_buf(m[rows, cols]))


ZERO_SKIP_MIN = 4
"""A product in row form whose rhs rows are at least this long skips the row update of
each lhs entry that is zero at run time (the contact and chain rows J~ and the contact
rows of G are about three quarters zeros)."""


@rule("dot_general")
def _dot_general(em, e, ins):
    """out[batch, lhs free, rhs free] = sum over the contracted dims, each entry's sum in
    the contracted dims' order, in double. Where the rhs's free dims are its innermost
    and there are some (the rhs not contracted along its last dim), the rhs free loop
    is innermost (row updates out[.., j] += a * b[.., j], along contiguous memory, which
    the C compiler vectorises); otherwise one dot product per entry. Either order adds
    the same products to each entry in the same order, so the two give the same bits.
    A constant lhs that is mostly zeros (a static summation matrix) is contracted over
    its nonzeros only (``_sparse_rows``), and in row form a zero entry of a run-time lhs
    skips its row update (``ZERO_SKIP_MIN``): the same bits for finite rhs entries, as
    adding a product 0 * b changes no sum."""
    out, a, b = _out(em, e), ins[0], ins[1]
    (lc, rc), (lb, rb) = e.params["dimension_numbers"]
    lf = [d for d in range(len(a.shape)) if d not in lc and d not in lb]
    rf = [d for d in range(len(b.shape)) if d not in rc and d not in rb]
    nb = len(lb)
    ai, bi = [""] * len(a.shape), [""] * len(b.shape)
    rows = (out.dtype == np.float64 and rf and int(np.prod([b.shape[d] for d in rf])) > 1
            and rf == list(range(len(b.shape) - len(rf), len(b.shape))))
    sparse = _sparse_rows(em, e, a, lf, lc, lb) if out.dtype == np.float64 else None

    def contraction(free_idx):
        """Open the contraction loop(s); returns (lhs value expression, loops opened)."""
        if sparse is None:
            cidx = em.loops([a.shape[d] for d in lc])
            for x, y, i in zip(lc, rc, cidx):
                ai[x] = bi[y] = i
            return a.at(flat_index(ai, a.shape)), len(cidx)
        start, col, val = sparse
        r = flat_index(free_idx, [a.shape[d] for d in lf]) if lf else "0"
        p = em.tmp("p")
        em.w(f"for (int64_t {p} = {start.at(r)}; {p} < {start.at(f'({r}) + 1')}; ++{p}) {{")
        em.depth += 1
        bi[rc[0]] = col.at(p)
        return val.at(p), 1

    if rows:
        outer = em.loops(out.shape[:nb + len(lf)])
        for k, (x, y) in enumerate(zip(lb, rb)):
            ai[x] = bi[y] = outer[k]
        for k, d in enumerate(lf):
            ai[d] = outer[nb + k]
        inner = [out.shape[nb + len(lf) + k] for k in range(len(rf))]
        jdx = em.loops(inner)
        em.w(f"{out.at(flat_index(outer + jdx, out.shape))} = 0;")
        em.close(len(jdx))
        aval, nc = contraction(outer[nb:])
        f = em.tmp("f")
        em.w(f"double {f} = (double){aval};")
        skip = sparse is None and math.prod(inner) >= ZERO_SKIP_MIN
        if skip:         # a zero of the lhs adds no products (ZERO_SKIP_MIN)
            em.w(f"if ({f} != 0) {{")
            em.depth += 1
        jdx = em.loops(inner)
        for d, j in zip(rf, jdx):
            bi[d] = j
        em.w(f"{out.at(flat_index(outer + jdx, out.shape))} += {f} * "
             f"(double){b.at(flat_index(bi, b.shape))};")
        em.close(len(jdx) + int(skip) + nc + len(outer))
        return [out]
    idx = em.loops(out.shape)
    for k, (x, y) in enumerate(zip(lb, rb)):
        ai[x] = bi[y] = idx[k]
    for k, d in enumerate(lf):
        ai[d] = idx[nb + k]
    for k, d in enumerate(rf):
        bi[d] = idx[nb + len(lf) + k]
    acc = em.tmp("acc")
    em.w(f"double {acc} = 0;")
    aval, nc = contraction(idx[nb:nb + len(lf)])
    em.w(f"{acc} += (double){aval} * (double){b.at(flat_index(bi, b.shape))};")
    em.close(nc)
    em.w(f"{out.at(flat_index(idx, out.shape))} = ({out.ctype}){acc};")
    em.close(len(idx))
    return [out]


def _gather_like(em, e, op, indices, out_shape, window_dims, collapsed, index_map,
                 slice_sizes, emit):
    """Loop over the result (gather) or the updates (scatter): ``emit(full operand
    index, result index, in-bounds test)``; starts clamped unless FILL_OR_DROP."""
    mode = str(e.params.get("mode"))
    fill = "FILL_OR_DROP" in mode
    idx = em.loops(out_shape)
    batch = [i for d, i in enumerate(idx) if d not in window_dims]
    win = [i for d, i in enumerate(idx) if d in window_dims]
    nvec = indices.shape[-1] if indices.shape else 1
    start = ["0"] * len(op.shape)
    ok = []
    for k in range(nvec):
        d = index_map[k]
        s = em.tmp("s")
        em.w(f"int64_t {s} = (int64_t){indices.at(flat_index(batch + [str(k)], indices.shape))};")
        hi = int(op.shape[d]) - int(slice_sizes[d])
        if fill:
            ok.append(f"{s} >= 0 && {s} <= {hi}")
        else:
            em.w(f"{s} = {s} < 0 ? 0 : ({s} > {hi} ? {hi} : {s});")
        start[d] = s
    full = []
    w = iter(win)
    for d in range(len(op.shape)):
        off = "0" if d in collapsed else next(w)
        full.append(f"{start[d]} + {off}")
    emit(full, idx, " && ".join(ok) if ok else "1")
    em.close(len(idx))


@rule("gather")
def _gather(em, e, ins):
    out, op, indices = _out(em, e), ins[0], ins[1]
    dn = e.params["dimension_numbers"]
    if dn.operand_batching_dims:
        raise UnsupportedPrimitive(f"gather with operand batching dims ({_where(e)})")
    fill = e.params.get("fill_value")
    fv = c_literal(np.nan if fill is None and out.dtype.kind == "f" else (fill or 0), out.dtype)

    def emit(full, idx, ok):
        val = op.at(flat_index(full, op.shape))
        em.w(f"{out.at(flat_index(idx, out.shape))} = ({ok}) ? {val} : {fv};"
             if ok != "1" else f"{out.at(flat_index(idx, out.shape))} = {val};")
    _gather_like(em, e, op, indices, out.shape, set(dn.offset_dims), set(dn.collapsed_slice_dims),
                 dn.start_index_map, e.params["slice_sizes"], emit)
    return [out]


@rule("scatter", "scatter-add", "scatter_add", "scatter-mul", "scatter_mul", "scatter-min",
      "scatter-max")
def _scatter(em, e, ins):
    out, op, indices, upd = _out_in_place(em, e, ins, 0), ins[0], ins[1], ins[2]
    dn = e.params["dimension_numbers"]
    if dn.operand_batching_dims:
        raise UnsupportedPrimitive(f"scatter with operand batching dims ({_where(e)})")
    em.copy(out, op)
    name = e.primitive.name.replace("_", "-")
    sizes = [1] * len(op.shape)
    wdims = list(dn.update_window_dims)
    kept = [d for d in range(len(op.shape)) if d not in dn.inserted_window_dims]
    for k, d in enumerate(kept):
        sizes[d] = upd.shape[wdims[k]]

    def emit(full, idx, ok):
        dst = out.at(flat_index(full, out.shape))
        val = upd.at(flat_index(idx, upd.shape))
        op_ = {"scatter": f"{dst} = {val};", "scatter-add": f"{dst} += {val};",
               "scatter-mul": f"{dst} *= {val};",
               "scatter-min": f"if ({val} < {dst}) {dst} = {val};",
               "scatter-max": f"if ({val} > {dst}) {dst} = {val};"}[name]
        em.w(f"if ({ok}) {op_}" if ok != "1" else op_)
    _gather_like(em, e, op, indices, upd.shape, set(wdims), set(dn.inserted_window_dims),
                 dn.scatter_dims_to_operand_dims, sizes, emit)
    return [out]


@rule("cumsum", "cumprod", "cummax", "cummin")
def _cumulative(em, e, ins):
    out, x = _out(em, e), ins[0]
    axis, rev = e.params["axis"], bool(e.params.get("reverse", False))
    op = {"cumsum": "{a} + {x}", "cumprod": "{a} * {x}",
          "cummax": "(isnan({a}) || {a} > {x}) ? {a} : {x}",
          "cummin": "(isnan({a}) || {a} < {x}) ? {a} : {x}"}[e.primitive.name]
    if x.dtype.kind != "f":
        op = op.replace("isnan({a}) || ", "")
    n = x.shape[axis]
    other = [d for k, d in enumerate(x.shape) if k != axis]
    idx = em.loops(other)
    j, acc = em.tmp("j"), em.tmp("a")
    em.w(f"{x.ctype} {acc} = 0;")
    em.w(f"for (int64_t {j}_ = 0; {j}_ < {n}; ++{j}_) {{")
    em.w(f"    int64_t {j} = {f'{n - 1} - {j}_' if rev else f'{j}_'};")
    full = flat_index(idx[:axis] + [j] + idx[axis:], x.shape)
    em.w(f"    {acc} = ({j}_ == 0) ? {x.at(full)} : "
         f"({x.ctype})({op.format(a=acc, x=x.at(full))});")
    em.w(f"    {out.at(full)} = {acc};")
    em.w("}")
    em.close(len(idx))
    return [out]


@rule("platform_index")
def _platform_index(em, e, ins):
    """The generated C runs on a CPU: the branch for "cpu", else the default."""
    out = _out(em, e)
    platforms = e.params["platforms"]
    k = next((i for i, group in enumerate(platforms) if group and "cpu" in group),
             len(platforms) - 1)
    em.w(f"{out.name}[0] = {k};")
    return [out]


# -- calls and control flow

def _closed(j):
    return (j.jaxpr, list(j.consts)) if hasattr(j, "consts") else (j, [])


def _inline(em, closed, args):
    jaxpr, consts = _closed(closed)
    cbufs = [em.const_buf(c) for c in consts]
    return em.run(jaxpr, args, cbufs)


def _owned_copy(em, e, outs):
    """The results of an inlined call: the call's own buffers, or copies where a result
    is an argument, a constant or a literal (the caller releases what it owns)."""
    res = []
    for v, o in zip(e.outvars, outs):
        if isinstance(o, Buf) and o.name in em.pooled:
            res.append(o)
        else:
            b = em.new_buf(v.aval)
            em.copy(b, o)
            res.append(b)
    # an output returned twice must not be released twice
    seen: set = set()
    for k, o in enumerate(res):
        if o.name in seen:
            b = em.new_buf(e.outvars[k].aval)
            em.copy(b, o)
            res[k] = b
        seen.add(res[k].name)
    return res


@rule("jit", "pjit", "closed_call", "core_call", "remat", "checkpoint", "custom_vmap_call")
def _call(em, e, ins):
    j = next(e.params[k] for k in ("jaxpr", "call_jaxpr", "call") if e.params.get(k) is not None)
    return _owned_copy(em, e, _inline(em, j, ins))


@rule("custom_jvp_call", "custom_vjp_call", "custom_vjp_call_jaxpr")
def _custom(em, e, ins):
    j = e.params.get("call_jaxpr", e.params.get("fun_jaxpr"))
    return _owned_copy(em, e, _inline(em, j, ins))


@rule("custom_linear_solve")
def _linear_solve(em, e, ins):
    cl = e.params["const_lengths"]
    a = cl.matvec + cl.vecmat
    consts, b = ins[a:a + cl.solve], ins[sum(cl):]
    return _owned_copy(em, e, _inline(em, e.params["jaxprs"].solve, [*consts, *b]))


@rule("scan")
def _scan(em, e, ins):
    p = e.params
    nc, ncar, length = p["num_consts"], p["num_carry"], int(p["length"])
    consts, init, xs = ins[:nc], ins[nc:nc + ncar], ins[nc + ncar:]
    body, bconsts = _closed(p["jaxpr"])
    cb = [em.const_buf(c) for c in bconsts]
    carry = []
    for v, x in zip(e.outvars[:ncar], init):
        b = em.new_buf(v.aval)
        em.copy(b, x)
        carry.append(b)
    ys = [em.new_buf(v.aval) for v in e.outvars[ncar:]]
    x_avals = body.invars[nc + ncar:]
    xbufs = [em.new_buf(v.aval) for v in x_avals]
    t = em.tmp("k")
    em.w(f"for (int64_t {t}_ = 0; {t}_ < {length}; ++{t}_) {{")
    em.depth += 1
    em.w(f"int64_t {t} = {f'{length - 1} - {t}_' if p['reverse'] else f'{t}_'};")
    for xb, x in zip(xbufs, xs):
        n = xb.size
        em.w(f"memcpy({xb.name}, {x.name} + {t}*{n}, sizeof({xb.ctype}) * {n});")
    outs = em.run(body, [*consts, *carry, *xbufs], cb)
    new = outs[:ncar]
    for y, o in zip(ys, outs[ncar:]):
        n = max(int(np.prod(y.shape[1:], dtype=np.int64)), 1)
        src = o.at("j_") if o.size > 1 else o.at("0")
        em.w(f"for (int64_t j_ = 0; j_ < {n}; ++j_) {y.name}[{t}*{n} + j_] = {src};")
    tmp = [em.new_buf(v.aval) for v in e.outvars[:ncar]]
    for b, o in zip(tmp, new):           # the new carry may read the old one
        em.copy(b, o)
    for c, b in zip(carry, tmp):
        em.copy(c, b)
    for b in tmp:
        em.release(b)
    for o in outs:
        if isinstance(o, Buf) and o.name in em.pooled and o not in carry:
            em.release(o)
    em.depth -= 1
    em.w("}")
    for xb in xbufs:
        em.release(xb)
    return [*carry, *ys]


@rule("while")
def _while(em, e, ins):
    p = e.params
    cn, bn = p["cond_nconsts"], p["body_nconsts"]
    cconsts, bconsts, init = ins[:cn], ins[cn:cn + bn], ins[cn + bn:]
    cj, cc = _closed(p["cond_jaxpr"])
    bj, bc = _closed(p["body_jaxpr"])
    ccb, bcb = [em.const_buf(c) for c in cc], [em.const_buf(c) for c in bc]
    carry = []
    for v, x in zip(e.outvars, init):
        b = em.new_buf(v.aval)
        em.copy(b, x)
        carry.append(b)
    em.w("for (;;) {")
    em.depth += 1
    (pred,) = em.run(cj, [*cconsts, *carry], ccb)
    em.w(f"if (!({pred.at('0')})) break;")
    em.release(pred)
    outs = em.run(bj, [*bconsts, *carry], bcb)
    tmp = [em.new_buf(v.aval) for v in e.outvars]
    for b, o in zip(tmp, outs):
        em.copy(b, o)
    for o in outs:
        if isinstance(o, Buf) and o.name in em.pooled and o not in carry:
            em.release(o)
    for c, b in zip(carry, tmp):
        em.copy(c, b)
    for b in tmp:
        em.release(b)
    em.depth -= 1
    em.w("}")
    return carry


@rule("cond")
def _cond(em, e, ins):
    index, args = ins[0], ins[1:]
    outs = [em.new_buf(v.aval) for v in e.outvars]
    branches = e.params["branches"]
    em.w(f"switch ((int64_t)({index.at('0')}) <= 0 ? 0 : ((int64_t)({index.at('0')}) >= "
         f"{len(branches) - 1} ? {len(branches) - 1} : (int64_t)({index.at('0')}))) {{")
    for k, br in enumerate(branches):
        em.w(f"case {k}: {{")
        em.depth += 1
        res = _inline(em, br, args)
        for o, r in zip(outs, res):
            em.copy(o, r)
        for r in res:
            if isinstance(r, Buf) and r.name in em.pooled and r not in outs:
                em.release(r)
        em.w("break;")
        em.depth -= 1
        em.w("}")
    em.w("}")
    return outs


# -- linear algebra (the routines are in RUNTIME)

def _batched(em, x: Buf, core: int):
    n = max(int(np.prod(x.shape[:-core], dtype=np.int64)), 1)
    return n, int(np.prod(x.shape[-core:], dtype=np.int64))


@rule("cholesky")
def _cholesky(em, e, ins):
    out, x = _out(em, e), ins[0]
    nb, m = _batched(em, x, 2)
    n = x.shape[-1]
    b = em.tmp("b")
    em.w(f"for (int64_t {b} = 0; {b} < {nb}; ++{b}) {{")
    em.w(f"    int64_t pf_[{max(n, 1)}];")
    em.w(f"    swbc_cholesky({n}, {x.name} + {b}*{m}, {out.name} + {b}*{m}, pf_);")
    em.w("}")
    return [out]


@rule("lu")
def _lu(em, e, ins):
    x = ins[0]
    lu, piv, perm = (_out(em, e, k) for k in range(3))
    nb, mm = _batched(em, x, 2)
    m, n = x.shape[-2], x.shape[-1]
    k = min(m, n)
    b = em.tmp("b")
    em.w(f"for (int64_t {b} = 0; {b} < {nb}; ++{b}) {{")
    em.w(f"    int64_t pv_[{max(k, 1)}], pm_[{max(m, 1)}];")
    em.w(f"    swbc_lu({m}, {n}, {x.name} + {b}*{mm}, {lu.name} + {b}*{mm}, pv_, pm_);")
    em.w(f"    for (int64_t j_ = 0; j_ < {k}; ++j_) {piv.name}[{b}*{k} + j_] = "
         f"({piv.ctype})pv_[j_];")
    em.w(f"    for (int64_t j_ = 0; j_ < {m}; ++j_) {perm.name}[{b}*{m} + j_] = "
         f"({perm.ctype})pm_[j_];")
    em.w("}")
    return [lu, piv, perm]


@rule("lu_pivots_to_permutation")
def _piv_to_perm(em, e, ins):
    out, piv = _out(em, e), ins[0]
    size = int(e.params["permutation_size"])
    k = piv.shape[-1]
    nb = max(int(np.prod(piv.shape[:-1], dtype=np.int64)), 1)
    b = em.tmp("b")
    em.w(f"for (int64_t {b} = 0; {b} < {nb}; ++{b}) {{")
    em.w(f"    for (int64_t j_ = 0; j_ < {size}; ++j_) {out.name}[{b}*{size} + j_] = j_;")
    row = f"{out.name} + {b}*{size}"
    em.w(f"    {out.ctype} *r_ = {row};")
    em.w(f"    for (int64_t j_ = 0; j_ < {k}; ++j_) {{")
    em.w(f"        int64_t p_ = (int64_t){piv.name}[{b}*{k} + j_];")
    em.w(f"        p_ = p_ < 0 ? p_ + {size} : p_;")
    em.w(f"        if (p_ >= 0 && p_ < {size}) {{ {out.ctype} t_ = r_[j_]; r_[j_] = r_[p_]; "
         "r_[p_] = t_; }")
    em.w("    }")
    em.w("}")
    return [out]


@rule("triangular_solve")
def _triangular_solve(em, e, ins):
    out, a, bmat = _out_in_place(em, e, ins, 1), ins[0], ins[1]
    p = e.params
    n = a.shape[-1]
    m, k = bmat.shape[-2], bmat.shape[-1]
    nb = max(int(np.prod(bmat.shape[:-2], dtype=np.int64)), 1)
    na = max(int(np.prod(a.shape[:-2], dtype=np.int64)), 1)
    b = em.tmp("b")
    em.copy(out, bmat)
    em.w(f"for (int64_t {b} = 0; {b} < {nb}; ++{b}) swbc_trisolve({n}, {m}, {k}, "
         f"{a.name} + ({b} % {na})*{n * n}, {out.name} + {b}*{m * k}, "
         f"{int(p['left_side'])}, {int(p['lower'])}, {int(p['transpose_a'])}, "
         f"{int(p['unit_diagonal'])});")
    return [out]


@rule("sort")
def _sort(em, e, ins):
    dim, nkeys = e.params["dimension"], e.params["num_keys"]
    outs = [_out(em, e, k) for k in range(len(ins))]
    for o, x in zip(outs, ins):
        em.copy(o, x)
    shape = outs[0].shape
    n = shape[dim]
    other = [s for d, s in enumerate(shape) if d != dim]
    idx = em.loops(other)
    st = strides(shape)[dim]
    base = flat_index(idx[:dim] + ["0"] + idx[dim:], shape)
    j, m = em.tmp("j"), em.tmp("m")
    # stable insertion sort along dim; keys compared lexicographically, NaN last
    em.w(f"for (int64_t {j} = 1; {j} < {n}; ++{j}) {{")
    em.w(f"    for (int64_t {m} = {j}; {m} > 0; --{m}) {{")
    conds = []
    for key in outs[:nkeys]:
        a = key.at(f"({base}) + ({m} - 1)*{st}")
        bb = key.at(f"({base}) + {m}*{st}")
        if key.dtype.kind == "f":
            conds.append((f"(isnan({a}) && !isnan({bb})) || (!isnan({a}) && !isnan({bb}) && "
                          f"{a} > {bb})", f"(isnan({a}) == isnan({bb})) && "
                          f"(isnan({a}) || {a} == {bb})"))
        else:
            conds.append((f"{a} > {bb}", f"{a} == {bb}"))
    swap, eq = conds[0][0], conds[0][1]
    for gt_, eq_ in conds[1:]:
        swap = f"({swap}) || (({eq}) && ({gt_}))"
        eq = f"({eq}) && ({eq_})"
    em.w(f"        if (!({swap})) break;")
    for o in outs:
        a = o.at(f"({base}) + ({m} - 1)*{st}")
        bb = o.at(f"({base}) + {m}*{st}")
        em.w(f"        {{ {o.ctype} t_ = {a}; {a} = {bb}; {bb} = t_; }}")
    em.w("    }")
    em.w("}")
    em.close(len(idx))
    return outs


RUNTIME = r"""
/* Cholesky A = L L^T (n x n, row-major; the lower triangle of A is read, the upper part of
   L is zero); a matrix that is not positive definite gives NaN everywhere, as XLA does.
   Row i of L is zero left of row i's first nonzero in A (its profile, p[i]; scratch of n
   from the caller), so the products left of it are zeros and are skipped: the same sums
   in the same order (a mass matrix factored leaves first has half its entries there). */
static void swbc_cholesky(int64_t n, const double *a, double *l, int64_t *p) {
    for (int64_t i = 0; i < n; ++i) {
        int64_t k = 0;
        while (k < i && a[i * n + k] == 0.0) ++k;
        p[i] = k;
    }
    for (int64_t i = 0; i < n * n; ++i) l[i] = 0.0;
    for (int64_t j = 0; j < n; ++j) {
        double d = a[j * n + j];
        for (int64_t k = p[j]; k < j; ++k) d -= l[j * n + k] * l[j * n + k];
        if (!(d > 0.0)) { for (int64_t i = 0; i < n * n; ++i) l[i] = NAN; return; }
        d = sqrt(d);
        l[j * n + j] = d;
        for (int64_t i = j + 1; i < n; ++i) {
            if (p[i] > j) continue;                /* left of row i's profile: zero */
            double s = a[i * n + j];
            int64_t k0 = p[i] > p[j] ? p[i] : p[j];
            for (int64_t k = k0; k < j; ++k) s -= l[i * n + k] * l[j * n + k];
            l[i * n + j] = s / d;
        }
    }
}

/* LU with partial pivoting (LAPACK getrf): P A = L U, L unit lower, in one m x n array;
   piv[k] the row swapped with row k, perm the resulting row order. */
static void swbc_lu(int64_t m, int64_t n, const double *a, double *lu, int64_t *piv,
                    int64_t *perm) {
    int64_t kmax = m < n ? m : n;
    for (int64_t i = 0; i < m * n; ++i) lu[i] = a[i];
    for (int64_t i = 0; i < m; ++i) perm[i] = i;
    for (int64_t k = 0; k < kmax; ++k) {
        int64_t p = k;
        double best = fabs(lu[k * n + k]);
        for (int64_t i = k + 1; i < m; ++i) {
            double v = fabs(lu[i * n + k]);
            if (v > best || (isnan(v) && !isnan(best))) { best = v; p = i; }
        }
        piv[k] = p;
        if (p != k) {
            for (int64_t j = 0; j < n; ++j) {
                double t = lu[k * n + j]; lu[k * n + j] = lu[p * n + j]; lu[p * n + j] = t;
            }
            int64_t t = perm[k]; perm[k] = perm[p]; perm[p] = t;
        }
        double d = lu[k * n + k];
        if (d != 0.0) {
            for (int64_t i = k + 1; i < m; ++i) {
                double f = lu[i * n + k] / d;
                lu[i * n + k] = f;
                for (int64_t j = k + 1; j < n; ++j) lu[i * n + j] -= f * lu[k * n + j];
            }
        }
    }
}

/* Triangular solve in place on b (m x k): left_side: op(A) X = B, else X op(A) = B;
   op(A) = A or A^T (transpose_a); A n x n, lower or upper, unit diagonal or not. The
   updates run along the rows of B (contiguous). */
static void swbc_trisolve(int64_t n, int64_t m, int64_t k, const double *a, double *b,
                          int left, int lower, int trans, int unit) {
    int low = trans ? !lower : lower;       /* the triangle of op(A) */
#define A_(i, j) (trans ? a[(j) * n + (i)] : a[(i) * n + (j)])
    if (left) {       /* row i of X from the rows solved before it */
        for (int64_t s_ = 0; s_ < n; ++s_) {
            int64_t i = low ? s_ : n - 1 - s_;
            double *bi = b + i * k;
            int64_t j0 = low ? 0 : i + 1, j1 = low ? i : n;
            for (int64_t j = j0; j < j1; ++j) {
                double f = A_(i, j);
                if (f == 0.0) continue;          /* a structural zero of the factor */
                const double *bj = b + j * k;
                for (int64_t c = 0; c < k; ++c) bi[c] -= f * bj[c];
            }
            if (!unit) { double d = A_(i, i); for (int64_t c = 0; c < k; ++c) bi[c] /= d; }
        }
    } else {          /* rows of B: x op(A) = b_row */
        for (int64_t r = 0; r < m; ++r) {
            double *x = b + r * k;
            if (low) {
                for (int64_t j = n - 1; j >= 0; --j) {
                    double s = x[j];
                    for (int64_t i = j + 1; i < n; ++i) s -= x[i] * A_(i, j);
                    x[j] = unit ? s : s / A_(j, j);
                }
            } else {
                for (int64_t j = 0; j < n; ++j) {
                    double s = x[j];
                    for (int64_t i = 0; i < j; ++i) s -= x[i] * A_(i, j);
                    x[j] = unit ? s : s / A_(j, j);
                }
            }
        }
    }
#undef A_
}
"""


def _param_key(v):
    """A hashable key of an equation's parameter that tells apart what ``==`` does not
    (0.0 and -0.0; arrays by their bytes); raises TypeError where there is none."""
    if isinstance(v, float):
        return ("f", v.hex())
    if isinstance(v, np.ndarray):
        return ("a", v.dtype.str, v.shape, v.tobytes())
    if isinstance(v, (tuple, list)):
        return (type(v).__name__, tuple(_param_key(x) for x in v))
    hash(v)
    return v


def _deduplicate(jaxpr):
    """``jaxpr`` with each equation that repeats an earlier one (the same primitive,
    parameters and inputs, no effects) left out, its results read from the earlier one's.
    JAX leaves such repeats (a frame's pose evaluated by several safe sets, say), which
    XLA's own CSE removes; here every equation would become C."""
    import jax.extend.core as jcore

    rep: dict = {}
    seen: dict = {}
    eqns = []
    for e in jaxpr.eqns:
        ins = [rep.get(v, v) if not isinstance(v, jcore.Literal) else v for v in e.invars]
        try:
            key = (e.primitive, tuple((k, _param_key(v)) for k, v in sorted(e.params.items())),
                   tuple(("lit", str(v.aval.dtype), np.asarray(v.val).tobytes())
                         if isinstance(v, jcore.Literal) else v for v in ins))
            hash(key)
        except TypeError:
            key = None
        if key is not None and not e.effects and key in seen:
            for a, b in zip(e.outvars, seen[key]):
                rep[a] = b
            continue
        if key is not None and not e.effects:
            seen[key] = e.outvars
        eqns.append(e.replace(invars=ins) if any(a is not b for a, b in zip(ins, e.invars))
                    else e)
    if len(eqns) == len(jaxpr.eqns):
        return jaxpr
    outs = [rep.get(v, v) if not isinstance(v, jcore.Literal) else v for v in jaxpr.outvars]
    return jaxpr.replace(eqns=eqns, outvars=outs)


def _forward_slices(jaxpr):
    """``jaxpr`` with each unit-stride ``slice`` of a ``concatenate``'s result that lies
    within one of its operands read from that operand instead (the operand itself where
    the slice is all of it), repeatedly through nested concatenations. A matrix assembled
    by blocks and sliced back into its blocks (the QP's P, A and G, and the elimination
    that reads their blocks) then costs no copies, and ``_dead_code_removed`` drops an
    assembly nobody else reads; XLA's algebraic simplifier does the same."""
    import jax.extend.core as jcore

    rep: dict = {}
    concat: dict = {}           # a concatenate's result -> (its operands, its dimension)
    eqns = []
    for e in jaxpr.eqns:
        ins = [rep.get(v, v) if not isinstance(v, jcore.Literal) else v for v in e.invars]
        name = e.primitive.name
        if name == "slice" and not any(k != 1 for k in (e.params["strides"] or ())):
            src = ins[0]
            start = list(e.params["start_indices"])
            limit = list(e.params["limit_indices"])
            while src in concat:
                operands, dim = concat[src]
                off, inner = 0, None
                for x in operands:
                    n = int(x.aval.shape[dim])
                    if off <= start[dim] and limit[dim] <= off + n:
                        inner = x
                        break
                    off += n
                if inner is None or isinstance(inner, jcore.Literal):
                    break
                src, start[dim], limit[dim] = inner, start[dim] - off, limit[dim] - off
            if src is not ins[0]:
                if (all(a == 0 for a in start)
                        and tuple(limit) == tuple(int(d) for d in src.aval.shape)):
                    rep[e.outvars[0]] = src
                    continue
                e = e.replace(params={**e.params, "start_indices": tuple(start),
                                      "limit_indices": tuple(limit)})
                ins[0] = src
        elif name == "concatenate":
            concat[e.outvars[0]] = (ins, e.params["dimension"])
        eqns.append(e.replace(invars=ins) if any(a is not b for a, b in zip(ins, e.invars))
                    else e)
    if not rep and all(a is b for a, b in zip(eqns, jaxpr.eqns)):
        return jaxpr
    outs = [rep.get(v, v) if not isinstance(v, jcore.Literal) else v for v in jaxpr.outvars]
    return jaxpr.replace(eqns=eqns, outvars=outs)


def _transposes_into_dots(jaxpr):
    """``jaxpr`` with each ``dot_general`` whose lhs is a matrix transposed by a top-level
    ``transpose`` reading that matrix instead, its contracting dim swapped: the same
    products summed in the same order (a quadratic form's N' P N, say), and the transposed
    copy, where nothing else reads it, left to ``_dead_code_removed``. The lhs only: a
    transposed rhs would put its free dim first, where the row form needs it last."""
    import jax.extend.core as jcore

    transposed: dict = {}       # a transpose's result -> the matrix it transposes
    eqns = []
    for e in jaxpr.eqns:
        name = e.primitive.name
        if (name == "transpose" and len(e.invars[0].aval.shape) == 2
                and tuple(e.params["permutation"]) == (1, 0)):
            transposed[e.outvars[0]] = e.invars[0]
        elif (name == "dot_general" and not isinstance(e.invars[0], jcore.Literal)
              and e.invars[0] in transposed):
            (lc, rc), (lb, _) = e.params["dimension_numbers"]
            if not lb and len(lc) == 1:
                e = e.replace(invars=[transposed[e.invars[0]], *e.invars[1:]],
                              params={**e.params, "dimension_numbers":
                                      (((1 - lc[0],), tuple(rc)), ((), ()))})
        eqns.append(e)
    if all(a is b for a, b in zip(eqns, jaxpr.eqns)):
        return jaxpr
    return jaxpr.replace(eqns=eqns)


def _dead_code_removed(jaxpr):
    """``jaxpr`` without the top-level equations whose results nothing reads (and that
    have no effects). Tracing keeps them (a value computed for a result that was then
    dropped, an assembly that ``_forward_slices`` bypassed); here each would become C."""
    import jax.extend.core as jcore

    live = {v for v in jaxpr.outvars if not isinstance(v, jcore.Literal)}
    kept = []
    for e in reversed(jaxpr.eqns):
        if e.effects or any(v in live for v in e.outvars):
            kept.append(e)
            live.update(v for v in e.invars if not isinstance(v, jcore.Literal))
    if len(kept) == len(jaxpr.eqns):
        return jaxpr
    return jaxpr.replace(eqns=kept[::-1])


ALIASING = frozenset(("convert_element_type", "reshape", "squeeze", "expand_dims", "slice"))
"""Primitives whose result may be a view of their operand's storage (``Emitter.alias``)."""


def _direct_outputs(jaxpr) -> dict:
    """{outvar: its output pointer as a Buf} for the outputs that the equation computing
    them may write in place: computed by a top-level equation that gives a fresh array,
    after the last equation that reads an input or an array that may be on an input's
    storage (the caller may pass one array as an input and an output). The others are
    copied out at the end."""
    import jax.extend.core as jcore

    on_input = set(jaxpr.invars)
    last = -1
    for k, e in enumerate(jaxpr.eqns):
        reads = [v for v in e.invars if not isinstance(v, jcore.Literal) and v in on_input]
        if reads:
            last = k
            if e.primitive.name in ALIASING or any(
                    isinstance(p, (jcore.Jaxpr, jcore.ClosedJaxpr)) or isinstance(p, tuple)
                    for p in e.params.values()):
                on_input.update(e.outvars)
    made = {v: e for k, e in enumerate(jaxpr.eqns) if k > last for v in e.outvars}
    out: dict = {}
    for k, v in enumerate(jaxpr.outvars):
        e = made.get(v)
        if (isinstance(v, jcore.Literal) or v in out or e is None or e.primitive.name in ALIASING
                or any(isinstance(p, (jcore.Jaxpr, jcore.ClosedJaxpr)) for p in e.params.values())):
            continue
        out[v] = Buf(f"out{k}", ctype(v.aval.dtype), tuple(v.aval.shape), np.dtype(v.aval.dtype))
    return out


def emit_function(name: str, closed) -> CFunction:
    """``closed`` (a ClosedJaxpr) as the C function ``name``: its inputs ``const T *in0,
    ...`` and outputs ``T *out0, ...`` are flat arrays of the jaxpr's shapes and dtypes.
    Raises ``UnsupportedPrimitive`` naming the first primitive without a rule."""
    jaxpr = closed.jaxpr
    path = _first_unsupported(jaxpr)
    if path:
        # where the user's code called it: the innermost equation of the path with a frame
        # outside JAX (an equation inside a jitted library function has none)
        where = next((w for w in map(_where, reversed(path)) if w), "no source location")
        raise UnsupportedPrimitive(f"primitive {path[-1].primitive.name!r} has no C rule "
                                   f"(called at {where}; in {name})")
    em = Emitter(name)
    ins = [Buf(f"in{k}", ctype(v.aval.dtype), tuple(v.aval.shape), np.dtype(v.aval.dtype),
               const=True) for k, v in enumerate(jaxpr.invars)]
    consts = [em.const_buf(c) for c in closed.consts]
    # before the outputs' places are chosen
    jaxpr = _dead_code_removed(_transposes_into_dots(_forward_slices(_deduplicate(jaxpr))))
    em.direct = _direct_outputs(jaxpr)
    outs = em.run(jaxpr, ins, consts, dedupe=False)
    # an output that is an input (or a view of one) is copied out of it first: the caller
    # may pass the same array as that input and as an output (a state updated in place)
    for k, o in enumerate(outs):
        if isinstance(o, Buf) and o.name.lstrip("(").startswith("in"):
            b = em.new_buf(jaxpr.outvars[k].aval)
            em.copy(b, o)
            outs[k] = b
    out_params = [f"{ctype(v.aval.dtype)} *out{k}" for k, v in enumerate(jaxpr.outvars)]
    for k, (v, o) in enumerate(zip(jaxpr.outvars, outs)):
        dst = Buf(f"out{k}", ctype(v.aval.dtype), tuple(v.aval.shape), np.dtype(v.aval.dtype))
        em.copy(dst, o)
    params = [f"const {b.ctype} *in{k}" for k, b in enumerate(ins)] + out_params
    proto = f"void {name}({', '.join(params)})"
    decls = [f"SWBC_SHARED {ct} {nm}[{size}];" for ct, nm, size in em.pool.decls]
    # the body in parts of about PART_LINES lines, each a function; the inputs and outputs
    # reach them through file-level pointers. The buffers, pointers and parts are static
    # in one translation unit, and shared where the file is built as several (``UNITS``)
    ptrs = [f"SWBC_SHARED const {b.ctype} *{name}_in{k};" for k, b in enumerate(ins)]
    ptrs += [f"SWBC_SHARED {ctype(v.aval.dtype)} *{name}_out{k};"
             for k, v in enumerate(jaxpr.outvars)]
    parts: list[list[str]] = []
    cur: list[str] = []
    for line in em.lines:
        if line == CUT:
            if len(cur) >= PART_LINES:
                parts.append(cur)
                cur = []
            continue
        cur.append(line)
    parts.append(cur)
    funcs = []
    # the inputs and outputs by their file-level pointers (one pass over each part)
    ports = re.compile(r"\b((?:in|out)\d+)\b")
    for k, body in enumerate(parts):
        text = ports.sub(rf"{name}_\1", "\n".join(body))
        funcs.append(f"#if SWBC_HAS({k})\nSWBC_PART void {name}_part{k}(void) {{\n{text}\n}}\n"
                     "#endif")
    setup = [f"    {name}_in{k} = in{k};" for k in range(len(ins))]
    setup += [f"    {name}_out{k} = out{k};" for k in range(len(jaxpr.outvars))]
    calls = [f"    {name}_part{k}();" for k in range(len(parts))]
    protos = [f"SWBC_PART void {name}_part{k}(void);" for k in range(len(parts))]
    used = set(re.findall(rf"\b{name}_c\d+\b", "\n".join(funcs)))
    const_decls = [c for c in em.consts if c.split("[", 1)[0].rsplit(" ", 1)[1] in used]
    code = "\n".join(const_decls + decls + ptrs + protos + funcs
                      + ["#if SWBC_MAIN", f"SWBC_API {proto} {{", *setup, *calls, "}",
                         "#endif"])
    nbytes = sum(size * (8 if ct in ("double", "int64_t", "uint64_t") else
                         4 if ct in ("float", "int32_t", "uint32_t") else 1)
                 for ct, _, size in em.pool.decls)
    return CFunction(name, code + "\n", proto, [v.aval for v in jaxpr.invars],
                     [v.aval for v in jaxpr.outvars], nbytes)


def _subjaxprs(eqn):
    import jax.extend.core as jcore

    for p in eqn.params.values():
        for sub in (p if isinstance(p, (list, tuple)) else [p]):
            if isinstance(sub, jcore.ClosedJaxpr):
                yield sub.jaxpr
            elif isinstance(sub, jcore.Jaxpr):
                yield sub
            elif hasattr(sub, "_fields"):      # custom_linear_solve's jaxprs
                for s in sub:
                    if isinstance(s, jcore.ClosedJaxpr):
                        yield s.jaxpr


def _first_unsupported(jaxpr) -> list:
    """The equations from the top down to the first one (depth first) whose primitive has
    no rule; [] where every primitive has one."""
    for e in jaxpr.eqns:
        if e.primitive.name not in RULES:
            return [e]
        for sub in _subjaxprs(e):
            path = _first_unsupported(sub)
            if path:
                return [e, *path]
    return []


UNITS = """
/* One translation unit, as written. Built with -DSWBC_UNITS=N -DSWBC_UNIT=k for k < N,
   it is N units that compile in parallel (each with the parts k, k + N, ...; unit 0
   defines the shared buffers and the entry points), linked into one library. */
#ifndef SWBC_UNITS
#define SWBC_SHARED static
#define SWBC_PART static
#define SWBC_HAS(k) 1
#define SWBC_MAIN 1
#define SWBC_API
#else
#define SWBC_API __attribute__((visibility("default")))  /* built -fvisibility=hidden */
#if SWBC_UNIT == 0
#define SWBC_SHARED
#else
#define SWBC_SHARED extern
#endif
#define SWBC_PART
#define SWBC_HAS(k) ((k) % SWBC_UNITS == SWBC_UNIT)
#define SWBC_MAIN (SWBC_UNIT == 0)
#endif
"""


def c_file(functions: list[CFunction], header_name: str | None = None) -> str:
    """One C99 file of ``functions`` with the runtime routines; it includes
    ``header_name``, or declares the functions itself where that is None. It builds as
    one translation unit, or as several (``UNITS``)."""
    body = "\n".join(f.code for f in functions)
    head = (f'#include "{header_name}"\n' if header_name else
            "".join(f.prototype + ";\n" for f in functions))
    return ("/* Generated by safewbc-jax from the controller's JAX definition. */\n"
            "#include <math.h>\n#include <stdint.h>\n#include <string.h>\n"
            + head + UNITS + RUNTIME + "\n" + body)


def c_header(functions: list[CFunction], guard: str) -> str:
    lines = [f"#ifndef {guard}", f"#define {guard}", "#include <stdint.h>", ""]
    for f in functions:
        sizes = ", ".join(str(int(np.prod(a.shape, dtype=np.int64))) for a in f.in_avals)
        outs = ", ".join(str(int(np.prod(a.shape, dtype=np.int64))) for a in f.out_avals)
        lines.append(f"/* inputs of sizes ({sizes}); outputs of sizes ({outs}) */")
        lines.append(f.prototype + ";")
    lines += ["", f"#endif  /* {guard} */", ""]
    return "\n".join(lines)
