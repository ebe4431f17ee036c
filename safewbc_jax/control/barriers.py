"""Acceleration-based exponential control barrier functions (A-ECBFs).

This module follows the paper's section "Exponential control barrier functions". A safe
set C = {x : h(x) >= 0} is described by a smooth barrier h of relative degree r_b. Its
lower derivatives are stacked into

    eta_b = [h, h^(1), ..., h^(r_b - 1)]                              (eq. 19)

which obeys the integrator chain eta_dot = F eta + G nu, h = C eta (eqs. 20, 21), with
nu = h^(r_b). Choosing K_alpha so that the closed loop
eta_dot = (F - G K_alpha) eta has its roots at -p_1, ..., -p_rb and asking

    nu >= -K_alpha eta                                                 (eq. 22)

gives, by the comparison lemma, h(x(t)) >= C e^{(F - G K_alpha) t} eta(x_0). Theorem 1
(eqs. 23-25) says when this bound is itself non-negative (see :func:`admissible_pole_bounds`).

In the inverse-dynamics QP the input is the generalized acceleration q_ddot (the
decision variable X = [q_ddot, u, lambda]), and the certificate becomes the A-ECBF row

    L_F^rb h + L_G L_F^(rb-1) h q_ddot >= -K_alpha eta                 (eq. 28)

For a barrier h(q) of the configuration (relative degree 2 in q_ddot):
    eta = [h, J_h v],   L_F^2 h = J_h_dot v,   L_G L_F h = J_h,
so the row reads J_h q_ddot >= -K_alpha eta - J_h_dot v.
For a barrier h(q, v) of the state (relative degree 1):
    eta = [h],   L_F h = (dh/dq) along v (with q_ddot = 0),   L_G h = dh/dv,
so the row reads dh/dv q_ddot >= -K_alpha eta - L_F h.

Sign convention: every row here is returned as ``a_row @ q_ddot >= b`` ("greater or
equal", the paper's form); ``qp.assemble`` turns them into rows of G X <= h.

Configuration derivatives are taken on the floating-base manifold with the helpers of
:mod:`safewbc_jax.model.spatial` (MuJoCo's q / v convention), so the rows are consistent with
the rest of the controller. Everything that takes arrays is pure JAX (jit / vmap over q,
v and the poles); the barrier structure (which barriers, their relative degrees) is
static. :func:`check_poles` is plain numpy, meant to run once before compiling.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from safewbc_jax.model import spatial


class PoleError(ValueError):
    """The poles of a barrier violate Theorem 1 at the start state (or the theorem does not
    apply there), so the exponential bound on h(x(t)) is not guaranteed non-negative."""


# --------------------------------------------------------------------------------------
# Pole placement of the integrator chain
# --------------------------------------------------------------------------------------

def _partial_products(poles):
    """Ascending coefficients of prod_{k <= i} (s + p_k) for i = 0..r.

    Returns a list c_0..c_r, c_i of shape (..., i + 1) (c_0 = [1]); c_i[..., j] is the
    coefficient of s^j. Works for batched poles (..., r)."""
    poles = jnp.asarray(poles)
    c = jnp.ones(poles.shape[:-1] + (1,), poles.dtype)
    out = [c]
    for i in range(poles.shape[-1]):
        p = poles[..., i:i + 1]
        zero = jnp.zeros_like(p)
        # (s + p) * sum_j c_j s^j = sum_j c_j s^{j+1} + p c_j s^j
        c = jnp.concatenate([zero, c], axis=-1) + p * jnp.concatenate([c, zero], axis=-1)
        out.append(c)
    return out


def k_alpha_from_poles(poles):
    """K_alpha = [k_0, ..., k_{r-1}] placing the roots of eta_dot = (F - G K_alpha) eta at
    -p_1, ..., -p_r (the root set p_b = -[p_1, ..., p_rb] before Theorem 1).

    F - G K_alpha is the companion matrix of s^r + k_{r-1} s^{r-1} + ... + k_0, so the
    k_j are the coefficients of prod_i (s + p_i). ``poles`` has shape (..., r) (leading
    axes are a batch); the result has the same shape. For r = 2:
    K_alpha = [p_1 p_2, p_1 + p_2]."""
    return _partial_products(poles)[-1][..., :-1]


def integrator_chain(r: int, dtype=jnp.float64):
    """(F, G, C) of the chain eta_dot = F eta + G nu, h = C eta (eqs. 20, 21):
    F (r, r) with ones on the superdiagonal, G = e_r (r, 1), C = e_1^T (1, r)."""
    f = jnp.eye(r, k=1, dtype=dtype)
    g = jnp.zeros((r, 1), dtype).at[-1, 0].set(1.0)
    c = jnp.zeros((1, r), dtype).at[0, 0].set(1.0)
    return f, g, c


def closed_loop_matrix(k_alpha):
    """F - G K_alpha of the closed-loop chain eta_dot = (F - G K_alpha) eta (the system of
    Theorem 1), for K_alpha of shape (r,)."""
    k_alpha = jnp.asarray(k_alpha)
    f, g, _ = integrator_chain(k_alpha.shape[-1], k_alpha.dtype)
    return f - g @ k_alpha[None, :]


def comparison_bound(eta0, poles, t):
    """C e^{(F - G K_alpha) t} eta(x_0): the lower bound on h(x(t)) that the constraint
    nu >= -K_alpha eta guarantees by the comparison lemma (ECBF definition, eq. 22).

    ``t`` is a scalar time; vmap for a time grid. When the constraint is active for all
    t >= 0 (nu = -K_alpha eta) h(x(t)) equals this bound."""
    eta0 = jnp.asarray(eta0)
    a = closed_loop_matrix(k_alpha_from_poles(poles))
    return (jax.scipy.linalg.expm(a * t) @ eta0)[0]


# --------------------------------------------------------------------------------------
# Theorem 1: the functions B_i and the admissible poles
# --------------------------------------------------------------------------------------

def b_functions(eta, poles):
    """[B_0, ..., B_{r-1}] of Theorem 1, written through eta = [h, h_dot, ..., h^(r-1)]:

        B_0 = h,   B_i = B_{i-1}_dot + p_i B_{i-1}   (i = 1..r-1; eqs. 23-24),

    i.e. B_i = prod_{k <= i}(d/dt + p_k) h, a linear combination of h..h^(i) with the
    coefficients of prod_{k <= i}(s + p_k). (B_r = h^(r) + K_alpha eta needs h^(r), the
    input; the constraint nu >= -K_alpha eta is exactly B_r >= 0.) Shapes: eta (..., r),
    poles (..., r) -> (..., r)."""
    eta = jnp.asarray(eta)
    r = eta.shape[-1]
    c = _partial_products(poles)
    return jnp.stack([jnp.sum(c[i] * eta[..., :i + 1], axis=-1) for i in range(r)], axis=-1)


def b_function_rates(eta, poles, h_r=None):
    """[B_0_dot, ..., B_{r-1}_dot] (Theorem 1) through eta: B_{i}_dot is the same
    combination as B_i shifted by one derivative. The last one, B_{r-1}_dot, contains
    h^(r) and is only defined when ``h_r`` (the value of h^(r)) is given; otherwise it is
    returned as NaN."""
    eta = jnp.asarray(eta)
    r = eta.shape[-1]
    if h_r is None:
        h_r = jnp.full(eta.shape[:-1], jnp.nan, eta.dtype)
    ext = jnp.concatenate([eta, jnp.asarray(h_r, eta.dtype)[..., None]], axis=-1)
    c = _partial_products(poles)
    return jnp.stack([jnp.sum(c[i] * ext[..., 1:i + 2], axis=-1) for i in range(r)], axis=-1)


def admissible_pole_bounds(eta0, poles, h_r0=None):
    """Lower bound on each pole p_i from Theorem 1 at the start state x_0:

        p_i > 0  and  p_i >= -B_{i-1}_dot(x_0) / B_{i-1}(x_0),   i = 1..r   (eq. 25).

    "Admissible" poles are those for which B_0(x_0), ..., B_{r-1}(x_0) are all >= 0: then
    B_r >= 0 (the A-ECBF constraint) propagates down the chain,
    B_{i-1}(t) >= B_{i-1}(x_0) e^{-p_i t} >= 0, and ends at h(x(t)) >= 0 for all t. Since
    B_i(x_0) = B_{i-1}_dot(x_0) + p_i B_{i-1}(x_0), the condition on p_i is the bound
    above, and it depends on p_1..p_{i-1} through B_{i-1}: entry i is the bound *given
    the earlier poles as passed* (``poles[..., i-1:]`` do not enter it). The poles are
    admissible iff p_i > 0 and p_i >= entry i for every i, which is what
    :func:`check_poles` checks in order.

    Entry i is max(0, -B_{i-1}_dot / B_{i-1}) where B_{i-1}(x_0) > 0; 0 where
    B_{i-1}(x_0) = 0 and B_{i-1}_dot(x_0) >= 0 (then B_i(x_0) = B_{i-1}_dot(x_0) >= 0 for
    any p_i); +inf where no p_i helps (B_{i-1}(x_0) < 0, e.g. h(x_0) < 0 for i = 1 or an
    inadmissible p_{i-1} for i > 1, or B_{i-1}(x_0) = 0 with a negative rate). The last
    pole's literal bound needs B_{r-1}_dot(x_0), which contains the input h^(r)(x_0);
    without ``h_r0`` only B_{r-1}(x_0) >= 0 is required of it (entry 0, or +inf when
    B_{r-1}(x_0) < 0), because B_r(x_0) >= 0 is enforced by the constraint itself, which
    is all the proof needs. At rest (h_dot = ... = 0, h > 0) every entry is 0: any
    positive poles are admissible (the paper's remark).

    Pure JAX; shapes eta0 (..., r), poles (..., r) -> (..., r)."""
    eta0 = jnp.asarray(eta0)
    r = eta0.shape[-1]
    bs = b_functions(eta0, poles)
    # a placeholder h^(r) keeps NaNs out (the last entry is replaced below without h_r0)
    rates = b_function_rates(eta0, poles, 0.0 if h_r0 is None else h_r0)
    pos = bs > 0
    ratio = -rates / jnp.where(pos, bs, 1.0)
    bound = jnp.where(pos, jnp.maximum(0.0, ratio),
                      jnp.where((bs == 0) & (rates >= 0), 0.0, jnp.inf))
    if h_r0 is None:
        # Only p_r's bound would need h^(r)(x_0); keep the state conditions on B_{r-1}.
        last = jnp.where(bs[..., r - 1] >= 0, 0.0, jnp.inf)
        bound = bound.at[..., r - 1].set(last)
    return bound


def check_poles(name: str, eta0, poles, h_r0=None):
    """Raise :class:`PoleError` unless the poles of barrier ``name`` satisfy Theorem 1 at
    the start state with eta(x_0) = ``eta0``; return the bounds (numpy, one per pole).

    Plain Python/numpy, to run once before anything is compiled. It walks i = 1..r and
    fails, naming the barrier, the pole index, its value and its bound, when
      * p_i <= 0 (or is not finite),
      * h(x_0) < 0: the start state is outside the safe set, the theorem does not apply,
      * B_{i-1}(x_0) <= 0 in a way no p_i can repair (see :func:`admissible_pole_bounds`),
      * p_i < -B_{i-1}_dot(x_0) / B_{i-1}(x_0).
    The comparison p_i >= bound is exact (no tolerance). ``h_r0`` is optional, see
    :func:`admissible_pole_bounds`."""
    eta0 = np.asarray(eta0, dtype=float).reshape(-1)
    poles = np.asarray(poles, dtype=float).reshape(-1)
    r = eta0.size
    if poles.size != r:
        raise PoleError(f"barrier {name!r}: {poles.size} poles given for relative degree {r} "
                        f"(eta(x0) has {r} entries)")
    if not np.all(np.isfinite(eta0)):
        raise PoleError(f"barrier {name!r}: eta(x0) = {eta0} is not finite")
    if eta0[0] < 0:
        raise PoleError(f"barrier {name!r}: h(x0) = {eta0[0]:.6g} < 0, the start state is "
                        "outside the safe set and Theorem 1 does not apply")
    ext = np.append(eta0, np.nan if h_r0 is None else float(h_r0))
    c = np.ones(1)  # ascending coefficients of prod_{k < i} (s + p_k)
    bounds = np.zeros(r)
    for i in range(1, r + 1):
        p = poles[i - 1]
        if not np.isfinite(p) or p <= 0:
            raise PoleError(f"barrier {name!r}: pole p_{i} = {p:.6g} must be > 0 "
                            "(Theorem 1)")
        b_prev = float(c @ ext[:i])
        if i == r and h_r0 is None:
            bound = 0.0  # B_r(x0) >= 0 is the constraint itself
        else:
            rate = float(c @ ext[1:i + 1])
            if b_prev > 0:
                bound = max(0.0, -rate / b_prev)
            elif b_prev == 0 and rate >= 0:
                bound = 0.0
            else:
                raise PoleError(
                    f"barrier {name!r}: B_{i - 1}(x0) = {b_prev:.6g} with rate {rate:.6g}: "
                    f"no pole p_{i} (= {p:.6g}) makes B_{i}(x0) >= 0, Theorem 1 does not "
                    "apply at this start state")
        bounds[i - 1] = bound
        if p < bound:
            raise PoleError(
                f"barrier {name!r}: pole p_{i} = {p:.6g} is below its admissible bound "
                f"{bound:.6g} = -dB_{i - 1}/dt(x0) / B_{i - 1}(x0) (Theorem 1); "
                f"h(x(t)) may cross zero")
        c = np.concatenate([[0.0], c]) + p * np.concatenate([c, [0.0]])
    return bounds


# --------------------------------------------------------------------------------------
# The A-ECBF row
# --------------------------------------------------------------------------------------

class AECBFRow(NamedTuple):
    """One A-ECBF inequality ``a_row @ q_ddot >= b`` (eq. 28) and its ingredients."""

    a_row: jax.Array  # (nv,)  L_G L_F^(r-1) h
    b: jax.Array      # ()     -K_alpha eta - L_F^r h
    eta: jax.Array    # (r,)   [h, ..., h^(r-1)]
    drift: jax.Array  # ()     L_F^r h (J_h_dot v for r = 2)


def aecbf_inequality(eta, lf_r_h, lg_lf_h, k_alpha):
    """The A-ECBF condition, eq. 28, rearranged:
    L_F^r h + L_G L_F^(r-1) h q_ddot >= -K_alpha eta  <=>  a_row @ q_ddot >= b
    with a_row = L_G L_F^(r-1) h, b = -K_alpha eta - L_F^r h.

    Algebraic, any relative degree; returns (a_row, b)."""
    b = -jnp.sum(jnp.asarray(k_alpha) * jnp.asarray(eta), axis=-1) - lf_r_h
    return jnp.asarray(lg_lf_h), b


def _check_scalar(val, what):
    if jnp.ndim(val) != 0:
        raise ValueError(f"{what} must return a scalar, got shape {jnp.shape(val)}")


def barrier_lie_derivatives(h_fn, q, v, relative_degree: int = 2):
    """(eta, L_F^r h, L_G L_F^(r-1) h) of a barrier by automatic differentiation (eqs.
    19, 26), derivatives taken on the configuration manifold (spatial.integrate).

    relative_degree 2: ``h_fn(q)``; eta = [h, J_h v], L_F^2 h = J_h_dot v (second
    derivative along q(t) = integrate(q, v t), i.e. with q_ddot = 0), L_G L_F h = J_h.
    relative_degree 1: ``h_fn(q, v)``; eta = [h], L_F h = d/dt h(integrate(q, v t), v)
    (again q_ddot = 0), L_G h = dh/dv."""
    nv = v.shape[-1]
    if relative_degree == 2:
        h = h_fn(q)
        _check_scalar(h, "h_fn(q)")
        j = spatial.tangent_jacobian(h_fn, q, nv)
        drift = spatial.second_derivative_along(h_fn, q, v)
        return jnp.stack([h, j @ v]), drift, j
    if relative_degree == 1:
        h = h_fn(q, v)
        _check_scalar(h, "h_fn(q, v)")
        lf = spatial.derivative_along(lambda qq: h_fn(qq, v), q, v)
        lg = jax.grad(h_fn, argnums=1)(q, v)
        return h[None], lf, lg
    raise ValueError(f"relative_degree must be 1 (h(q, v)) or 2 (h(q)), got {relative_degree}")


def aecbf_row(h_fn, q, v, poles, relative_degree: int = 2) -> AECBFRow:
    """The A-ECBF row a_row @ q_ddot >= b of eq. 28 for the barrier ``h_fn`` at (q, v)
    with the closed-loop roots -poles (K_alpha from :func:`k_alpha_from_poles`).

    ``h_fn(q)`` for relative degree 2, ``h_fn(q, v)`` for relative degree 1 (see
    :func:`barrier_lie_derivatives`). ``poles`` has shape (relative_degree,); ``h_fn``
    and ``relative_degree`` are static, q, v and poles may be traced (jit, vmap)."""
    poles = jnp.asarray(poles)
    if poles.shape[-1] != relative_degree:
        raise ValueError(f"{poles.shape[-1]} poles for a barrier of relative degree "
                         f"{relative_degree}")
    eta, drift, lg = barrier_lie_derivatives(h_fn, q, v, relative_degree)
    a_row, b = aecbf_inequality(eta, drift, lg, k_alpha_from_poles(poles))
    return AECBFRow(a_row=a_row, b=b, eta=eta, drift=drift)


def aecbf_row_from_terms(h, j_h, jdot_h_v, v, poles) -> AECBFRow:
    """The A-ECBF row of eq. 28 for a relative-degree-2 barrier whose h, J_h and
    J_h_dot v are given in closed form (``SafeSet.terms``): eta = [h, J_h v],
    L_F^2 h = J_h_dot v, L_G L_F h = J_h, as ``barrier_lie_derivatives`` takes them by
    automatic differentiation."""
    poles = jnp.asarray(poles)
    if poles.shape[-1] != 2:
        raise ValueError(f"{poles.shape[-1]} poles for a barrier of relative degree 2")
    eta = jnp.stack([h, j_h @ v])
    a_row, b = aecbf_inequality(eta, jdot_h_v, j_h, k_alpha_from_poles(poles))
    return AECBFRow(a_row=a_row, b=b, eta=eta, drift=jdot_h_v)


__all__ = [
    "PoleError", "k_alpha_from_poles", "integrator_chain", "closed_loop_matrix",
    "comparison_bound", "b_functions", "b_function_rates", "admissible_pole_bounds",
    "check_poles", "AECBFRow", "aecbf_inequality", "barrier_lie_derivatives", "aecbf_row",
    "aecbf_row_from_terms",
]
