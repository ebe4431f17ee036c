"""``solvers.solve_qp`` with every subset of the optional parts that qpsolvers accepts
(G/h, A/b, lb, ub: any of them None), for one QP and for a batch, with solver="jax" and
solver="piqp", fallback False and True, structure "auto" and "generic"; and the
"controller" structure on a small QP that has it (refused with a message on one that
does not).

References, independent of both solvers. Each feasible QP is built from its optimum
(``_constructed``): pick x*, P > 0, which constraints are active and their multipliers
(> 0: strict complementarity, so x* is the unique optimum and well separated from the
other active sets), the slack of the others, and set q from the KKT stationarity
condition P x* + q + G'z + A'y + z_u - z_l = 0. Unconstrained and equality-only QPs are
also checked against a plain numpy solve of their KKT system (x = -P^-1 q;
[P A'; A 0] [x; y] = [-q; b]). QPs with a singular P but a finite minimum (not unique)
are checked on their optimal value, from the pseudo-inverse of the (reduced) Hessian.

Tolerances. ``ATOL_JAX`` 1e-8: the JAX solver ends with an exact KKT solve of the
active set (its polish; ~1e-13 on these well-conditioned QPs, cond(P) < 1e3), and without
the polish its interior point stops at 1e-10 (scaled): 1e-8 leaves margin for the
conditioning and still fails for any wrong active set (those move x by ~0.1 here, the
slacks and multipliers being >= 0.2). ``ATOL_PIQP`` 1e-6: PIQP at its default settings
stops at residuals eps_abs 1e-8 / eps_rel 1e-9, which leaves x within cond(P) * 1e-8
~ 1e-6 of the optimum (the solvers' tolerance order, as in test_jax_qp.py's 1e-6).
Measured on this file's QPs: JAX <= 1.2e-15, PIQP <= 1.3e-8 (x); optimal values of the
singular QPs within 2e-16 (JAX) and 1.1e-9 (PIQP) relative, checked at 1e-7.

Decisions tested here (documented in solvers/__init__.py):
  * lb_j > ub_j for some j (an empty box): status INFEASIBLE and no x, with either
    solver and either fallback (the fallback relaxes soft rows of G, never bounds); in a
    batch only that QP. PIQP itself reports it primal infeasible; the JAX solver's
    infeasibility certificate is over the rows of G and would not see it, so solve_qp
    decides it from the data for both.
  * unbounded below (P singular on the feasible directions, q not orthogonal to them):
    INFEASIBLE (dual infeasible), no x, both solvers.
  * A with more rows than variables: solver="jax" raises ValueError naming A (the
    null-space method needs full row rank; PIQP solves a consistent one).
  * a shape mismatch: ValueError naming the argument.

Cost: the JAX solver compiles once per distinct shape (~8-12 s each on this 2-core
CPU), so the QPs are grouped: n = 5 everywhere, G of 3 rows and A of 2 whenever present,
every batch of 4; an absent part is filled with the same shapes whichever of lb/ub are
None, so the 16 subsets cost 4 compiles for one QP and 4 for a batch; the square
equalities and the controller structure one each. No float32 case here (one more
compile): test_jax_qp.py::test_float32_path runs the float32 solver on the controller
QPs; on the row-less QPs of this file float32 was measured within 3e-8 of x*.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import scipy.linalg as sl

from safewbc_jax.solvers import INFEASIBLE, SOLVED, SolveStatus, jax_qp, solve_qp

N, MI, ME, NB = 5, 3, 2, 4
ATOL_JAX = 1e-8
ATOL_PIQP = 1e-6
CLASSES = list(itertools.product((False, True), repeat=2))       # (inequalities, equalities)
# the fast tier keeps the class with both (G+A+) for one QP; the other classes compile
# again (slow tier), and so do the batched solves (test_jax_qp.py solves the recorded QPs
# batched in the fast tier)
CLASS_PARAMS = [pytest.param(c, marks=() if all(c) else pytest.mark.slow) for c in CLASSES]
BOUNDS = list(itertools.product((False, True), repeat=2))        # (lb given, ub given)


@pytest.fixture(scope="module", autouse=True)
def one_blas_thread():
    """As in test_jax_qp.py: OpenBLAS worker threads compete with XLA's on a small CPU."""
    with jax_qp.blas_threads(1):
        yield


def _spd(rng, n):
    L = rng.normal(size=(n, n))
    return L @ L.T + np.eye(n)


