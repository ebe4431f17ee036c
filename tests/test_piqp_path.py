"""PIQP deployment path and the soft-row relaxation (fast: a few seconds).

Only PIQP is installed as a qpsolvers backend, so optimality is certified independently of
the solver: from PIQP's x we identify the active set, solve the equality-constrained KKT
system of that active set with numpy, and require that its solution equals x, is feasible,
and has non-negative inequality multipliers (that point is then the unique optimum of the
strictly convex QP). Stationarity is also checked at x itself with least-squares
multipliers.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from safewbc_jax.solvers.problem import QP
from safewbc_jax.solvers.piqp_path import PiqpSolver, residuals, solve_qp_piqp
from safewbc_jax.solvers.result import (FALLBACK_FAILED, FALLBACK_NONE, FALLBACK_RELAXED,
                                        NOT_ATTEMPTED, SolveResult)
from safewbc_jax.solvers.relax import (relax_soft_rows, relax_soft_rows_np, split_slack,
                                       strip_slack)
from safewbc_jax.solvers.status import SolveStatus

N, ME, MI = 78, 58, 40        # X = [q_ddot (36), u (20), lambda (22)]
U = slice(36, 56)             # torque block: the bounded variables
N_SOFT = 16                   # last rows: ZMP + barrier (soft); first rows: friction (hard)
FIELDS = ("P", "q", "A", "b", "G", "h", "lb", "ub", "soft")


def random_qp(rng, n=N, me=ME, mi=MI, n_soft=N_SOFT, return_x0=False):
    """Strictly convex, feasible by construction around a random x0 (numpy arrays)."""
    L = rng.normal(size=(n, n)) / np.sqrt(n)
    P = L @ L.T + 1e-2 * np.eye(n)
    q = 3.0 * rng.normal(size=n)
    x0 = rng.normal(size=n)
    A = rng.normal(size=(me, n))
    b = A @ x0
    G = rng.normal(size=(mi, n))
    gap = np.abs(rng.normal(size=mi)) * (rng.random(mi) < 0.6)   # many rows tight at x0
    h = G @ x0 + gap
    lb = np.full(n, -np.inf)
    ub = np.full(n, np.inf)
    nu = U.stop - U.start
    lb[U] = x0[U] - rng.uniform(0.05, 1.0, nu)
    ub[U] = x0[U] + rng.uniform(0.05, 1.0, nu)
    soft = np.zeros(mi)
    soft[mi - n_soft:] = 1.0
    qp = QP(P=P, q=q, A=A, b=b, G=G, h=h, lb=lb, ub=ub, soft=soft)
    return (qp, x0) if return_x0 else qp


def perturbed(qp: QP, x0: np.ndarray, rng, eps: float) -> QP:
    """A nearby QP (the next control step), still feasible at x0."""
    n = qp.P.shape[0]
    E = eps * rng.normal(size=(n, n))
    A = qp.A + eps * rng.normal(size=qp.A.shape)
    G = qp.G + eps * rng.normal(size=qp.G.shape)
    gap = np.maximum(qp.h - qp.G @ x0, 0.0)
    return QP(P=qp.P + E @ E.T, q=qp.q + eps * rng.normal(size=n), A=A, b=A @ x0, G=G,
              h=G @ x0 + gap, lb=qp.lb, ub=qp.ub, soft=qp.soft)


def to_jax(qp: QP) -> QP:
    return QP(*(jnp.asarray(getattr(qp, f)) for f in FIELDS))


def kkt_certificate(qp: QP, x: np.ndarray, act_tol: float = 1e-6) -> dict:
    """Optimality of x from the active set, with numpy only."""
    P, q, A, b, G, h, lb, ub = (qp.P, qp.q, qp.A, qp.b, qp.G, qp.h, qp.lb, qp.ub)
    n, me = P.shape[0], A.shape[0]
    act_g = G @ x - h > -act_tol * (1 + np.abs(h))
    act_ub = np.isfinite(ub) & (x - ub > -act_tol * (1 + np.abs(np.where(np.isfinite(ub), ub, 0))))
    act_lb = np.isfinite(lb) & (lb - x > -act_tol * (1 + np.abs(np.where(np.isfinite(lb), lb, 0))))
    eye = np.eye(n)
    C = np.vstack([A, G[act_g], eye[act_ub], -eye[act_lb]])
    d = np.concatenate([b, h[act_g], ub[act_ub], -lb[act_lb]])
    k = C.shape[0]
    assert np.linalg.matrix_rank(C) == k, "degenerate active set (LICQ fails)"
    K = np.block([[P, C.T], [C, np.zeros((k, k))]])
    sol = np.linalg.solve(K, np.concatenate([-q, d]))
    x_kkt, mu = sol[:n], sol[n:]
    grad = P @ x + q
    mu_ls = np.linalg.lstsq(C.T, -grad, rcond=None)[0]
    x_kkt_qp = QP(P=P, q=q, A=A, b=b, G=G, h=h, lb=lb, ub=ub, soft=qp.soft)
    eq_kkt, ineq_kkt, _ = residuals(x_kkt, x_kkt_qp)
    return {
        "n_active": k - me,
        "x_err": float(np.max(np.abs(x_kkt - x))),
        "min_ineq_mult": float(np.min(mu[me:], initial=np.inf)),
        "kkt_point_eq": eq_kkt,
        "kkt_point_ineq": ineq_kkt,
        "stationarity": float(np.max(np.abs(grad + C.T @ mu_ls))),
        "scale": 1.0 + float(np.max(np.abs(q))) + float(np.max(np.abs(mu))),
    }


# ---------------------------------------------------------------- optimality, both paths

# PIQP's defaults (eps_abs 1e-8, eps_rel 1e-9) stop with complementarity ~1e-8 left on
# nearly-active rows, which leaves x up to ~1e-6 (1e-5 on long drifting streams) from the
# exact optimum of these QPs. Two or three more iterations with these settings bring it to
# ~1e-11: the optimality certificate and the path comparison use them.
TIGHT = {"eps_abs": 1e-12, "eps_rel": 1e-14,
         "eps_duality_gap_abs": 1e-12, "eps_duality_gap_rel": 1e-14}


@pytest.mark.parametrize("seed", range(6))
def test_random_qp_kkt(seed):
    qp = random_qp(np.random.default_rng(seed))
    x_ref, status = solve_qp_piqp(qp, **TIGHT)
    assert status == SolveStatus.SOLVED and x_ref is not None
    solver = PiqpSolver(**TIGHT)
    r = solver.solve(qp)
    x = r.x
    assert isinstance(r, SolveResult)
    assert r.status == SolveStatus.SOLVED and r.fallback == FALLBACK_NONE
    assert r.relaxed_status == NOT_ATTEMPTED and not r.polished and r.polish_iterations == 0
    assert r.max_slack == 0.0 and r.iterations > 0 and solver.last_solve_time_us > 0
    assert r.eq_residual <= 1e-8 and r.ineq_violation <= 1e-8
    for xx in (x_ref, x):
        eq, ineq, hard = residuals(xx, qp)
        assert eq <= 1e-8 and ineq <= 1e-8 and hard <= ineq
        c = kkt_certificate(qp, xx)
        assert c["n_active"] > 0                         # the test exercises constraints
        assert c["x_err"] <= 1e-8                        # x is the exact KKT point
        assert c["min_ineq_mult"] >= -1e-8 * c["scale"]  # dual feasibility
        assert c["kkt_point_eq"] <= 1e-9 and c["kkt_point_ineq"] <= 1e-8
        assert c["stationarity"] <= 1e-8 * c["scale"]

    # default settings (the real-time ones): feasible to 1e-8, optimal to ~1e-6
    r = PiqpSolver().solve(qp)
    x_def = r.x
    assert r.eq_residual <= 1e-8 and r.ineq_violation <= 1e-8
    assert np.max(np.abs(x_def - x)) <= 1e-5


def test_dense_paths_match_qpsolvers():
    """The DenseSolver kept across a stream of slowly varying QPs gives the qpsolvers
    answer at every step: bit for bit with a setup per call; to 1e-7 through ``update``,
    whose preconditioning differs from a fresh setup's (so the comparison is made at
    tight tolerances, where both are ~1e-11 from the exact optimum)."""
    rng = np.random.default_rng(10)
    qp, x0 = random_qp(rng, return_x0=True)
    resetup = PiqpSolver("dense", update=False)
    upd = PiqpSolver("dense", **TIGHT)
    upd_pre = PiqpSolver("dense", preconditioner_reuse_on_update=True, **TIGHT)
    via_qpsolvers = PiqpSolver("qpsolvers", **TIGHT)
    for _ in range(8):
        x_ref, status = solve_qp_piqp(qp)
        assert status == SolveStatus.SOLVED
        r = resetup.solve(qp)
        x = r.x
        assert r.fallback == FALLBACK_NONE
        assert np.max(np.abs(x - x_ref)) <= 1e-12

        x_tight, status = solve_qp_piqp(qp, **TIGHT)
        x_cls = via_qpsolvers.solve(qp).x
        np.testing.assert_array_equal(x_cls, x_tight)
        for solver in (upd, upd_pre):
            r = solver.solve(qp)
            assert r.fallback == FALLBACK_NONE
            x = r.x
            assert np.max(np.abs(x - x_tight)) <= 1e-7
        qp = perturbed(qp, x0, rng, 1e-3)


def test_jax_array_input():
    qp = random_qp(np.random.default_rng(3))
    x_np = PiqpSolver().solve(qp).x
    r = PiqpSolver().solve(to_jax(qp))
    x_j = r.x
    assert r.fallback == FALLBACK_NONE
    assert isinstance(x_j, np.ndarray) and x_j.dtype == np.float64
    np.testing.assert_allclose(x_j, x_np, atol=1e-12)
    x_1, st = solve_qp_piqp(to_jax(qp))
    assert st == SolveStatus.SOLVED
    np.testing.assert_allclose(x_1, x_np, atol=1e-7)


# ---------------------------------------------------------------- fallback policy

def _soft_conflict(qp: QP, row: int, j: int, amount: float = 0.5) -> QP:
    """Row ``row`` demands x_j >= ub_j + amount, contradicting the bound."""
    G, h = qp.G.copy(), qp.h.copy()
    G[row] = 0.0
    G[row, j] = -1.0
    h[row] = -(qp.ub[j] + amount)
    return QP(P=qp.P, q=qp.q, A=qp.A, b=qp.b, G=G, h=h, lb=qp.lb, ub=qp.ub, soft=qp.soft)


@pytest.mark.parametrize("backend", ["dense", "qpsolvers"])
def test_soft_conflict_relaxed(backend):
    qp = _soft_conflict(random_qp(np.random.default_rng(20)), row=MI - 1, j=40, amount=0.5)
    assert qp.soft[MI - 1] == 1.0
    solver = PiqpSolver(backend)
    for _ in range(2):                                   # second call: update path
        r = solver.solve(qp)
        x = r.x
        assert r.status != SolveStatus.SOLVED     # INFEASIBLE with PIQP 0.7
        assert r.fallback == FALLBACK_RELAXED
        assert r.relaxed_status == SolveStatus.SOLVED
        assert np.all(np.isfinite(x)) and x.shape == (N,)
        eq, ineq, hard = residuals(x, qp)
        assert eq <= 1e-8 and hard <= 1e-8               # equalities, hard rows, bounds hold
        assert r.hard_violation <= 1e-8 and r.eq_residual <= 1e-8
        # the bound wins, the soft row gives exactly the contradiction (0.5) or more
        assert r.max_slack == pytest.approx(r.ineq_violation, abs=1e-8)
        assert r.max_slack >= 0.5 - 1e-8
        assert r.iterations > 0


@pytest.mark.parametrize("backend", ["dense", "qpsolvers"])
def test_hard_conflict_failed(backend):
    qp = _soft_conflict(random_qp(np.random.default_rng(21)), row=0, j=40)
    assert qp.soft[0] == 0.0
    r = PiqpSolver(backend).solve(qp)
    assert np.isnan(r.x).all()                           # never a usable-looking number
    assert r.fallback == FALLBACK_FAILED
    assert r.status != SolveStatus.SOLVED and r.relaxed_status != SolveStatus.SOLVED
    assert r.relaxed_status != NOT_ATTEMPTED
    assert np.isnan(r.max_slack) and np.isnan(r.eq_residual)
    x1, st = solve_qp_piqp(qp)
    assert x1 is None and st != SolveStatus.SOLVED


def test_nonfinite_data_fails_cleanly():
    qp = random_qp(np.random.default_rng(22))
    q = qp.q.copy()
    q[3] = np.nan
    bad = QP(P=qp.P, q=q, A=qp.A, b=qp.b, G=qp.G, h=qp.h, lb=qp.lb, ub=qp.ub, soft=qp.soft)
    solver = PiqpSolver(max_iter=50)
    r = solver.solve(bad)
    assert np.isnan(r.x).all() and r.fallback == FALLBACK_FAILED
    # the solver recovers on the next good QP
    r = solver.solve(qp)
    assert r.fallback == FALLBACK_NONE and np.all(np.isfinite(r.x))


def test_max_iter_status():
    qp = random_qp(np.random.default_rng(23))
    r = PiqpSolver(max_iter=2).solve(qp)
    assert r.status == SolveStatus.MAX_ITER
    assert r.relaxed_status == SolveStatus.MAX_ITER
    assert np.isnan(r.x).all() and r.fallback == FALLBACK_FAILED


# ---------------------------------------------------------------- relax_soft_rows

def test_relax_structure_and_numpy_twin():
    qp = random_qp(np.random.default_rng(30))
    r = relax_soft_rows(to_jax(qp), rho=1e6, rho_lin=2.0)
    assert r.P.shape == (N + MI, N + MI) and r.G.shape == (MI, N + MI)
    assert r.A.shape == (ME, N + MI) and r.lb.shape == (N + MI,)
    soft = qp.soft > 0
    np.testing.assert_array_equal(np.asarray(r.lb[N:]), 0.0)
    np.testing.assert_array_equal(np.asarray(r.ub[N:])[~soft], 0.0)       # pinned
    assert np.all(np.isposinf(np.asarray(r.ub[N:])[soft]))
    np.testing.assert_array_equal(np.asarray(r.q[N:]), np.where(soft, 2.0, 0.0))
    np.testing.assert_array_equal(np.asarray(r.G[:, N:]), -np.eye(MI))
    np.testing.assert_array_equal(np.asarray(r.P[N:, N:]), 1e6 * np.eye(MI))
    np.testing.assert_array_equal(np.asarray(r.soft), 0.0)
    r_np = relax_soft_rows_np(qp, rho=1e6, rho_lin=2.0)
    for f in FIELDS:
        np.testing.assert_array_equal(np.asarray(getattr(r, f)), getattr(r_np, f))


def test_relaxed_always_feasible_wrt_soft_rows():
    """A soft-row conflict: the relaxed QP (built in JAX) is solvable, its hard slacks are
    zero, and x satisfies every hard row."""
    qp = _soft_conflict(random_qp(np.random.default_rng(31)), row=MI - 2, j=45, amount=2.0)
    assert solve_qp_piqp(qp)[1] != SolveStatus.SOLVED
    z, st = solve_qp_piqp(relax_soft_rows(to_jax(qp)))
    assert st == SolveStatus.SOLVED
    x, s = split_slack(z, qp)
    np.testing.assert_array_equal(strip_slack(z, qp), x)
    assert np.max(np.abs(s[qp.soft == 0])) <= 1e-12
    assert np.min(s) >= -1e-9 and np.max(s) >= 2.0 - 1e-8
    eq, _, hard = residuals(x, qp)
    assert eq <= 1e-8 and hard <= 1e-8


def test_relaxed_exact_with_linear_penalty():
    """With rho_lin above the soft-row multipliers the relaxation of a feasible QP returns
    the original optimum (exact penalty); the pure quadratic penalty does not quite."""
    qp = random_qp(np.random.default_rng(32))
    x_star, _ = solve_qp_piqp(qp)
    z, st = solve_qp_piqp(relax_soft_rows_np(qp, rho=1e3, rho_lin=1e4))
    assert st == SolveStatus.SOLVED
    assert np.max(np.abs(strip_slack(z, qp) - x_star)) <= 1e-6
    z0, _ = solve_qp_piqp(relax_soft_rows_np(qp, rho=1e3, rho_lin=0.0))
    _, s0 = split_slack(z0, qp)
    assert np.max(s0) > 1e-6                     # quadratic penalty: active soft rows give


def test_relax_jit_and_vmap():
    rng = np.random.default_rng(33)
    qps = [random_qp(rng, n_soft=k) for k in (0, 7, 16, MI)]   # different soft masks
    single = [relax_soft_rows(to_jax(qp), 1e5, 3.0) for qp in qps]

    jitted = jax.jit(relax_soft_rows)
    for qp, ref in zip(qps, single):
        out = jitted(to_jax(qp), 1e5, 3.0)
        for f in FIELDS:
            np.testing.assert_array_equal(np.asarray(getattr(out, f)), np.asarray(getattr(ref, f)))

    batch = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *[to_jax(qp) for qp in qps])
    rhos = jnp.array([1e5, 1e5, 1e5, 1e5])
    out = jax.jit(jax.vmap(relax_soft_rows, in_axes=(0, 0, None)))(batch, rhos, 3.0)
    assert out.P.shape == (len(qps), N + MI, N + MI)
    for i, ref in enumerate(single):
        for f in FIELDS:
            np.testing.assert_array_equal(np.asarray(getattr(out, f)[i]),
                                          np.asarray(getattr(ref, f)))

    z = jnp.arange(len(qps) * (N + MI), dtype=jnp.float64).reshape(len(qps), N + MI)
    xs = jax.vmap(strip_slack)(z, batch)
    assert xs.shape == (len(qps), N)
    np.testing.assert_array_equal(np.asarray(xs), np.asarray(z[:, :N]))
    x_b, s_b = split_slack(z, batch)                  # leading batch dims, no vmap
    assert x_b.shape == (len(qps), N) and s_b.shape == (len(qps), MI)


# ---------------------------------------------------------------- precomputed checks

def test_precomputed_checks_match_the_policy():
    """``policy.checks`` (computed once per QP, by the deployment's jitted step) and
    ``residuals_checked`` give the residuals and the acceptance of ``policy.residuals``
    and ``policy.scales``: at feasible, infeasible and non-finite x, with infinite and
    absent (>= BIG) bounds, soft rows and a switched-off row, with and without equality
    rows (the reduced QP has none). Residuals agree to 1e-12 relative (one
    matrix-vector product ordered differently); the decisions exactly."""
    from safewbc_jax.solvers import policy
    from safewbc_jax.solvers.status import NUMERICAL, SOLVED

    rng = np.random.default_rng(7)
    for k in range(12):
        qp, x0 = random_qp(rng, return_x0=True)
        if k % 2:   # the reduced QP's form: no equality rows
            qp = dataclasses.replace(qp, A=np.zeros((0, N)), b=np.zeros(0))
        lb, ub, h, G = qp.lb.copy(), qp.ub.copy(), qp.h.copy(), qp.G.copy()
        lb[0], ub[1] = -2e20, 3e20          # "absent" bounds (>= BIG in size)
        G[3], h[3] = 0.0, 1e9               # a barrier row switched off
        qp = dataclasses.replace(qp, lb=lb, ub=ub, G=G, h=h)
        ch = policy.checks(qp, np)
        ch_j = policy.checks(to_jax(qp), jnp)
        for a, b in zip(ch, ch_j):
            np.testing.assert_array_equal(np.asarray(b), a)
        xs = [x0, x0 + 1e-3 * rng.normal(size=N), x0 + rng.normal(size=N)]
        bad = [x0.copy() for _ in range(3)]
        bad[0][5], bad[1][40], bad[2][70] = np.nan, np.inf, -np.inf
        for x in xs + bad:
            ref = policy.residuals(x, qp, np)[:3]
            got = policy.residuals_checked(x, qp, ch)
            for r, g in zip(ref, got):
                if np.isfinite(r):
                    assert abs(g - r) <= 1e-12 * (1.0 + abs(r)), (k, ref, got)
            for tol in (1e-6, 1e-1):
                s_ref, _ = policy.accept(x, qp, SOLVED, tol, np)
                s_got, _ = policy.accept(x, qp, SOLVED, tol, np, checks=ch)
                assert s_ref == s_got, (k, tol, ref, got)
        assert policy.accept(bad[0], qp, SOLVED, 1e9, np, checks=ch)[0] == NUMERICAL


def test_solve_with_checks_is_the_same_solve():
    """``PiqpSolver.solve(qp, checks=policy.checks(qp))`` gives the SolveResult of
    ``solve(qp)``, on solvable QPs and on a hard conflict (FAILED on both)."""
    from safewbc_jax.solvers import policy

    rng = np.random.default_rng(3)
    qps = [random_qp(rng) for _ in range(3)]
    conflict = dataclasses.replace(qps[0], G=np.vstack([qps[0].G, -qps[0].G[:1]]),
                               h=np.concatenate([qps[0].h, -qps[0].h[:1] - 1.0]),
                               soft=np.concatenate([np.zeros(MI), [0.0]]))
    for qp in qps + [conflict]:
        a = PiqpSolver(update=False).solve(qp)
        b = PiqpSolver(update=False).solve(qp, checks=policy.checks(qp, np))
        assert a.status == b.status and a.fallback == b.fallback
        np.testing.assert_array_equal(a.x, b.x)
        for f in ("eq_residual", "ineq_violation", "hard_violation"):
            ra, rb = getattr(a, f), getattr(b, f)
            assert (np.isnan(ra) and np.isnan(rb)) or abs(ra - rb) <= 1e-12 * (1 + abs(ra)), f
