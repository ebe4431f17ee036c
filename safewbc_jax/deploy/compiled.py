"""The deployed step, compiled once: ``prepare`` (with the exact elimination of the QP's
equality rows) and ``conclude`` jitted on flat float64 vectors, their layouts, and the host
side of a step over explicit per-lane state.

    step = CompiledStep(ctx, fixed, q, v)          # traces and jits; compiles at first call
    lane = LaneState(solver, step.nu)              # one robot's host-side state
    flats, reasons = step.admit([lane], [meas])
    state, prep, packed = step.prepare(fixed, state, flats[0])
    cmds, sols = step.finish([lane], prep[None], packed[None], reasons, [meas.t], t_in)

One robot is one lane; for several lanes the unjitted functions vmap over the lanes and
the host side handles all the lanes at once. A lane's result does not depend on the other
lanes. Every argument and result of a step is one float64 vector (``packing.FlatTree``),
not a pytree of some forty arrays.
"""

from __future__ import annotations

import dataclasses
import functools
import time
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from safewbc_jax.control import qp as qp_assembly
from safewbc_jax.control import step as control_step
from safewbc_jax.control.step import Measurement, state_ok
from safewbc_jax.deploy.checks import check_measurement
from safewbc_jax.deploy.packing import FlatTree, Packer
from safewbc_jax.solvers import host, policy, reduce
from safewbc_jax.solvers.piqp_path import PiqpSolver
from safewbc_jax.solvers.problem import QP
from safewbc_jax.solvers.result import (FALLBACK_FAILED, FALLBACK_NONE, FALLBACK_RELAXED,
                                        NOT_ATTEMPTED, SolveResult, failed, fallback_name, row)
from safewbc_jax.solvers.status import SolveStatus


@functools.partial(jax.tree_util.register_dataclass,
                   data_fields=["u", "motor", "latency_us"],
                   meta_fields=["solve_status", "fallback", "measurement"])
@dataclasses.dataclass(frozen=True)
class Command:
    """One step's output.

    Attributes:
        u: joint torques (nu,), in the controller's actuator order.
        motor: motor torques (nu,), in the robot's motor order (``MotorMap``), clipped to
            the motor limits.
        solve_status: the QP's ``SolveStatus``; None where no QP ran.
        fallback: "none", "relaxed", "failed" (the QP failed: the last good torque is
            held) or "held" (the measurement was refused: the last good torque is held).
        measurement: "ok", or why the measurement was refused.
        latency_us: the step's wall time in microseconds.
    """

    u: np.ndarray
    motor: np.ndarray
    solve_status: SolveStatus | None
    fallback: str
    measurement: str
    latency_us: float


ENGINES = ("auto", "c", "xla")


def resolve_engine(engine: str) -> str:
    """"c" or "xla" for ``engine``: "auto" is C where a C compiler exists, else XLA.
    Raises ValueError for another name, or for "c" without a compiler."""
    from safewbc_jax.deploy.codegen.build import compiler

    if engine not in ENGINES:
        raise ValueError(f"engine {engine!r}: one of {', '.join(ENGINES)}")
    if engine == "auto":
        return "c" if compiler() is not None else "xla"
    if engine == "c" and compiler() is None:
        raise ValueError("engine 'c': no C compiler found (set CC, or install cc, gcc or "
                         "clang), or use engine 'xla'")
    return engine


@dataclasses.dataclass(frozen=True)
class HostRecord:
    """A good step, for logs: the control step's ``StepRecord`` (numpy), the state the QP
    saw (v with the rigid swing-leg rates), the domain, X or None, the solver's
    ``SolveResult`` (x over the full X, NaN where failed; eq_residual of the full QP, the
    other residuals of the reduced QP PIQP solved; None where the measurement was
    refused), the wall times of the QP's preparation and of the solve (us)."""

    step: Any
    q: np.ndarray
    v: np.ndarray
    domain: Any          # walking.Domain, or None
    x: np.ndarray | None
    solve: Any
    t_qp: float
    t_solve: float

    @property
    def tau(self) -> float:
        return float(self.step.tau)



class EqualityRows(NamedTuple):
    """The full QP's equality rows A X = b (paper eqs. 1-3), the one part of it that the
    step's host side reads after the solve (X's equality residual). ``prepare`` writes
    these, not the whole 78-variable QP: ``CompiledStep.full_qp`` computes that on
    demand (``Controller.last_qp``)."""

    A: Any    # (nv + nc, n)
    b: Any    # (nv + nc,)