def _constructed(seed, ineq, eq, lower, upper, fixed=False):
    """A QP with the given parts (absent ones None) and its known unique optimum x*.

    Active at x*: row 0 of G, both equalities, lb_0, ub_1 (and lb_2 = ub_2 with
    ``fixed``); inactive rows and bounds have slack 0.2..1; lb_3 = -inf and ub_4 = +inf
    (given arrays with infinite entries). Returns (kwargs for solve_qp, x*)."""
    rng = np.random.default_rng(seed)
    n = N
    P = _spd(rng, n)
    x = rng.uniform(-0.5, 0.5, n)
    grad = P @ x                        # P x* + q + G'z + A'y + z_u - z_l = 0
    kw = {"P": P}
    if ineq:
        G = rng.normal(size=(MI, n))
        z = np.zeros(MI)
        z[0] = rng.uniform(0.5, 1.5)
        slack = np.r_[0.0, rng.uniform(0.2, 1.0, MI - 1)]
        kw.update(G=G, h=G @ x + slack)
        grad = grad + G.T @ z
    if eq:
        A = rng.normal(size=(ME, n))
        y = rng.normal(size=ME)
        kw.update(A=A, b=A @ x)
        grad = grad + A.T @ y
    if lower:
        lb = x - rng.uniform(0.2, 1.0, n)
        lb[0], lb[3] = x[0], -np.inf
        grad = grad - np.eye(n)[0] * rng.uniform(0.5, 1.5)          # z_l,0 > 0
        kw["lb"] = lb
    if upper:
        ub = x + rng.uniform(0.2, 1.0, n)
        ub[1], ub[4] = x[1], np.inf
        grad = grad + np.eye(n)[1] * rng.uniform(0.5, 1.5)          # z_u,1 > 0
        kw["ub"] = ub
    if fixed:
        assert lower and upper
        kw["lb"][2] = kw["ub"][2] = x[2]
        grad = grad + np.eye(n)[2] * rng.normal()                   # z_u - z_l: any sign
    kw["q"] = -grad
    return kw, x


def _crossed(seed, ineq, eq):
    """A feasible-looking QP whose box is empty (lb_2 > ub_2)."""
    kw, _ = _constructed(seed, ineq, eq, True, True)
    kw["lb"][2] = kw["ub"][2] + 0.1
    return kw


def _singular(seed, eq, bounded):
    """P singular on the feasible set (no inequalities, no bounds): unbounded below, or
    (``bounded``) with a finite minimum that is not unique. (kwargs, optimal value)."""
    rng = np.random.default_rng(seed)
    n = N
    if eq:
        A = rng.normal(size=(ME, n))
        b = rng.normal(size=ME)
        Z = sl.null_space(A)                                  # (n, n - ME)
        P = A.T @ A + 2.0 * np.outer(Z[:, 0], Z[:, 0])        # Z'PZ = diag(2, 0, 0)
        xp = np.linalg.lstsq(A, b, rcond=None)[0]
        if bounded:     # q such that Z'(P xp + q) lies in range(Z'PZ)
            q = A.T @ rng.normal(size=ME) + Z[:, 0] * rng.normal() - P @ xp
        else:
            q = rng.normal(size=n)
        Pz, qz = Z.T @ P @ Z, Z.T @ (P @ xp + q)
        xs = xp + Z @ (-np.linalg.pinv(Pz) @ qz)
        kw = {"P": P, "q": q, "A": A, "b": b}
    else:
        V = np.linalg.qr(rng.normal(size=(n, n)))[0]
        P = V[:, :3] @ np.diag(rng.uniform(1, 3, 3)) @ V[:, :3].T  # rank 3
        q = P @ rng.normal(size=n) if bounded else rng.normal(size=n)
        xs = -np.linalg.pinv(P) @ q
        kw = {"P": P, "q": q}
    return kw, 0.5 * xs @ P @ xs + kw["q"] @ xs


def _objective(P, q, x):
    return 0.5 * x @ P @ x + q @ x


def _drop(kw, ineq, eq, lower, upper):
    """kwargs with the parts not in the combination removed (None)."""
    keep = {"P", "q"} | ({"G", "h"} if ineq else set()) | ({"A", "b"} if eq else set())
    keep |= ({"lb"} if lower else set()) | ({"ub"} if upper else set())
    return {k: v for k, v in kw.items() if k in keep}


def _label(cls):
    return f"G{'+' if cls[0] else '-'}A{'+' if cls[1] else '-'}"


