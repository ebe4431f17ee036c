"""The batched JAX QP solver (safewbc_jax/solvers/jax_qp.py) against PIQP on recorded
controller QPs, and the qpsolvers-style ``solve_qp`` over both solvers.

Data: tests/data/controller_qps.npz, 1,137 QPs recorded from the deployment runs of every
scenario (``tests/data/record_qps.py``: squat, bow, arms with and without the barrier,
walking), PIQP statuses included; storage format in ``tests/data/qp_fixture.py``.

Infeasible instances are derived deterministically from recorded ones (``_conflict``): the
QP is reduced exactly to the torques (X = x0 + N u, ``reduce.eliminate_equalities_np``),
so the least value that row i of G can take over the torque box is
g0 + sum_j min(g_j lb_j, g_j ub_j) with g = G_i N, g0 = G_i x0; h_i is set below it by
``frac`` of the row's range over the box. The row then contradicts the torque limits:
  * on a soft row (the largest ZMP/barrier row in the reduced space) the QP is infeasible
    but its relaxation is not (the recorded solution satisfies every hard row):
    PIQP and the JAX solver must both report INFEASIBLE and fall back to "relaxed";
  * on a hard row (the largest friction/contact row) the relaxation is infeasible too:
    both must report INFEASIBLE and "failed" (JAX: x all NaN, to be ignored by the caller,
    who holds its last torque; PIQP path: x None).

Reference solutions: PIQP at tight tolerances (``TIGHT``: residuals 1e-12 absolute /
1e-14 relative, and the duality gap as tight). On 332 of the 1,137 recorded QPs PIQP's
duality-gap test never passes at those tolerances (0 of 332 with 200 iterations, with or
without its preconditioner), while its primal and dual residuals do: there the reference
is PIQP at the same residual tolerances with the gap test off (``TIGHT_NO_GAP``).
Measured (``jax_qp.solve_batch`` against these references): max |X - X_piqp| / max(1,
|X_piqp|) 2.1e-9 on the 805 tight QPs and 9.1e-9 on the 332 others. The looser fallback
used before (eps_abs 1e-10, eps_rel 1e-12 with the gap test on) left one QP at 1.5e-6 and
p99 1e-7: PIQP's defaults leave x up to ~5e-5 (relative) from the exact optimum on these
QPs (the internal-force directions of lambda cost only the small Gamma), too loose for
the 1e-6 agreement checked here. The KKT certificate test checks the JAX solution with
no second solver at all.

Runs in ~1 minute on a 2-core CPU (its XLA compiles, ~8 s each, dominate).
"""

from __future__ import annotations

from pathlib import Path

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from safewbc_jax.base import chunking
from safewbc_jax.solvers.problem import QP
from safewbc_jax.solvers import (INFEASIBLE, MAX_ITER, SOLVED, SolveStatus, jax_qp, reduce,
                                 solve_qp)
from safewbc_jax.solvers.piqp_path import PiqpSolver, residuals, solve_qp_piqp
from safewbc_jax.solvers.result import SolveResult, fallback_name

FIELDS = ("P", "q", "A", "b", "G", "h", "lb", "ub", "soft")
FIXTURE = Path(__file__).parent / "data" / "controller_qps.npz"
NV, NU = 36, 20       # Digit's: the fixture's QPs are the controller's (X = [q_ddot, u, lambda])
TIGHT = {"eps_abs": 1e-12, "eps_rel": 1e-14, "eps_duality_gap_abs": 1e-12,
         "eps_duality_gap_rel": 1e-14, "max_iter": 60}
TIGHT_NO_GAP = {**TIGHT, "check_duality_gap": False}
REF = {"eps_abs": 1e-10, "eps_rel": 1e-12}
N_INFEAS = 6        # soft-infeasible and hard-infeasible instances each


@pytest.fixture(scope="module", autouse=True)
def one_blas_thread():
    """jaxlib's CPU LAPACK kernels run on scipy's OpenBLAS; its worker threads, left
    spinning after a call, compete with XLA's thread pool on this 2-core machine and can
    slow the solver tenfold. One thread for this module, restored afterwards."""
    with jax_qp.blas_threads(1):
        yield