def accept_solution(motors: control_step.MotorArrays, sol: FlatTree, blocks, eqs: EqualityRows,
                    red, rmap, checks: policy.Checks, x, status, iterations, feas_tol):
    """The host side of a step after PIQP has solved the reduced QP as posed: the
    acceptance of x (``policy.accept_batch``'s test), X = x0 + N x (``reduce.expand``), the
    full QP's equality residual, X's torques u and the motor map (``MotorArrays.to_motor``).
    Written once in jax.numpy; the C engine runs it as generated C (``swbc_accept``,
    ``CompiledStep.solve_one``). ``tests/test_deploy_same_qp.py`` holds the C to XLA's and
    its decision to ``policy.accept_batch``; ``tests/test_lockstep.py`` holds
    ``solve_one`` to the numpy path of ``CompiledStep.solve``.

    Args:
        motors: the motor map.
        sol: the layout of conclude's flat solve record (``Layouts.sol``).
        blocks: the full QP's block sizes (``QP.blocks``).
        eqs, red, rmap, checks: the full QP's equality rows, the reduced QP, the map back
            to X and the reduced QP's ``policy.Checks``, as ``prepare`` packed them.
        x: PIQP's solution of the reduced QP.
        status, iterations: PIQP's ``SolveStatus`` code and iteration count.
        feas_tol: the solver's acceptance tolerance.

    Returns:
        (the flat solve record, u, motor torques, ok): ok is 1 where x is accepted and X
        is finite, else 0; then the host runs the policy's fallback (relaxed QP, or the
        torque held) and the other outputs are not used.
    """
    eq, ineq, hard = policy.residuals_checked(x, red, checks, jnp)
    X = reduce.expand(x, rmap)
    ok = ((status == int(SolveStatus.SOLVED)) & policy.within(eq, ineq, feas_tol, checks)
          & jnp.isfinite(X).all())
    res = SolveResult(x=X, status=status, fallback=FALLBACK_NONE, relaxed_status=NOT_ATTEMPTED,
                      iterations=iterations, max_slack=0.0,
                      eq_residual=jnp.abs(eqs.A @ X - eqs.b).max(initial=0.0),
                      ineq_violation=ineq, hard_violation=hard, polished=False,
                      polish_iterations=0)
    u = blocks.split(X)[1]
    return sol.pack(res, jnp), u, motors.to_motor(u, jnp), ok.astype(jnp.float64)


class Layouts(NamedTuple):
    """The flat-vector layout of each argument and result of the compiled step."""

    fixed: FlatTree      # (ControllerParams, scenario.Start, RunValues)
    state: FlatTree      # control.step.ControllerState
    tally: FlatTree      # control.step.Tally
    meas: FlatTree       # control.step.Measurement
    prep: FlatTree       # control.step.Prepared
    sol: FlatTree        # solvers.result.SolveResult


@dataclasses.dataclass(eq=False)
class LaneState:
    """The host side of one robot running a ``CompiledStep``: its solver (of the
    ``solvers.host`` protocol), its counters, the torque it holds, the time of its last
    accepted measurement, the wall times of its last good step (prepare, solve; us) and
    the flat (ControllerState, measurement) its last good step started from (for
    ``CompiledStep.full_qp``)."""

    solver: Any
    nu: int
    steps: int = 0
    qp_failed: int = 0
    fallbacks: int = 0
    bad_measurements: int = 0
    last_u: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))
    prev_t: float | None = None
    last_times: tuple[float, float] = (np.nan, np.nan)
    last_inputs: tuple[Any, np.ndarray] | None = None
    # the C engine's prepare writes into the lane's own output arrays, whose QPs are
    # unpacked once (``CompiledStep.prepare_lane``)
    outputs: tuple = ()
    views: Any = None
    fast: Any = None              # ``CompiledStep.solve_one``'s views and buffer

    def __post_init__(self) -> None:
        self.last_u = np.zeros(self.nu)

    def reset(self) -> None:
        """Counters zero, no torque held, the clock restarting, the solver set up afresh."""
        self.steps = self.qp_failed = self.fallbacks = self.bad_measurements = 0
        self.last_u = np.zeros(self.nu)
        self.prev_t, self.last_inputs = None, None
        self.last_times = (np.nan, np.nan)
        self.outputs, self.views, self.fast = (), None, None
        host.reset(self.solver)

    def sibling(self) -> LaneState:
        """A fresh lane with an independent solver of the same settings."""
        return LaneState(host.lane(self.solver), self.nu)