def _check_reference(kw, x_star):
    """The construction agrees with a plain KKT solve where one exists (no inequalities
    and no bounds)."""
    P, q = kw["P"], kw["q"]
    if "G" in kw or "lb" in kw or "ub" in kw:
        return
    if "A" in kw:
        A, b = kw["A"], kw["b"]
        K = np.block([[P, A.T], [A, np.zeros((ME, ME))]])
        x_kkt = np.linalg.solve(K, np.r_[-q, b])[:N]
    else:
        x_kkt = np.linalg.solve(P, -q)
    np.testing.assert_allclose(x_kkt, x_star, atol=1e-12)


def _solvers():
    """(solver, keyword arguments) of every solve_qp variant for a generic QP."""
    for fallback in (False, True):
        for structure in ("auto", "generic"):
            yield "jax", {"fallback": fallback, "structure": structure}
        yield "piqp", {"fallback": fallback}


# ---------------------------------------------------------------- one QP, 16 subsets

@pytest.mark.parametrize("cls", CLASS_PARAMS, ids=_label)
def test_single_qp_every_subset(cls):
    ineq, eq = cls
    for k, (lower, upper) in enumerate(BOUNDS):
        kw, x_star = _constructed(10 * k + 2 * ineq + eq, ineq, eq, lower, upper)
        _check_reference(kw, x_star)
        for solver, opts in _solvers():
            x, st = solve_qp(**kw, solver=solver, **opts)
            assert st == SolveStatus.SOLVED and isinstance(st, SolveStatus), \
                (cls, lower, upper, solver, opts, st)
            assert isinstance(x, np.ndarray) and x.dtype == np.float64 and x.shape == (N,)
            atol = ATOL_JAX if solver == "jax" else ATOL_PIQP
            np.testing.assert_allclose(x, x_star, atol=atol, rtol=0,
                                       err_msg=f"{cls} lb={lower} ub={upper} {solver} {opts}")
    # the QPs with no solution, same shapes (no new compile)
    kw = _drop(_crossed(99, ineq, eq), ineq, eq, True, True)
    for solver, opts in _solvers():
        x, st = solve_qp(**kw, solver=solver, **opts)
        assert x is None and st == SolveStatus.INFEASIBLE, (cls, solver, opts, st)
    if not ineq:
        kw, _ = _singular(98, eq, bounded=False)
        for solver, opts in _solvers():
            x, st = solve_qp(**kw, solver=solver, **opts)
            assert x is None and st == SolveStatus.INFEASIBLE, (cls, "unbounded", solver, opts, st)


# ---------------------------------------------------------------- batches of 4, 16 subsets

def _batch_members(ineq, eq, lower, upper):
    """NB QPs of one combination: constructed ones (x* known) and, where the combination
    allows, the special cases. Each entry (kwargs, kind, reference)."""
    out = []
    for i in range(NB):
        kw, xs = _constructed(1000 + 37 * i + 4 * lower + 2 * upper + ineq, ineq, eq,
                              lower, upper)
        out.append((kw, "x", xs))
    if not ineq and not lower and not upper:
        kw, value = _singular(200 + eq, eq, bounded=True)
        out[2] = (kw, "value", value)
        out[3] = (_singular(300 + eq, eq, bounded=False)[0], "infeasible", None)
    if lower and upper:
        out[2] = (_crossed(400 + 2 * ineq + eq, ineq, eq), "infeasible", None)
        if not ineq and not eq:
            kw, xs = _constructed(500, False, False, True, True, fixed=True)
            out[3] = (kw, "x", xs)
    return out


def _stack(members, ineq, eq, lower, upper):
    kws = [_drop(kw, ineq, eq, lower, upper) for kw, _, _ in members]
    return {k: np.stack([kw[k] for kw in kws]) for k in kws[0]}


