"""The C emitter (``deploy.codegen``): each rule's C against XLA on random inputs of several
shapes, NaN and out-of-range indices included, all built as one C file (one compile), and
an unsupported primitive refused by name.

Tolerance: 1e-12 relative to max(1, |XLA's value|). Both sides evaluate the same float64
operations; they differ only where the order of a sum differs (a dot product, a
factorisation: a few ulp for these sizes and well-conditioned matrices) or where libm and
XLA's own approximations of sin, exp, ... differ (1 ulp), far below 1e-12. Integer,
boolean and index results are compared exactly.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax import lax

import safewbc_jax
from safewbc_jax.deploy.codegen import build, emit

safewbc_jax.enable_x64()
RTOL = 1e-12
rng = np.random.default_rng(7)


def _r(*shape):
    return rng.standard_normal(shape)


def _spd(n, batch=()):
    a = rng.standard_normal(batch + (n, n))
    return a @ np.swapaxes(a, -1, -2) + n * np.eye(n)


def _profile_spd(n):
    """A positive definite matrix whose rows start at random columns (a profile, as a
    mass matrix factored leaves first has): L L' with L zero left of each row's start."""
    first = [int(rng.integers(0, i + 1)) for i in range(n)]
    low = np.tril(rng.standard_normal((n, n))) + n * np.eye(n)
    for i, k in enumerate(first):
        low[i, :k] = 0.0
    return low @ low.T


def _with_nan(x):
    x = np.array(x)
    x.flat[::5] = np.nan
    return x


SPARSE = np.where(rng.random((6, 5)) < 0.3, rng.standard_normal((6, 5)), 0.0)
SPARSE[2] = 0.0                                  # an empty row
SPARSE3 = np.where(rng.random((3, 2, 5)) < 0.3, 1.0, 0.0)
tril = lambda a: jnp.tril(a) + 3 * jnp.eye(a.shape[-1])  # noqa: E731
CASES = {
    # elementwise, implicit broadcast of size-1 dims, scalars, NaN
    "unary": (lambda x: jnp.stack([jnp.sin(x), jnp.cos(x), jnp.exp(x / 3), jnp.tanh(x),
                                   jnp.sinh(x), jnp.cosh(x), jnp.abs(x), -x, jnp.floor(x),
                                   jnp.round(x), jnp.sign(x), x ** 3, jnp.sqrt(jnp.abs(x)),
                                   jnp.arcsin(jnp.tanh(x)), jnp.isfinite(x) * 1.0]),
              [_with_nan(_r(4, 5))]),
    "binary": (lambda x, y: jnp.stack([x + y, x - y, x * y, x / y, jnp.arctan2(x, y),
                                       jnp.maximum(x, y), jnp.minimum(x, y),
                                       jnp.where(x > y, x, y), jnp.fmod(x, y),
                                       (x >= y) * 1.0, (x == y) * 1.0]),
               [_with_nan(_r(3, 4)), _r(3, 4)]),
    "broadcast": (lambda x, y, z: x * y + z - 2.0, [_r(5, 1, 1), _r(5, 3, 3), _r(1, 3, 3)]),
    "clip_select": (lambda x, i: (jnp.clip(x, -0.5, 0.5),
                                  lax.select_n(i, x, 2 * x, 3 * x)),
                    [_r(2, 6), rng.integers(0, 3, (2, 6)).astype(np.int32)]),
    "ints": (lambda a, b: (a // b, a % b, a * b - 3, jnp.maximum(a, b), a & b, a | b, ~a,
                           (a < b) & (a > 0)),
             [rng.integers(-9, 9, (7,)).astype(np.int32),
              rng.integers(1, 5, (7,)).astype(np.int32)]),
    "convert": (lambda x: (x.astype(jnp.int32), (x > 0).astype(jnp.float64),
                           x.astype(jnp.int64) * 2), [3 * _r(6)]),
    # layout
    "layout": (lambda x: (x.T, x.reshape(2, 6)[:, ::2], x[1:, 2:], jnp.flip(x, 0),
                          jnp.concatenate([x, 2 * x], 1), jnp.stack([x, x], 1),
                          x[:, None, :] * jnp.ones((1, 2, 1)), jnp.expand_dims(x, 0).sum(0)),
               [_r(3, 4)]),
    "pad": (lambda x: (lax.pad(x, 0.5, [(1, -1, 1), (-1, 2, 0)]), jnp.pad(x, 2)),
            [_r(4, 3)]),
    "iota": (lambda x: x + jnp.arange(12.0).reshape(3, 4) + lax.broadcasted_iota(
        jnp.int32, (3, 4), 0), [_r(3, 4)]),
    "dynamic": (lambda x, i: (lax.dynamic_slice(x, (i, i + 1), (2, 2)),
                              lax.dynamic_update_slice(x, jnp.ones((2, 2)), (i, i))),
                [_r(4, 5), np.int32(3)]),
    "dynamic_clamped": (lambda x, i: lax.dynamic_slice(x, (i, -i), (2, 3)),
                        [_r(4, 5), np.int32(9)]),
    # reductions
    "reduce": (lambda x: (x.sum(0), x.max(1), x.min(), jnp.prod(x, 1), (x > 0).all(1),
                          (x > 0).any(0), jnp.argmax(x, 1), jnp.argmin(x, 0),
                          jnp.cumsum(x, 1), lax.cumsum(x, 0, reverse=True)),
               [_r(4, 6)]),
    "reduce_nan": (lambda x: (x.max(1), jnp.argmax(x, 1), jnp.argmin(x, 1)),
                   [_with_nan(_r(3, 7))]),
    "dot": (lambda a, b, c: (a @ b, jnp.einsum("bij,bjk->bik", c, c),
                             jnp.einsum("ij,ij->i", a, a), jnp.tensordot(c, a, ([2], [0]))),
            [_r(4, 4), _r(4, 3), _r(2, 4, 4)]),
    # a run-time lhs with zeros (rows of contacts): its zero entries skip their row updates
    "dot_zeros": (lambda a, b: (a @ b, jnp.einsum("bij,bjk->bik", a[None], b[None])),
                  [np.where(rng.random((5, 7)) < 0.7, 0.0, _r(5, 7)), _r(7, 6)]),
    # a constant lhs mostly zeros: contracted over its nonzeros only
    "dot_sparse_const": (lambda x, y: (jnp.asarray(SPARSE) @ x, jnp.asarray(SPARSE) @ y,
                                       jnp.einsum("ijk,k->ij", jnp.asarray(SPARSE3), y)),
                         [_r(5, 4), _r(5)]),
    # indexing
    "gather": (lambda x, i: (x[i], jnp.take(x, i, axis=1, mode="clip"),
                             jnp.take(x, i, axis=0, mode="fill", fill_value=-1.0),
                             x[i, i % 3]),
               [_r(5, 4), np.array([0, 4, 2, 7, -1], np.int32)]),
    "scatter": (lambda x, i, u: (x.at[i].set(u), x.at[i].add(u), x.at[i].mul(u),
                                 x.at[i, 1].set(u[:, 0])),
                [_r(6, 3), np.array([1, 4, 4, 9], np.int32), _r(4, 3)]),
    "sort": (lambda x, k: (jnp.sort(x, axis=1), lax.sort((k, x[0]), num_keys=1),
                           jnp.argsort(x[1])),
             [_with_nan(_r(2, 6)), rng.integers(0, 3, 6).astype(np.int32)]),
    # control flow
    "scan": (lambda x: lax.scan(lambda c, xi: (c * 0.5 + xi, c + xi.sum()), x[0], x)[0:2],
             [_r(5, 3)]),
    "while": (lambda x: lax.fori_loop(0, 7, lambda i, c: c * 0.9 + jnp.sin(c) + i, x),
              [_r(4)]),
    "cond": (lambda x, i: (lax.cond(x.sum() > 0, lambda a: a * 2, lambda a: -a, x),
                           lax.switch(i, [jnp.sin, jnp.cos, jnp.exp], x)),
             [_r(3), np.int32(2)]),
    # linear algebra, batched too
    "cholesky": (lambda a, p: (jnp.linalg.cholesky(a), jnp.linalg.cholesky(-a),
                               jnp.linalg.cholesky(p)), [_spd(5, (2,)), _profile_spd(9)]),
    "lu_solve": (lambda a, b: (jnp.linalg.solve(a, b), lax.linalg.lu(a)[0], lax.linalg.lu(a)[2]),
                 [_r(5, 5) + 3 * np.eye(5), _r(5, 2)]),
    "triangular": (lambda a, b, c: tuple(
        lax.linalg.triangular_solve(tril(a) if low else tril(a).T, m, left_side=left,
                                    lower=low, transpose_a=tr, unit_diagonal=unit)
        for left, m in ((True, b), (False, c)) for low in (True, False)
        for tr in (True, False) for unit in (True, False)),
        [_r(4, 4), _r(4, 3), _r(2, 4)]),
    "cho_solve": (lambda a, b: jax.scipy.linalg.cho_solve(jax.scipy.linalg.cho_factor(a), b),
                  [_spd(6), _r(6)]),
}


@pytest.fixture(scope="module")
def compiled(tmp_path_factory, monkeypatch_module):
    fns, jitted = {}, {}
    for name, (f, args) in CASES.items():
        closed = jax.make_jaxpr(f)(*args)
        fns[name] = emit.emit_function(f"t_{name}", closed)
        jitted[name] = jax.jit(f)
    path, _ = build.build(emit.c_file(list(fns.values())))
    lib = build.load(path)
    return {n: build.CCall(lib, fn) for n, fn in fns.items()}, jitted


@pytest.fixture(scope="module")
def monkeypatch_module(tmp_path_factory):
    mp = pytest.MonkeyPatch()
    mp.setenv("SAFEWBC_C_CACHE", str(tmp_path_factory.mktemp("c_cache")))
    yield mp
    mp.undo()


@pytest.mark.parametrize("name", list(CASES))
def test_rule_against_xla(compiled, name):
    calls, jitted = compiled
    args = CASES[name][1]
    want = jax.tree_util.tree_leaves(jitted[name](*args))
    got = calls[name](*args)
    assert len(got) == len(want)
    for k, (w, g) in enumerate(zip(want, got)):
        w = np.asarray(w)
        g = np.asarray(g).reshape(w.shape)
        if w.dtype.kind != "f":
            np.testing.assert_array_equal(g, w, err_msg=f"{name} output {k}")
            continue
        np.testing.assert_array_equal(np.isnan(g), np.isnan(w), err_msg=f"{name} output {k}")
        fin = np.isfinite(w)
        np.testing.assert_array_equal(g[~fin & ~np.isnan(w)], w[~fin & ~np.isnan(w)])
        np.testing.assert_allclose(g[fin], w[fin], rtol=0,
                                   atol=RTOL * max(1.0, float(np.abs(w[fin]).max(initial=0))),
                                   err_msg=f"{name} output {k}")


def test_the_build_flags_compute_the_same_bits(compiled):
    """Every rule's C as the engine builds it (``build.opt_flags``, gcc's vectorising
    -O2, and this CPU's x86-64 level, ``build.isa_flags``: AVX2 vectors) gives the same
    bits as the same C built with -O3 for the baseline x86-64: contraction is off and no
    reduction is reordered, so the flags change the speed and nothing else (C lanes held
    to one robot's loop exactly, caches per level)."""
    if not build.isa_flags() and build.opt_flags() == build.OPT_OTHER:
        pytest.skip("the engine's flags are -O3 for the baseline x86-64 here")
    calls, _ = compiled
    fns = {n: c.fn for n, c in calls.items()}
    base = build.load(build.build(emit.c_file(list(fns.values())), isa=False,
                                  opt=build.OPT_OTHER)[0])
    for name, fn in fns.items():
        got = calls[name](*CASES[name][1])
        want = build.CCall(base, fn)(*CASES[name][1])
        for k, (g, w) in enumerate(zip(got, want)):
            np.testing.assert_array_equal(g, w, err_msg=f"{name} output {k}")


def test_isa_level_from_the_compilers_macros():
    """``build.isa_level``: the highest x86-64 level (v2 or v3) whose features are all
    defined, each level needing the ones below it."""
    v2 = {"__SSE3__", "__SSSE3__", "__SSE4_1__", "__SSE4_2__", "__POPCNT__"}
    v3 = v2 | {"__AVX__", "__AVX2__", "__BMI__", "__BMI2__", "__F16C__", "__FMA__",
               "__LZCNT__", "__MOVBE__"}
    v4 = v3 | {"__AVX512F__", "__AVX512BW__", "__AVX512CD__", "__AVX512DQ__", "__AVX512VL__"}
    assert build.isa_level(set()) is None
    assert build.isa_level(v2 - {"__POPCNT__"}) is None
    assert build.isa_level(v2) == "x86-64-v2"
    assert build.isa_level(v3 - {"__FMA__"}) == "x86-64-v2"
    assert build.isa_level(v3) == "x86-64-v3"
    assert build.isa_level(v4) == "x86-64-v3"                  # v4 is not used (build.py)
    assert build.isa_level(v4 - v2 | {"__SSE3__"}) is None     # AVX-512 without SSE4


def test_shapes_of_the_same_rule(monkeypatch, tmp_path):
    """One rule (a batched matmul with broadcasting) at several shapes, from 0-d to 3-d."""
    monkeypatch.setenv("SAFEWBC_C_CACHE", str(tmp_path))
    f = lambda a, b: jnp.tanh(a @ b) * 2.0 + a.sum()  # noqa: E731
    shapes = [((), ()), ((3,), (3,)), ((2, 3), (3, 4)), ((2, 3, 3), (2, 3, 1))]
    fns, args = [], []
    for k, (sa, sb) in enumerate(shapes):
        a, b = rng.standard_normal(sa), rng.standard_normal(sb)
        g = (lambda x, y: x * y * 2.0 + x) if not sa else f
        fns.append((emit.emit_function(f"s{k}", jax.make_jaxpr(g)(a, b)), g))
        args.append((a, b))
    lib = build.load(build.build(emit.c_file([fn for fn, _ in fns]))[0])
    for (fn, g), (a, b) in zip(fns, args):
        (got,) = build.CCall(lib, fn)(a, b)
        want = np.asarray(jax.jit(g)(a, b))
        np.testing.assert_allclose(got.reshape(want.shape), want, rtol=RTOL, atol=RTOL)


def test_an_unsupported_primitive_is_refused_by_name():
    closed = jax.make_jaxpr(lambda x: jnp.fft.fft(x).real)(np.ones(8))
    with pytest.raises(emit.UnsupportedPrimitive, match="'fft'"):
        emit.emit_function("f", closed)


def test_buffers_are_reused_by_liveness():
    """A chain of 50 operations on a 1000-vector needs two or three buffers, not 50."""
    def chain(x):
        for k in range(50):
            x = jnp.sin(x) + k
        return x
    fn = emit.emit_function("chain", jax.make_jaxpr(chain)(np.ones(1000)))
    assert fn.buffer_bytes <= 3 * 8 * 1000, fn.buffer_bytes


def test_a_free_buffer_grows_instead_of_a_new_one(monkeypatch):
    """Small arrays whose buffers are free by the time a larger one is needed: with
    ``emit.GROW`` one of them grows to the larger size, without it a new buffer is made;
    the C computes the same bits either way."""
    def f(x, y):
        a = jnp.sin(x) * 2.0
        b = jnp.cos(x) * 3.0
        s = a.sum() + b.sum()
        return jnp.tanh(y) * s + 1.0
    args = (_r(10), _r(500))
    closed = jax.make_jaxpr(f)(*args)
    fns, got = {}, {}
    for grow in (False, True):
        monkeypatch.setattr(emit, "GROW", grow)
        fns[grow] = emit.emit_function(f"grow{int(grow)}", closed)
        lib = build.load(build.build(emit.c_file([fns[grow]]))[0])
        got[grow] = build.CCall(lib, fns[grow])(*args)[0]
    count = {g: fn.code.count("SWBC_SHARED double") for g, fn in fns.items()}
    assert count[True] < count[False], count
    np.testing.assert_array_equal(got[True], got[False])
    np.testing.assert_allclose(got[True], np.asarray(jax.jit(f)(*args)), rtol=RTOL)


def test_literals_are_exact():
    for x in (0.1, -1e-300, 1.0 / 3.0, 2.0 ** 60):
        assert float.fromhex(emit.c_literal(x, np.float64).strip("()")) == x
    assert emit.c_literal(np.nan, np.float64) == "NAN"



def test_a_sparse_constant_is_contracted_over_its_nonzeros_with_the_same_bits():
    """The emitted loop visits the constant's nonzeros only (its CSR arrays are in the C),
    and gives the dense product's bits: the same products, added in the same order."""
    x = _r(5, 7)
    fn = emit.emit_function("sp", jax.make_jaxpr(lambda x: jnp.asarray(SPARSE) @ x)(x))
    nnz = int(np.count_nonzero(SPARSE))
    assert f"[{nnz}] = {{" in fn.code and f"[{SPARSE.shape[0] + 1}] = {{" in fn.code
    lib = build.load(build.build(emit.c_file([fn]))[0])
    (got,) = build.CCall(lib, fn)(x)
    want = np.zeros((6, 7))
    for i in range(6):
        for k in range(5):
            want[i] += SPARSE[i, k] * x[k]
    np.testing.assert_array_equal(got, want)


def test_an_output_may_be_the_array_of_an_input():
    """The caller may pass one array as an input and an output (a state updated in
    place). An output computed before the last read of that input is not written in
    place: here the first output is computed before the input is read again."""
    import ctypes

    f = lambda s: (jnp.concatenate([s[1:], s[:1]]), s * 3.0)  # noqa: E731
    s0 = _r(6)
    fn = emit.emit_function("inplace", jax.make_jaxpr(f)(s0))
    lib = build.load(build.build(emit.c_file([fn]))[0])
    s, out1 = s0.copy(), np.zeros(6)
    ptr = lambda a: a.ctypes.data_as(ctypes.c_void_p)  # noqa: E731
    getattr(lib, "inplace")(ptr(s), ptr(s), ptr(out1))
    np.testing.assert_array_equal(s, np.roll(s0, -1))
    np.testing.assert_array_equal(out1, s0 * 3.0)


def test_constants_are_folded_and_contiguous_slices_of_inputs_are_views():
    """Equations on constants alone (an identity's rows, an iota, their sum) are computed
    at generation (no loop for them in the C), and a contiguous slice of an input is
    read where it lies (no copy loop): two loops remain, the product and the sum."""
    def f(x):
        c = jnp.eye(4)[0:3] + lax.broadcasted_iota(jnp.float64, (3, 4), 1)
        return x[2:5] * 2.0 + c
    x = _r(6, 4)
    fn = emit.emit_function("fold", jax.make_jaxpr(f)(x))
    assert fn.code.count("for (") == 2, fn.code
    lib = build.load(build.build(emit.c_file([fn]))[0])
    (got,) = build.CCall(lib, fn)(x)
    np.testing.assert_array_equal(got, np.asarray(jax.jit(f)(x)))


def test_repeated_equations_are_computed_once():
    """An equation that repeats an earlier one (same primitive, parameters and inputs) is
    read from the earlier one's result, also where a jitted call repeats: one sin, one
    exp in the C. A literal of another value (-0.0 against 0.0) is a different input."""
    inner = jax.jit(lambda x: jnp.exp(x) * 3.0)

    def f(x):
        a, b = jnp.sin(x) * 2.0, jnp.sin(x) * 2.0
        return a + b + inner(x) + inner(x), jnp.maximum(x, 0.0) + jnp.maximum(x, -0.0)
    x = _with_nan(_r(7))
    fn = emit.emit_function("dedup", jax.make_jaxpr(f)(x))
    assert fn.code.count("sin(") == 1 and fn.code.count("exp(") == 1, fn.code
    assert "(0x0.0p+0)" in fn.code and "(-0x0.0p+0)" in fn.code    # both maxima kept
    lib = build.load(build.build(emit.c_file([fn]))[0])
    for got, want in zip(build.CCall(lib, fn)(x), jax.jit(f)(x)):   # libm's sin and exp
        np.testing.assert_allclose(got, np.asarray(want), rtol=1e-12)   # against XLA's


def test_slices_of_a_block_assembly_read_the_blocks_and_unread_results_are_dropped():
    """A matrix assembled by blocks (nested concatenations) and sliced back: each slice
    within one block reads that block (the assembly itself becomes dead and is not
    emitted), a slice across two blocks still reads the assembly. Unread results (the
    cosine) are not emitted. The C equals XLA exactly (the same copies and products)."""
    across = jax.make_jaxpr(lambda a, b: jnp.concatenate([a, b])[1:4])(_r(2), _r(3))
    kept = emit._dead_code_removed(emit._forward_slices(across.jaxpr))
    assert [e.primitive.name for e in kept.eqns] == ["concatenate", "slice"]
    def f(a, b, c):
        top = jnp.concatenate([a * 2.0, b], axis=1)              # (3, 2 + 4)
        m = jnp.concatenate([top, c + 1.0], axis=0)              # (3 + 2, 6)
        _ = jnp.cos(a)
        return m[0:3, 2:6] * 3.0, m[3:5, 1:4], m[1:2, 0:1] + m[3:5, :].sum()
    args = (_r(3, 2), _r(3, 4), _r(2, 6))
    closed = jax.make_jaxpr(f)(*args)
    fn = emit.emit_function("blocks", closed)
    assert "cos(" not in fn.code
    # each slice lies in one block: the first reads b, the second c + 1, the third's
    # a * 2 and all of c + 1 (the block itself)
    simplified = emit._dead_code_removed(emit._forward_slices(closed.jaxpr))
    prims = [e.primitive.name for e in simplified.eqns]
    assert prims.count("concatenate") == 0 and "cos" not in prims, prims
    lib = build.load(build.build(emit.c_file([fn]))[0])
    for got, want in zip(build.CCall(lib, fn)(*args), jax.jit(f)(*args)):
        np.testing.assert_array_equal(got, np.asarray(want))


def test_a_compiler_that_cannot_build_is_not_used(monkeypatch):
    """``build.works``: True with the system compiler (CI has gcc), False where ``$CC``
    names a program that builds nothing (``false``): the sweep's lanes then run XLA's
    step (``pool.lanes_engine``)."""
    from safewbc_jax.sweeps.pool import lanes_engine

    build.works.cache_clear()
    try:
        assert build.works() and lanes_engine() == "c"
        monkeypatch.setenv("CC", "false")
        build.works.cache_clear()
        assert build.compiler() == "false" and not build.works() and lanes_engine() == "xla"
    finally:
        monkeypatch.delenv("CC")
        build.works.cache_clear()


def test_a_ccall_reads_an_array_passed_again_afresh():
    """``CCall`` keeps the address of the array last passed at each input: the same array,
    changed in place, gives the new result; another array, or one it must convert (a list,
    float32), is read as given; a call with the wrong number of inputs is refused."""
    def f(x, y):
        return jnp.sin(x) * y
    x, y = _r(7), _r(7)
    fn = emit.emit_function("again", jax.make_jaxpr(f)(x, y))
    call = build.CCall(build.load(build.build(emit.c_file([fn]))[0]), fn)
    np.testing.assert_allclose(call(x, y)[0], np.sin(x) * y, rtol=RTOL)
    x[:] = _r(7)
    np.testing.assert_allclose(call(x, y)[0], np.sin(x) * y, rtol=RTOL)   # same array, new data
    z = y.astype(np.float32).tolist()
    np.testing.assert_allclose(call(x.copy(), z)[0], np.sin(x) * np.asarray(z), rtol=RTOL)
    with pytest.raises(ValueError, match="1 inputs, expected 2"):
        call(x)