def _fixture_module():
    """tests/data/qp_fixture.py (the fixture's storage format)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("qp_fixture", FIXTURE.with_name("qp_fixture.py"))
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _sized(arrays) -> QP:
    """The fixture's arrays as the controller's QP, with its block sizes (as qp.assemble
    gives them)."""
    n = np.shape(arrays[0])[-1]
    return QP(*arrays, nv=NV, nu=NU, nc=n - NV - NU)


def _take(data, i) -> QP:
    return _sized([np.asarray(data[f][i]) for f in FIELDS])


def _batch(data, idx=slice(None)) -> QP:
    return _sized([jnp.asarray(data[f][idx]) for f in FIELDS])


def _conflict(qp: QP, soft: bool, frac: float) -> tuple[QP, int, float]:
    """(QP with row i below its least value over the torque box, i, the gap); see the
    module docstring."""
    red, rmap = reduce.eliminate_equalities_np(qp)
    rows = np.flatnonzero((qp.soft > 0) == soft)
    i = rows[np.argmax(np.abs(red.G[rows]).sum(axis=1))]
    g = red.G[i]
    lo = np.minimum(g * red.lb, g * red.ub).sum()
    hi = np.maximum(g * red.lb, g * red.ub).sum()
    gap = frac * (hi - lo)
    h = qp.h.copy()
    h[i] = qp.G[i] @ rmap.x0 + lo - gap
    return dataclasses.replace(qp, h=h), int(i), float(gap)


@pytest.fixture(scope="module")
def data():
    """The recorded QPs (stacked numpy fields) plus the derived infeasible ones at the end:
    N_INFEAS soft-infeasible, then N_INFEAS hard-infeasible."""
    d = _fixture_module().load(FIXTURE)
    out = {f: d[f"qp_{f}"] for f in FIELDS}
    recorded_status = d["qp_status"]
    nrec = out["P"].shape[0]
    assert nrec >= 1000 and set(d["qp_scenario"]) >= {"squat", "bow", "arms", "arms_no_barrier"}
    picks = np.linspace(0, nrec - 1, N_INFEAS).astype(int)
    extra, meta = [], []
    for soft in (True, False):
        for k, i in enumerate(picks):
            frac = 1e-2 if k % 2 == 0 else 1e-4      # clear and marginal contradictions
            qp, row, gap = _conflict(_take(out, i), soft, frac)
            extra.append(qp)
            meta.append((soft, row, gap))
    for f in FIELDS:
        out[f] = np.concatenate([out[f], np.stack([getattr(q, f) for q in extra])])
    return {"qps": out, "nrec": nrec, "meta": meta, "recorded_status": recorded_status,
            "scenario": d["qp_scenario"].astype(str)}


@pytest.fixture(scope="module")
def jax_result(data):
    """One batched JAX solve of every QP (recorded and derived)."""
    res = jax_qp.solve_batch(_batch(data["qps"]))
    return jax.tree_util.tree_map(np.asarray, res)


@pytest.fixture(scope="module")
def piqp_ref(data):
    """PIQP's solution of every recorded QP (TIGHT, else TIGHT_NO_GAP), no fallback, and
    whether TIGHT was reached."""
    xs, sts, tight = [], [], []
    for i in range(data["nrec"]):
        qp = _take(data["qps"], i)
        x, st = solve_qp_piqp(qp, **TIGHT)
        tight.append(st == SolveStatus.SOLVED)
        if st != SolveStatus.SOLVED:
            x, st = solve_qp_piqp(qp, **TIGHT_NO_GAP)
        xs.append(x)
        sts.append(st)
    return xs, sts, np.array(tight)


# ---------------------------------------------------------------- recorded QPs

def test_recorded_qps_agree_with_piqp(data, jax_result, piqp_ref):
    nrec = data["nrec"]
    xs, sts, tight = piqp_ref
    r = jax_result
    assert all(s == SolveStatus.SOLVED for s in sts)
    if data["recorded_status"] is not None:          # the statuses recorded at run time
        np.testing.assert_array_equal(data["recorded_status"], SOLVED)
    np.testing.assert_array_equal(r.status[:nrec], SOLVED)
    np.testing.assert_array_equal(r.fallback[:nrec], jax_qp.FALLBACK_NONE)
    assert r.polished[:nrec].all()                   # exact active-set KKT points
    err = np.array([np.abs(r.x[i] - xs[i]).max() / max(1.0, np.abs(xs[i]).max())
                    for i in range(nrec)])
    # measured 2.1e-9 (TIGHT) and 9.1e-9 (TIGHT_NO_GAP): the bound, on every QP
    assert err.max() <= 1e-6, f"max relative |X - X_piqp| = {err.max():.2e} at {err.argmax()}"
    assert tight.sum() >= 0.5 * nrec           # the gap test is off on a minority only
    # residuals of the returned X in the full (78-variable) QP, absolute
    assert r.eq_residual[:nrec].max() <= 1e-8
    assert r.ineq_violation[:nrec].max() <= 1e-8
    for i in range(0, nrec, max(1, nrec // 50)):     # recomputed independently
        eq, ineq, _ = residuals(r.x[i], _take(data["qps"], i))
        assert eq <= 1e-8 and ineq <= 1e-8


def _kkt(qp: QP, x):
    """(stationarity residual, least multiplier of an active inequality, gradient scale)
    with least-squares multipliers on the active set of x."""
    scale = 1.0 + np.abs(qp.h).max() + np.abs(qp.ub[np.isfinite(qp.ub)]).max()
    # a variable with lb = ub (a passive motor of the walking QPs) is an equality: its
    # multiplier has no sign and would be split arbitrarily between the two bounds
    fixed = np.isfinite(qp.ub) & (qp.ub - qp.lb <= 0.0)
    act_g = qp.G @ x - qp.h > -1e-9 * scale
    act_u = np.isfinite(qp.ub) & (x - qp.ub > -1e-9 * scale) & ~fixed
    act_l = np.isfinite(qp.lb) & (qp.lb - x > -1e-9 * scale) & ~fixed
    eye = np.eye(x.size)
    eq = np.vstack([qp.A, eye[fixed]])
    C = np.vstack([eq, qp.G[act_g], eye[act_u], -eye[act_l]])
    grad = qp.P @ x + qp.q
    mult, *_ = np.linalg.lstsq(C.T, -grad, rcond=None)
    return np.abs(grad + C.T @ mult).max(), mult[eq.shape[0]:].min(initial=0.0), \
        1.0 + np.abs(grad).max()


def test_recorded_qps_kkt_certificate(data, jax_result):
    """Optimality without a second solver: from the active set of the JAX solution,
    least-squares multipliers must satisfy stationarity and have the right signs."""
    r = jax_result
    nrec = data["nrec"]
    for i in range(0, nrec, max(1, nrec // 40)):
        res, least, gscale = _kkt(_take(data["qps"], i), r.x[i])
        assert res <= 1e-8 * gscale, i
        assert least >= -1e-7 * gscale, i


# ---------------------------------------------------------------- infeasible QPs, fallback

def test_infeasible_statuses_and_fallback_agree_with_piqp(data, jax_result):
    nrec = data["nrec"]
    r = jax_result
    piqp = PiqpSolver(update=False, **REF)
    for k, (soft, row, gap) in enumerate(data["meta"]):
        j = nrec + k
        qp = _take(data["qps"], j)
        res_p = piqp.solve(qp)
        x_p = res_p.x
        expect = "relaxed" if soft else "failed"
        assert res_p.status == SolveStatus.INFEASIBLE and fallback_name(res_p.fallback) == expect, k
        assert r.status[j] == INFEASIBLE, k                     # certified, not MAX_ITER
        assert jax_qp.FALLBACK_NAMES[r.fallback[j]] == expect, k
        if soft:
            assert r.relaxed_status[j] == SOLVED
            # equalities, hard rows and bounds hold; the soft row gives at least the gap
            assert r.eq_residual[j] <= 1e-8 and r.hard_violation[j] <= 1e-8
            assert r.max_slack[j] >= gap * (1 - 1e-6)
            assert r.max_slack[j] == pytest.approx(res_p.max_slack, rel=1e-5, abs=1e-8)
            assert np.abs(r.x[j] - x_p).max() <= 1e-6 * max(1.0, np.abs(x_p).max()), k
        else:
            assert r.relaxed_status[j] == INFEASIBLE
            # what the caller gets for a failed step: no usable x at all
            assert np.isnan(r.x[j]).all() and np.isnan(r.max_slack[j]) and np.isnan(x_p).all()


# ---------------------------------------------------------------- jit / vmap at user level

@pytest.mark.slow
def test_user_level_jit_vmap_matches_solve_batch(data, jax_result):
    """``jax_qp.solve`` is a single-QP function: the caller's own jit(vmap(...)) gives the
    batched results (here 6 recorded QPs, a soft- and a hard-infeasible one)."""
    nrec = data["nrec"]
    idx = np.r_[np.linspace(0, nrec - 1, 6).astype(int), nrec, nrec + N_INFEAS]
    qps = _batch(data["qps"], idx)
    fn = jax.jit(jax.vmap(lambda qp: jax_qp.solve(qp, p_blockdiag=True)))
    r = jax.tree_util.tree_map(np.asarray, fn(qps))
    ref = jax_result
    np.testing.assert_array_equal(r.status, ref.status[idx])
    np.testing.assert_array_equal(r.fallback, ref.fallback[idx])
    assert r.fallback.tolist() == [0] * 6 + [jax_qp.FALLBACK_RELAXED, jax_qp.FALLBACK_FAILED]
    ok = r.fallback != jax_qp.FALLBACK_FAILED
    np.testing.assert_allclose(r.x[ok], ref.x[idx][ok], rtol=0,
                               atol=1e-9 * np.nanmax(np.abs(ref.x)))
    assert np.isnan(r.x[~ok]).all()


# ---------------------------------------------------------------- chunked batches

@pytest.mark.slow
def test_chunked_batch_matches_unchunked(data, jax_result):
    """``solve_batch(chunk=8)`` on 20 QPs (3 chunks of 7, padded with a copy of the last
    QP) gives the module's solve of all 1,149 QPs (chunks of 64 on the CPU) for the same
    QPs: the padding is stripped and no QP's result depends on the other QPs of its chunk.
    A soft- and a hard-infeasible QP sit in the second and third chunks, so the first chunk
    skips the relaxed solve that the others run (the batch-level cond is per chunk)."""
    nrec = data["nrec"]
    rec = np.linspace(0, nrec - 1, 18).astype(int)
    idx = np.r_[rec[:10], nrec, rec[10:], nrec + N_INFEAS]       # soft at 10, hard at 19
    qps = _batch(data["qps"], idx)
    ref = jax.tree_util.tree_map(lambda a: a[idx], jax_result)
    r = jax.tree_util.tree_map(np.asarray, jax_qp.solve_batch(qps, chunk=8))
    assert r.x.shape == ref.x.shape == (20, data["qps"]["P"].shape[1])
    assert r.fallback[10] == jax_qp.FALLBACK_RELAXED and r.fallback[19] == jax_qp.FALLBACK_FAILED
    for name, a, b in zip(jax_qp.Result._fields, r, ref):
        if np.issubdtype(a.dtype, np.floating):
            scale = max(1.0, np.nanmax(np.abs(b), initial=0.0))
            np.testing.assert_allclose(a, b, rtol=0, atol=1e-12 * scale, equal_nan=True,
                                       err_msg=name)
        else:
            np.testing.assert_array_equal(a, b, err_msg=name)
    # a chunk at least the batch is the unchunked function itself (no second compile)
    assert jax_qp._resolve_chunk(20, 20) is None and jax_qp._resolve_chunk(8, 20) == 8
    assert chunking.chunk_layout(20, 8) == (3, 7) and chunking.chunk_layout(1024, 64) == (16, 64)
    with pytest.raises(ValueError, match="chunk"):
        jax_qp.solve_batch(qps, chunk=0)


# ---------------------------------------------------------------- float32

@pytest.mark.slow
def test_float32_path(data, piqp_ref):
    """float32 (the accelerator option) at loose tolerances: the reduced Hessian's
    condition number (~1e7) is about 1/eps32, so X is only good to ~1e-2 relative
    (torques to ~1% of their limits); statuses and feasibility hold. Checked on the
    double-support QPs only: on the single-support walking QPs (passive stance ankle,
    one foot's wrench) float32 torques were off by up to 35% of their limits (measured on
    this fixture), so walking rollouts need float64."""
    scen = data["scenario"]
    ds = np.flatnonzero(scen != "walk")
    idx = ds[np.linspace(0, ds.size - 1, 64).astype(int)]
    args = [data["qps"][f][idx] for f in ("P", "q", "G", "h", "A", "b", "lb", "ub")]
    x, status = solve_qp(*args, solver="jax", dtype=jnp.float32, nv=NV, nu=NU)
    np.testing.assert_array_equal(status, SOLVED)
    assert np.isfinite(x).all()
    xs = np.stack([piqp_ref[0][i] for i in idx])
    err = np.abs(x - xs).max(axis=1) / np.abs(xs).max(axis=1)
    assert np.median(err) <= 5e-2 and err.max() <= 0.25
    torque_limit = data["qps"]["ub"][idx][:, NV:NV + NU]
    assert (np.abs(x - xs)[:, NV:NV + NU] / torque_limit).max() <= 5e-2
    for k, i in enumerate(idx):
        eq, ineq, _ = residuals(x[k], _take(data["qps"], i))
        assert eq <= 1e-3 * (1 + np.abs(data["qps"]["b"][i]).max())
        assert ineq <= 1e-3 * (1 + np.abs(data["qps"]["h"][i]).max() + torque_limit[k].max())


# ---------------------------------------------------------------- solve_qp, both solvers

@pytest.mark.slow
def test_solve_qp_single_both_solvers(data, piqp_ref):
    nrec = data["nrec"]
    names = ("P", "q", "G", "h", "A", "b", "lb", "ub")
    i = nrec // 3
    args = [data["qps"][f][i] for f in names]
    x_j, st_j = solve_qp(*args, solver="jax", nv=NV, nu=NU)
    x_p, st_p = solve_qp(*args, solver="piqp", **REF)
    assert st_j == st_p == SolveStatus.SOLVED and isinstance(x_j, np.ndarray)
    assert np.abs(x_j - x_p).max() <= 1e-6 * np.abs(x_p).max()
    soft = data["qps"]["soft"][i]
    for k, expect in ((0, "relaxed"), (N_INFEAS, "failed")):
        args = [data["qps"][f][nrec + k] for f in names]
        for solver in ("jax", "piqp"):
            sizes = {"nv": NV, "nu": NU} if solver == "jax" else {}
            x, st = solve_qp(*args, solver=solver, **sizes)       # plain: no solution
            assert st == SolveStatus.INFEASIBLE and x is None
            x, st = solve_qp(*args, solver=solver, soft=soft, fallback=True, **sizes)
            assert st == SolveStatus.INFEASIBLE
            assert (x is None) == (expect == "failed"), (solver, expect)
    with pytest.raises(ValueError, match="unknown solver"):
        solve_qp(*args, solver="osqp")
    with pytest.raises(ValueError, match="together"):
        solve_qp(data["qps"]["P"][0], data["qps"]["q"][0], G=data["qps"]["G"][0])


@pytest.mark.slow
def test_solve_qp_generic_qps():
    """QPs without the controller's structure go through the generic (null-space) path;
    a batch of them, with and without equalities, an unbounded one and an infeasible one,
    against PIQP."""
    rng = np.random.default_rng(7)
    n, me, mi = 8, 3, 6
    Ps, qs, Gs, hs, As, bs, lbs, ubs = ([] for _ in range(8))
    for k in range(4):
        L = rng.normal(size=(n, n))
        P = L @ L.T + 0.1 * np.eye(n)
        x0 = rng.uniform(-0.5, 0.5, n)
        A = rng.normal(size=(me, n))
        G = rng.normal(size=(mi, n))
        h = G @ x0 + rng.uniform(0, 0.3, mi) * (rng.random(mi) < 0.5)
        q = 3 * rng.normal(size=n)
        if k == 2:                                   # unbounded below: P singular along e0
            P[0, :] = P[:, 0] = 0.0
            q[0], G[:, 0], A[:, 0] = -1.0, 0.0, 0.0
        if k == 3:                                   # infeasible: x_1 >= 2 with ub 1
            G[0] = 0.0
            G[0, 1], h[0] = -1.0, -2.0
        Ps.append(P), qs.append(q), Gs.append(G), hs.append(h), As.append(A)
        bs.append(A @ x0), lbs.append(np.full(n, -1.0)), ubs.append(np.full(n, 1.0))
        if k == 2:
            lbs[-1][0], ubs[-1][0] = -np.inf, np.inf
    args = [np.stack(v) for v in (Ps, qs, Gs, hs, As, bs, lbs, ubs)]
    x_j, st_j = solve_qp(*args, solver="jax")
    x_p, st_p = solve_qp(*args, solver="piqp", **REF)
    np.testing.assert_array_equal(st_j, st_p)
    np.testing.assert_array_equal(st_j, [SOLVED, SOLVED, INFEASIBLE, INFEASIBLE])
    np.testing.assert_allclose(x_j[:2], x_p[:2], atol=1e-7)
    assert np.isnan(x_j[2:]).all()
    # no equalities: bounds stay bounds
    x1, s1 = solve_qp(Ps[0], qs[0], Gs[0], hs[0], lb=lbs[0], ub=ubs[0], solver="jax")
    x2, s2 = solve_qp(Ps[0], qs[0], Gs[0], hs[0], lb=lbs[0], ub=ubs[0], solver="piqp", **REF)
    assert s1 == s2 == SolveStatus.SOLVED and np.abs(x1 - x2).max() <= 1e-7


@pytest.mark.slow
def test_iteration_limit_status(data):
    """Too few iterations: MAX_ITER for the QP as posed and for its relaxation, and the
    step is reported failed (x all NaN), never a half-converged x."""
    st = jax_qp.Settings(max_iter=2, polish=False)
    qps = _batch(data["qps"], slice(0, 2))
    r = jax.tree_util.tree_map(np.asarray, jax_qp.solve_batch(qps, settings=st))
    np.testing.assert_array_equal(r.status, MAX_ITER)
    np.testing.assert_array_equal(r.relaxed_status, MAX_ITER)
    np.testing.assert_array_equal(r.fallback, jax_qp.FALLBACK_FAILED)
    assert np.isnan(r.x).all()


# ---------------------------------------------------------------- one seam, one answer

def test_both_solvers_give_one_result_type(data, jax_result):
    """The seam: both solvers take the QP alone (block sizes from it) and return the same
    ``SolveResult``; on recorded QPs and on a soft- and a hard-infeasible one they agree
    on status and fallback, and on x within the tolerance of the tests above (1e-6
    relative to max |x|, PIQP at TIGHT; x all NaN where both fail)."""
    nrec = data["nrec"]
    idx = np.r_[np.linspace(0, nrec - 1, 5).astype(int), nrec, nrec + N_INFEAS]
    tight, ref = PiqpSolver(update=False, **TIGHT_NO_GAP), PiqpSolver(update=False, **REF)
    for j in idx:
        qp = _take(data["qps"], j)
        res_p = (tight if j < nrec else ref).solve(qp)
        res_j = jax.tree_util.tree_map(lambda a: a[j], jax_result)
        assert type(res_p) is SolveResult and type(jax_result) is SolveResult
        assert res_p._fields == jax_qp.Result._fields
        assert int(res_p.status) == int(res_j.status), j
        assert int(res_p.fallback) == int(res_j.fallback), j
        if res_p.fallback == jax_qp.FALLBACK_FAILED:
            assert np.isnan(res_p.x).all() and np.isnan(res_j.x).all()
        else:
            scale = max(1.0, np.abs(res_p.x).max())
            assert np.abs(res_j.x - res_p.x).max() <= 1e-6 * scale, j
            assert res_p.eq_residual <= 1e-8 and res_j.eq_residual <= 1e-8


def test_solvers_refuse_a_qp_without_block_sizes(data):
    """The controller's path takes nv, nu from the QP: a QP without them is refused with
    a message (solve_generic solves it), never solved at some default size."""
    plain = QP(*(np.asarray(data["qps"][f][0]) for f in FIELDS))
    assert not plain.has_blocks and not reduce.has_controller_structure(plain)
    with pytest.raises(ValueError, match="block sizes"):
        jax_qp.solve(plain)
    with pytest.raises(ValueError, match="block sizes"):
        reduce.eliminate_equalities_np(plain)
    sized = _take(data["qps"], 0)
    assert reduce.has_controller_structure(sized) and reduce.p_block_diagonal(sized)
    qdd, u, lam = sized.split(np.arange(sized.n))
    assert (qdd.size, u.size, lam.size) == (NV, NU, sized.n - NV - NU)