@pytest.mark.slow
@pytest.mark.parametrize("cls", CLASSES, ids=_label)
def test_batch_every_subset(cls):
    ineq, eq = cls
    for lower, upper in BOUNDS:
        members = _batch_members(ineq, eq, lower, upper)
        args = _stack(members, ineq, eq, lower, upper)
        for solver, opts in _solvers():
            x, st = solve_qp(**args, solver=solver, **opts)
            where = f"{cls} lb={lower} ub={upper} {solver} {opts}"
            assert x.shape == (NB, N) and st.shape == (NB,) and st.dtype == np.int32, where
            for i, (kw, kind, ref) in enumerate(members):
                if kind == "infeasible":
                    assert st[i] == INFEASIBLE and np.isnan(x[i]).all(), (where, i)
                    continue
                assert st[i] == SOLVED, (where, i, st[i])
                if kind == "x":
                    atol = ATOL_JAX if solver == "jax" else ATOL_PIQP
                    np.testing.assert_allclose(x[i], ref, atol=atol, rtol=0, err_msg=f"{where} {i}")
                else:
                    # a singular P: x is not unique; its value and feasibility are. The
                    # JAX solver returns its interior point there (the polish needs
                    # P > 0), accurate to its stopping tolerance 1e-10 (scaled).
                    f = _objective(kw["P"], kw["q"], x[i])
                    assert abs(f - ref) <= 1e-7 * (1 + abs(ref)), (where, i, f, ref)
                    if "A" in kw:
                        assert np.abs(kw["A"] @ x[i] - kw["b"]).max() <= 1e-7, (where, i)


# ---------------------------------------------------------------- other shapes and dtypes

def test_square_and_tall_equalities():
    """A of n rows (full rank): x = A^-1 b is the only feasible point, SOLVED when it
    satisfies G and the bounds and INFEASIBLE when not. More rows than variables: PIQP
    solves a consistent system; the JAX path needs full row rank and says so."""
    rng = np.random.default_rng(11)
    A = rng.normal(size=(2, N, N))
    x_star = np.stack([rng.uniform(-0.5, 0.5, N), rng.uniform(-0.5, 0.5, N)])
    x_star[1, 0] = 2.0                                      # outside the box below
    args = {"P": np.stack([_spd(rng, N), _spd(rng, N)]), "q": rng.normal(size=(2, N)),
            "A": A, "b": np.einsum("bij,bj->bi", A, x_star),
            "lb": -np.ones((2, N)), "ub": np.ones((2, N))}
    for solver, opts in _solvers():
        x, st = solve_qp(**args, solver=solver, **opts)
        np.testing.assert_array_equal(st, [SOLVED, INFEASIBLE])
        np.testing.assert_allclose(x[0], np.linalg.solve(A[0], args["b"][0]),
                                   atol=ATOL_JAX if solver == "jax" else ATOL_PIQP, rtol=0)
        assert np.isnan(x[1]).all()
    kw, x_star = _constructed(12, False, True, False, False)
    kw["A"] = np.vstack([kw["A"], kw["A"], kw["A"][:2]])    # 6 consistent rows, rank 2
    kw["b"] = np.r_[kw["b"], kw["b"], kw["b"][:2]]
    x, st = solve_qp(**kw, solver="piqp")
    assert st == SolveStatus.SOLVED
    np.testing.assert_allclose(x, x_star, atol=ATOL_PIQP, rtol=0)
    with pytest.raises(ValueError, match=r"A has 6 rows for 5 variables"):
        solve_qp(**kw, solver="jax")


def _controller_qp(seed, nv=3, nu=2, nc=1):
    """A QP with the controller's structure (X = [q_ddot, u, lambda], A = [[M, -B, -J'],
    [J, 0, D]]), torque bounds only (no G: its reduced QP has no rows), u_0 at its lower
    bound at the optimum; (kwargs, x*)."""
    rng = np.random.default_rng(seed)
    n = nv + nu + nc
    M = _spd(rng, nv)
    A = np.block([[M, -rng.normal(size=(nv, nu)), -rng.normal(size=(nv, nc))],
                  [rng.normal(size=(nc, nv)), np.zeros((nc, nu)), 0.5 * np.eye(nc)]])
    P = _spd(rng, n)
    x = rng.uniform(-0.5, 0.5, n)
    y = rng.normal(size=nv + nc)
    lb = np.full(n, -np.inf)
    ub = np.full(n, np.inf)
    lb[nv:nv + nu] = x[nv:nv + nu] - rng.uniform(0.2, 1.0, nu)
    ub[nv:nv + nu] = x[nv:nv + nu] + rng.uniform(0.2, 1.0, nu)
    lb[nv] = x[nv]
    zl = np.zeros(n)
    zl[nv] = rng.uniform(0.5, 1.5)
    q = -(P @ x + A.T @ y - zl)
    return {"P": P, "q": q, "A": A, "b": A @ x, "lb": lb, "ub": ub}, x