class CompiledStep:
    """``control.step.prepare`` (with ``solvers.reduce.eliminate_equalities``) and
    ``control.step.conclude`` of one ``control.step.Context``, on flat vectors.

    Args:
        ctx: what the step is compiled for (model, scenario, control period, motors).
        fixed: a template of (ControllerParams, scenario.Start, RunValues), the step's
            per-run values; only shapes and dtypes are read.
        q: a start configuration; the QP traced at (q, v) gives the elimination's static
            data.
        v: a start velocity.

    Attributes:
        prepare: jitted ``prepare(fixed, state, meas) -> (state, prepared, packed QP)``.
        conclude: jitted ``conclude(fixed, tally, prepared, solve) -> (tally, packed
            record)``.
        prepare_fn, conclude_fn: the same, unjitted (to vmap over lanes).
        layouts: the ``Layouts`` of the flat vectors.
        unpack_qp: packed QP -> (the full QP's ``EqualityRows``, reduced QP, map back to
            X, ``policy.Checks``).
        blocks: the full QP's block sizes.
        unpack_record: packed record -> (StepRecord, q, v, domain).
        no_solution: the flat solve record of a step without a solution.
    """

    def __init__(self, ctx: control_step.Context, fixed: tuple, q: np.ndarray, v: np.ndarray,
                 engine: str = "xla", native: bool = False):
        self.ctx = ctx
        self.walking = ctx.walking
        self.nq, self.nv, self.nu = ctx.model.nq, ctx.model.nv, ctx.model.nu
        state0, tally0 = control_step.init_state(ctx, q, v, np, np.float64)
        meas0 = Measurement(q, v, 0.0, np.zeros(2))
        # the elimination's static data is the QP's structure by construction
        # (qp.P_STRUCTURE): no bounded variable outside u, P block-diagonal with diagonal u
        # and lambda blocks
        bounded, p_blockdiag = np.zeros(0, int), qp_assembly.P_STRUCTURE
        f_fixed, f_state, f_tally, f_meas = (FlatTree(t) for t in (fixed, state0, tally0, meas0))
        qp_packer, out_packer = Packer(), Packer()
        traced: dict = {}             # the Prepared layout and nx, from the first trace

        def built(fixed, state, meas):         # control_step.prepare on the flat vectors
            return control_step.prepare(ctx, *f_fixed.unpack(fixed, jnp),
                                        f_state.unpack(state, jnp), f_meas.unpack(meas, jnp))

        def prepare(fixed, state, meas):
            state, prep, qpm = built(fixed, state, meas)
            red, rmap = reduce.eliminate_equalities(qpm, bounded, p_blockdiag)
            flat = traced.setdefault("prep", FlatTree(prep))
            traced.setdefault("nx", int(qpm.P.shape[-1]))
            traced.setdefault("nr", int(red.P.shape[-1]))
            traced.setdefault("blocks", qpm.blocks)
            return (f_state.pack(state, jnp), flat.pack(prep, jnp),
                    qp_packer.pack((EqualityRows(qpm.A, qpm.b), red, rmap,
                                    policy.checks(red, jnp))))

        def conclude(fixed, tally, prep, sol):
            L = self.layouts
            prep = L.prep.unpack(prep, jnp)
            tally, out = control_step.conclude(ctx, L.fixed.unpack(fixed, jnp)[2],
                                               L.tally.unpack(tally, jnp), prep,
                                               L.sol.unpack(sol, jnp))
            return (L.tally.pack(tally, jnp),
                    out_packer.pack((out.record, prep.q, prep.v, prep.domain)))

        def accept(packed, solved):
            L = self.layouts
            eqs, red, rmap, checks = qp_packer.unpack(packed, jnp)
            nr = red.P.shape[-1]
            return accept_solution(ctx.motors, L.sol, self.blocks, eqs, red, rmap, checks,
                                   solved[:nr], *solved[nr:])

        self._built: Callable = built
        self.prepare_fn: Callable = prepare
        self.conclude_fn: Callable = conclude
        self.accept_fn: Callable = accept
        self.accept: Callable | None = None     # the C engine's (``_use_c``)
        self.prepare: Callable = jax.jit(prepare)
        self.conclude: Callable = jax.jit(conclude)
        self.engine = resolve_engine(engine)
        # one trace of prepare gives its layouts (and, for C, the jaxpr to write out);
        # XLA's jit reuses it at the first call
        zeros = [np.zeros(f.size) for f in (f_fixed, f_state, f_meas)]
        jp = (jax.make_jaxpr(prepare)(*zeros) if self.engine == "c"
              else self.prepare.trace(*zeros))       # type: ignore[attr-defined]
        self.nx, self.nr, self.qp_size = traced["nx"], traced["nr"], qp_packer.size
        self.blocks = traced["blocks"]
        self._full_qp: Callable | None = None
        self.layouts = Layouts(f_fixed, f_state, f_tally, f_meas, traced["prep"],
                               FlatTree(failed(self.nx)))
        self.no_solution = self.flat_solution(failed(self.nx))
        # their layouts are recorded by the first trace of prepare / conclude
        self.unpack_qp: Callable = qp_packer.unpack
        self.unpack_record: Callable = out_packer.unpack
        self.c_source: str | None = None
        self.c_built = False           # compiled at this start, not found in the cache
        if self.engine == "c":
            self._use_c(jp, native)

    def _use_c(self, jp, native: bool) -> None:
        """``prepare`` (its jaxpr ``jp``) and ``conclude`` as generated C
        (``deploy.codegen``), built with the system compiler (cached by the source's hash)
        and called on numpy arrays."""
        from safewbc_jax.deploy.codegen import build, emit

        L = self.layouts
        zeros = lambda flat: np.zeros(flat.size)  # noqa: E731
        jc = jax.make_jaxpr(self.conclude_fn)(zeros(L.fixed), zeros(L.tally), zeros(L.prep),
                                              zeros(L.sol))
        ja = jax.make_jaxpr(self.accept_fn)(np.zeros(self.qp_size), np.zeros(self.nr + 3))
        fp, fc = emit.emit_function("swbc_prepare", jp), emit.emit_function("swbc_conclude", jc)
        fa = emit.emit_function("swbc_accept", ja)
        self.c_source = emit.c_file([fp, fc, fa])
        path, self.c_built = build.build(self.c_source, native)
        lib = build.load(path)
        self.prepare, self.conclude = build.CCall(lib, fp), build.CCall(lib, fc)
        self.accept = build.CCall(lib, fa)

    def asarray(self, a):
        """``a`` as the engine's arrays take it (numpy for C, a JAX array for XLA)."""
        return np.asarray(a) if self.engine == "c" else jnp.asarray(a)

    def full_qp(self, fixed, state, meas) -> QP:
        """The full QP (numpy) that ``prepare`` builds from these flat inputs, before its
        elimination: computed on demand by XLA (jitted at the first call), whatever the
        engine, since the step itself writes only its ``EqualityRows``."""
        if self._full_qp is None:
            built = self._built
            self._full_qp = jax.jit(lambda *flat: built(*flat)[2])
        return self._full_qp(fixed, state, meas).with_arrays(np.array)

    # -- flat vectors
    def pack_fixed(self, params, start, run: control_step.RunValues) -> np.ndarray:
        """The per-run values (ControllerParams, the references' start data, RunValues) as
        the step's flat ``fixed`` vector."""
        return self.layouts.fixed.pack((params, start, run))

    def initial(self, q, v) -> tuple[np.ndarray, np.ndarray]:
        """The flat (ControllerState, Tally) before the first step at the start state."""
        state, tally = control_step.init_state(self.ctx, q, v, np, np.float64)
        return self.layouts.state.pack(state), self.layouts.tally.pack(tally)

    @property
    def ok_index(self) -> int:
        """Where ``Prepared.ok`` (the step's state tests passed) sits in the flat Prepared
        vector."""
        flat = self.layouts.prep
        return int(flat.unpack(np.arange(flat.size, dtype=float)).ok)

    @property
    def tau_index(self) -> int:
        """Where tau sits in the flat Prepared vector."""
        flat = self.layouts.prep
        return int(flat.unpack(np.arange(flat.size, dtype=float)).tau)

    def flat_solution(self, res: SolveResult) -> np.ndarray:
        """A host SolveResult (one QP's, or L's with a leading axis) as conclude's flat
        vector(s): x, then each scalar field, in ``layouts.sol``'s order."""
        out = np.empty(np.shape(res.x)[:-1] + (self.nx + len(res) - 1,))
        out[..., :self.nx] = res.x
        for k, f in enumerate(res[1:]):
            out[..., self.nx + k] = f
        return out

    def flat_measurement(self, meas: Measurement) -> np.ndarray | None:
        """The measurement as the step's flat vector (q, v, sole forces, t), or None where
        it cannot be one (shapes, types; sole forces missing while walking)."""
        try:
            q, v = np.asarray(meas.q, float), np.asarray(meas.v, float)
            f = (np.zeros(2) if meas.sole_force is None and not self.walking
                 else np.asarray(meas.sole_force, float))
            if q.shape != (self.nq,) or v.shape != (self.nv,) or f.shape != (2,):
                return None
            return np.concatenate([q, v, f, [float(meas.t)]])
        except (TypeError, ValueError):
            return None

    def prepare_lane(self, lane: LaneState, fixed, state, flat) -> tuple:
        """``prepare`` for one lane: (state, Prepared, packed QPs, their unpacked QPs with
        a leading axis of 1, or None). The C engine writes into the lane's output arrays
        (made at the first call), whose QPs are unpacked once."""
        if self.engine != "c":
            return (*self.prepare(fixed, state, flat), None)
        if not lane.outputs:
            lane.outputs = self.prepare.outputs()  # type: ignore[attr-defined]
            lane.views = self.unpack_qp(lane.outputs[2][None])
        new, prep, packed = self.prepare(fixed, state, flat, out=lane.outputs)
        return new, prep, packed, lane.views

    def admit_fast(self, lane: LaneState, meas: Measurement) -> np.ndarray | None:
        """The measurement's flat vector where the host-only tests pass (shapes, types, t
        advancing), counting the step; None where they fail, for ``admit_one``. The state
        tests run inside ``prepare`` (``Prepared.ok``); ``refused`` names a refusal."""
        flat = self.flat_measurement(meas)
        if flat is None or (lane.prev_t is not None and not flat[-1] > lane.prev_t):
            return None
        lane.steps += 1
        return flat

    def refused(self, lane: LaneState, meas: Measurement) -> str:
        """Why ``prepare`` refused a measurement that ``admit_fast`` let in
        (``check_measurement``), counted as a bad measurement."""
        lane.bad_measurements += 1
        reason = check_measurement(meas, self.walking, self.nq, self.nv)
        return reason if reason != "ok" else "refused by the step's state tests"

    # -- the host side of a step
    def admit_one(self, lane: LaneState, meas: Measurement) -> tuple[np.ndarray | None, str]:
        """Count the step and check the measurement (``check_measurement``, and that t
        advances). Returns (its flat vector, or None where it cannot enter the step; "ok"
        or why it is refused)."""
        lane.steps += 1
        reason = check_measurement(meas, self.walking, self.nq, self.nv)
        if reason == "ok" and lane.prev_t is not None and not meas.t > lane.prev_t:
            reason = f"t = {meas.t} does not advance (last step at {lane.prev_t})"
        if reason != "ok":
            lane.bad_measurements += 1
        return self.flat_measurement(meas), reason

    def admit(self, lanes: list[LaneState], meas: list) -> tuple[list, list[str]]:
        """``admit_one`` for several lanes: the state test (``state_ok``) and the time tests
        run once over the stacked measurements; a lane whose measurement fails one of
        them, or cannot be stacked, goes through ``admit_one``, which names the reason."""
        try:
            flat = np.stack([self.flat_measurement(m) for m in meas])  # type: ignore[misc]
        except (TypeError, ValueError):      # some measurement cannot be a flat vector
            flat = None
        if flat is None or flat.dtype != np.float64:
            out = [self.admit_one(lane, m) for lane, m in zip(lanes, meas)]
            return [f for f, _ in out], [r for _, r in out]
        nq, nv = self.nq, self.nv
        t = flat[:, -1]
        prev = np.array([-np.inf if lane.prev_t is None else lane.prev_t for lane in lanes])
        good = (state_ok(flat[:, :nq], flat[:, nq:nq + nv]) & np.isfinite(t) & (t > prev)
                & np.isfinite(flat[:, nq + nv:-1]).all(axis=1))
        reasons = ["ok"] * len(lanes)
        for i, lane in enumerate(lanes):
            if good[i]:
                lane.steps += 1
            else:
                reasons[i] = self.admit_one(lane, meas[i])[1]
        return list(flat), reasons

    def solve(self, lanes: list[LaneState], packed: np.ndarray, ts, t_in: float,
              t_step: float, unpacked: tuple | None = None
              ) -> tuple[list[Command], np.ndarray, SolveResult, np.ndarray, np.ndarray]:
        """The host side of a step for lanes with accepted measurements, from the jitted
        prepare's packed QPs (leading axis L): each lane's reduced QP by its own solver
        (``solvers.host.solve_lanes``), X = x0 + N u, the usable test, the held-torque
        rule, the motor map and each lane's counters.

        ``unpacked``: ``unpack_qp(packed)`` where it is at hand (``prepare_lane``).

        Returns:
            (the Commands; conclude's flat solve records (L, .); the SolveResult, x over
            the full X and NaN where not usable, eq_residual of the full QP; X; usable).
        """
        eqs, red, rmap, checks = self.unpack_qp(packed) if unpacked is None else unpacked
        t1 = time.perf_counter()
        res = host.solve_lanes([lane.solver for lane in lanes], red, checks)
        return self._conclude_lanes(lanes, eqs, rmap, res, ts, t_in, t_step, t1)

    def _conclude_lanes(self, lanes: list[LaneState], eqs, rmap, res: SolveResult, ts,
                        t_in: float, t_step: float, t1: float) -> tuple:
        """``solve`` after the solvers' ``res`` over the reduced QPs (started at ``t1``)."""
        x = reduce.expand(res.x, rmap)
        usable = (res.fallback != FALLBACK_FAILED) & np.isfinite(x).all(axis=-1)
        eq = np.abs((eqs.A @ x[..., None])[..., 0] - eqs.b).max(axis=-1)
        res = res._replace(x=x, eq_residual=eq)
        if not usable.all():      # rare: failed()'s fields on those rows, with the
            res = SolveResult(*(np.array(f) for f in res))   # solver's status, or
            for i in np.flatnonzero(~usable).tolist():       # NUMERICAL for a non-finite X
                status = (res.status[i] if res.fallback[i] == FALLBACK_FAILED
                          else SolveStatus.NUMERICAL)
                bad = failed(self.nx, status)._replace(iterations=res.iterations[i])
                for f, v in zip(res, bad):
                    f[i] = v
        t2 = time.perf_counter()
        last_u = np.stack([lane.last_u for lane in lanes])
        u = control_step.hold_torque(res.x, usable[:, None], last_u, self.blocks)
        motor = self.ctx.motors.to_motor(u)
        sols = self.flat_solution(res)
        times = ((t1 - t_step) * 1e6, (t2 - t1) * 1e6 / len(lanes))
        t_out = (time.perf_counter() - t_in) * 1e6
        cmds = []
        for j, lane in enumerate(lanes):
            fb = int(res.fallback[j])
            lane.last_times = times
            lane.qp_failed += fb == FALLBACK_FAILED
            lane.fallbacks += fb == FALLBACK_RELAXED
            lane.last_u, lane.prev_t = u[j], ts[j]
            cmds.append(Command(u[j].copy(), motor[j], SolveStatus(int(res.status[j])),
                                fallback_name(fb), "ok", t_out))
        return cmds, sols, res, x, usable

    def fast(self, lane: LaneState) -> bool:
        """Whether ``solve_one`` takes ``lane``'s step: the C engine with a ``PiqpSolver``."""
        return self.accept is not None and isinstance(lane.solver, PiqpSolver)

    def solve_one(self, lane: LaneState, packed: np.ndarray, t: float, t_in: float,
                  t_step: float) -> tuple[Command, np.ndarray, np.ndarray | None]:
        """``solve`` for one lane (``fast``) after ``prepare_lane``: PIQP on the reduced QP
        as posed, then the generated ``swbc_accept`` (``accept_solution``) in one call. Where
        it does not accept x, ``solve``'s numpy path finishes the step from the same solve
        (the relaxed QP, or the held torque). Returns (the Command; conclude's flat solve
        record; X, or None where not usable)."""
        if lane.fast is None:       # the lane's reduced QP (views of its output arrays)
            _, red, _, checks = lane.views
            lane.fast = (red.row(0), type(checks)(*(c[0] for c in checks)),
                         np.zeros(self.nr + 3))
        red, checks, solved = lane.fast
        s: PiqpSolver = lane.solver
        t1 = time.perf_counter()
        x, status, iters = s.solve_nominal(red)
        s.last_solve_time_us = (time.perf_counter() - t1) * 1e6
        solved[:-3], solved[-3:] = x, (status, iters, s.feas_tol)
        sol, u, motor, ok = self.accept(packed, solved)          # type: ignore[misc]
        if not ok:                   # rare: the policy's fallback, in numpy
            eqs, red_l, rmap, checks_l = lane.views
            res = PiqpSolver.solve_lanes([s], red_l, checks_l,
                                         nominal=(x[None], [status], [iters]))
            cmds, sols, _, xs, usable = self._conclude_lanes([lane], eqs, rmap, res, (t,),
                                                             t_in, t_step, t1)
            return cmds[0], sols[0], xs[0] if usable[0] else None
        t2 = time.perf_counter()
        lane.last_times = ((t1 - t_step) * 1e6, (t2 - t1) * 1e6)
        lane.last_u, lane.prev_t = u, t
        return (Command(u.copy(), motor, SolveStatus.SOLVED, "none", "ok",
                        (time.perf_counter() - t_in) * 1e6), sol, sol[:self.nx])

    def solve_result(self, sol: np.ndarray) -> SolveResult:
        """One QP's SolveResult (``result.row``'s types) from its flat solve record."""
        return row(SolveResult(*(np.asarray(f)[None] for f in self.layouts.sol.unpack(sol))), 0)

    def solve_lane(self, lane: LaneState, reason: str, packed, views, t: float, t_in: float,
                   t_step: float) -> tuple[Command, np.ndarray, np.ndarray | None]:
        """The host side of one lane's step after ``prepare_lane`` (``reason``: "ok", or why
        its measurement is refused): ``hold`` where refused, ``solve_one`` where ``fast``,
        else ``solve`` of the one lane. Returns (the Command; conclude's flat solve record;
        X, or None where there is no usable one)."""
        if reason != "ok":         # the torque is held
            return self.hold(lane, reason, t_in), self.no_solution, None
        if self.fast(lane):        # the C engine with PIQP: one call after the solve
            return self.solve_one(lane, packed, t, t_in, t_step)
        cmds, sols, _, xs, usable = self.solve([lane], np.asarray(packed)[None], (t,), t_in,
                                               t_step, views)
        return cmds[0], sols[0], xs[0] if usable[0] else None

    def hold(self, lane: LaneState, reason: str, t_in: float) -> Command:
        """A refused measurement's step: no solve, the lane's last good torque held."""
        lane.last_times = (np.nan, np.nan)
        return self.command(lane.last_u, None, "held", reason, t_in)

    def finish(self, lanes: list[LaneState], prep: np.ndarray, packed: np.ndarray,
               reasons: list[str], ts, t_in: float) -> tuple[list[Command], np.ndarray]:
        """The host side of a step for several lanes, from the rows of the prepare
        (``prep``, ``packed``: leading axis L): the lanes whose measurement was accepted
        through ``solve`` together, the others hold their torque (``hold``). ``ts``: the
        measurements' times. Returns (the Commands, conclude's flat solve records (L, .))."""
        sols = np.tile(self.no_solution, (len(lanes), 1))
        cmds: list = [None] * len(lanes)
        ok = np.array([r == "ok" for r in reasons])
        for i in np.flatnonzero(~ok).tolist():
            cmds[i] = self.hold(lanes[i], reasons[i], t_in)
        idx = np.flatnonzero(ok)
        if idx.size:
            every = idx.size == len(lanes)
            got, sols[idx], *_ = self.solve(
                lanes if every else [lanes[i] for i in idx], packed if every else packed[idx],
                ts if every else [ts[i] for i in idx], t_in, t_in)
            for i, c in zip(idx.tolist(), got):
                cmds[i] = c
        return cmds, sols

    def command(self, u, status: SolveStatus | None, fallback: str, reason: str,
                t_in: float) -> Command:
        """A Command of the torques u, timed from ``t_in`` (``time.perf_counter``)."""
        u = np.array(u)
        return Command(u, self.ctx.motors.to_motor(u), status, fallback, reason,
                       (time.perf_counter() - t_in) * 1e6)