def test_controller_structure():
    """structure="controller" (and "auto", which detects it with the right nv, nu) on a
    small QP of the controller's structure with no G rows, against x* and PIQP; a QP
    without the structure is refused with a message, not a crash."""
    kw, x_star = _controller_qp(21)
    for structure in ("controller", "auto"):
        for fallback in (False, True):
            x, st = solve_qp(**kw, solver="jax", structure=structure, nv=3, nu=2,
                             fallback=fallback)
            assert st == SolveStatus.SOLVED
            np.testing.assert_allclose(x, x_star, atol=ATOL_JAX, rtol=0)
    x, st = solve_qp(**kw, solver="piqp")
    assert st == SolveStatus.SOLVED
    np.testing.assert_allclose(x, x_star, atol=ATOL_PIQP, rtol=0)
    kw2, _ = _constructed(3, True, True, True, True)
    with pytest.raises(ValueError, match=r"structure='controller' needs the controller's QP"):
        solve_qp(**kw2, solver="jax", structure="controller", nv=3, nu=2)
    with pytest.raises(ValueError, match=r"structure='controller' needs the block sizes"):
        solve_qp(**kw, solver="jax", structure="controller")      # no nv, nu given
    with pytest.raises(ValueError, match="structure must be"):
        solve_qp(**kw2, solver="jax", structure="dense")


# ---------------------------------------------------------------- argument checks

def test_shape_errors_name_the_argument():
    kw, _ = _constructed(5, True, True, True, True)
    bad = {
        "q": np.zeros(N + 1), "G": np.zeros((MI, N + 1)), "h": np.zeros(MI + 1),
        "A": np.zeros((ME, N - 1)), "b": np.zeros(ME + 1), "lb": np.zeros(N - 1),
        "ub": np.zeros((2, N)),
    }
    for name, value in bad.items():
        for solver in ("jax", "piqp"):
            with pytest.raises(ValueError, match=rf"^{name}: "):
                solve_qp(**{**kw, name: value}, solver=solver)
    with pytest.raises(ValueError, match=r"^soft: "):
        solve_qp(**kw, soft=np.zeros(MI + 1))
    with pytest.raises(ValueError, match="G and h must be given together"):
        solve_qp(kw["P"], kw["q"], h=kw["h"])
    with pytest.raises(ValueError, match="A and b must be given together"):
        solve_qp(kw["P"], kw["q"], A=kw["A"])
    with pytest.raises(ValueError, match="^P must be"):
        solve_qp(np.zeros((N, N + 1)), kw["q"])
    # a batch: every given part with the batch's leading dimension
    args = {k: np.stack([v, v]) for k, v in kw.items()}
    for name in ("q", "G", "h", "lb"):
        with pytest.raises(ValueError, match=rf"^{name}: "):
            solve_qp(**{**args, name: args[name][:1]})
    with pytest.raises(ValueError, match=r"^G: expected a matrix"):
        solve_qp(**{**args, "G": args["G"][:, 0]})                # (B, n): rows missing


def test_qpsolvers_argument_forms():
    """The forms qpsolvers normalises for one QP: a 1-D G or A is one row, a scalar h or
    b one entry, (n, 1) / (1, n) vectors are flat, sparse matrices are accepted; lists
    too. Same x as the plain arrays."""
    import scipy.sparse as sp

    kw, x_star = _constructed(6, True, True, True, True)
    one_row = {"G": kw["G"][0], "h": float(kw["h"][0]), "A": kw["A"][0], "b": kw["b"][0]}
    x1, s1 = solve_qp(kw["P"], kw["q"], **one_row, lb=kw["lb"], ub=kw["ub"], solver="piqp")
    x2, s2 = solve_qp(kw["P"], kw["q"], kw["G"][:1], kw["h"][:1], kw["A"][:1], kw["b"][:1],
                      kw["lb"], kw["ub"], solver="piqp")
    assert s1 == s2 == SolveStatus.SOLVED
    np.testing.assert_array_equal(x1, x2)
    forms = {"P": sp.csc_matrix(kw["P"]), "q": kw["q"][:, None], "G": sp.csc_matrix(kw["G"]),
             "h": kw["h"][None, :], "A": kw["A"].tolist(), "b": list(kw["b"]),
             "lb": kw["lb"][None, :], "ub": kw["ub"][:, None]}
    for solver in ("jax", "piqp"):
        x, st = solve_qp(**forms, solver=solver)
        assert st == SolveStatus.SOLVED
        np.testing.assert_allclose(x, x_star, atol=ATOL_JAX if solver == "jax" else ATOL_PIQP,
                                   rtol=0)
