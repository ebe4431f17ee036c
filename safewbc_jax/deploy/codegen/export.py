"""``safewbc export-c``: one scenario's controller as a C99 folder a robot computer builds
with ``make`` and no Python.

    safewbc_step.h     the functions, the vector sizes, the measurement's layout
    safewbc_step.c     the generated functions (static buffers, no malloc, libm only)
    main.c             an example: one step at a stored state, checked against Python's
    Makefile           ``make`` builds the example and runs it

The functions, all on flat double vectors (sizes in the header):

    swbc_start(q, fixed)                     the run's fixed vector from the start pose q
                                             (the controller parameters are built in)
    swbc_init(q, v, state, tally)            the step's state before the first step
    swbc_step(fixed, state, tally, meas,     one whole control step: measurement in, motor
              state', tally', motor, u)      torques out, the QP solved by the batched
                                             path's interior-point solver (``jax_qp``)
    swbc_prepare(fixed, state, meas,         the step up to the QP, for an own QP solver:
                 state', prep, qp)           qp holds the reduced QP in the torques, the
                                             map back to X, the full QP's equality rows and
                                             the acceptance checks' rows (``SWBC_QP_*``:
                                             where each array starts, row-major)
    swbc_accept(qp, solved,                  after an own solver's solution of the reduced
                sol, u, motor, ok)           QP (solved: its x, status, iterations, feas_tol):
                                             the acceptance test, X, the torques, the motor
                                             map; ok 0 where the solution is not accepted
    swbc_conclude(fixed, tally, prep, sol,   the torque, record and metrics from a solution
                  tally', record)

The measurement vector is (q (nq), v (nv), left and right sole normal forces (2), t).
Theorem 1's start check is not in the C: run it in Python (``Controller.start``) for the
poles you export.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np

from safewbc_jax.deploy.codegen import emit

HEADER = "safewbc_step.h"


@dataclasses.dataclass
class Export:
    """What ``export_c`` wrote: the folder, the emitted functions, the example's stored
    motor command and the diagonal of its reduced QP's P (Python's, by XLA)."""

    out: Path
    functions: list
    motor: np.ndarray
    reduced_p_diagonal: np.ndarray


def stand_state() -> tuple[np.ndarray, np.ndarray]:
    """(q, v) of the controller model at the simulator's "stand" keyframe."""
    from safewbc_jax.model import statemap

    _, _, sm, d = statemap.load_stand()
    q, v = sm.to_controller(d.qpos, d.qvel)
    return np.asarray(q, float), np.asarray(v, float)


def step_functions(ctl) -> dict[str, tuple[Any, tuple]]:
    """{C name: (a JAX function of flat vectors, example arguments)} of a started
    ``Controller``: start, init, the whole step, prepare, the acceptance and conclude."""
    import jax.numpy as jnp

    from safewbc_jax.control import step as control_step

    cs, L = ctl.compiled, ctl.compiled.layouts
    ctx, model, sc = cs.ctx, ctl.model, ctl.scenario
    q, v = ctl.start_state

    def start(q):
        data = control_step.start_data(model, sc, q)
        return L.fixed.pack((ctl.params, data, ctl.run_values), jnp)

    def init(q, v):
        state, tally = control_step.init_state(ctx, q, v, jnp, jnp.float64)
        return L.state.pack(state, jnp), L.tally.pack(tally, jnp)

    def step(fixed, state, tally, meas):
        params, data, run = L.fixed.unpack(fixed, jnp)
        st, ta, out = control_step.step_jax(ctx, params, data, run, L.state.unpack(state, jnp),
                                            L.tally.unpack(tally, jnp), L.meas.unpack(meas, jnp))
        return L.state.pack(st, jnp), L.tally.pack(ta, jnp), out.motor, out.u

    fixed = cs.pack_fixed(ctl.params, ctl.start_data, ctl.run_values)
    state, tally = cs.initial(q, v)
    meas = np.zeros(L.meas.size)
    return {"swbc_start": (start, (q,)), "swbc_init": (init, (q, v)),
            "swbc_step": (step, (fixed, state, tally, meas)),
            "swbc_prepare": (cs.prepare_fn, (fixed, state, meas)),
            "swbc_accept": (cs.accept_fn, (np.zeros(cs.qp_size), np.zeros(cs.nr + 3))),
            "swbc_conclude": (cs.conclude_fn, (fixed, tally, np.zeros(L.prep.size),
                                               cs.no_solution))}


def _array(name: str, a) -> str:
    a = np.asarray(a, float).ravel()
    vals = ",\n    ".join(", ".join(emit.c_literal(x, np.float64) for x in a[i:i + 4])
                          for i in range(0, a.size, 4))
    return f"static const double {name}[{max(a.size, 1)}] = {{\n    {vals}\n}};\n"


def export_c(scenario, out, params=None, safe_sets=(), barrier: bool = True,
             speed: float | None = None, settle: float | None = None,
             duration: float | None = None) -> Export:
    """Write the C folder of ``scenario`` (a name, "FILE.py:NAME" or a Scenario) with
    ``params`` (ControllerParams; None: the scenario's defaults) and the user's
    ``safe_sets`` into ``out``. Returns the ``Export``. Raises ``UnsupportedPrimitive``
    naming a primitive the C emitter cannot write (and where it comes from), or
    barriers.PoleError where the poles fail Theorem 1 at the stand."""
    import jax

    from safewbc_jax import scenarios
    from safewbc_jax.control.step import DEFAULT_SPEED
    from safewbc_jax.deploy.controller import Controller

    sc = scenarios.get_scenario(scenario, barrier, tuple(safe_sets))
    ctl = Controller(sc, params, barrier=barrier,
                     speed=DEFAULT_SPEED if speed is None else speed, settle=settle,
                     duration=duration, engine="xla")
    q, v = stand_state()
    ctl.start(q, v, warm_up=False)
    fns = []
    jitted = {}
    for name, (fn, args) in step_functions(ctl).items():
        closed = jax.make_jaxpr(fn)(*args)
        fns.append(emit.emit_function(name, closed))
        jitted[name] = jax.jit(fn)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "safewbc_step.c").write_text(emit.c_file(fns, HEADER))
    cs = ctl.compiled
    assert cs is not None      # started above
    L, m = cs.layouts, ctl.model
    sizes = {"NQ": m.nq, "NV": m.nv, "NU": m.nu, "FIXED": L.fixed.size, "STATE": L.state.size,
             "TALLY": L.tally.size, "MEAS": L.meas.size, "PREP": L.prep.size,
             "SOL": L.sol.size, "QP": cs.qp_size, "SOLVED": cs.nr + 3}
    (out / HEADER).write_text(_header(fns, sizes, sc.name, qp_layout(cs)))
    # the example: one step at the stand, t = 0, the soles carrying half the weight each
    weight = ctl.ctx.weight
    meas = np.concatenate([q, v, [weight / 2, weight / 2], [0.0]])
    fixed = np.asarray(jitted["swbc_start"](q))
    state, tally = (np.asarray(a) for a in jitted["swbc_init"](q, v))
    motor = np.asarray(jitted["swbc_step"](fixed, state, tally, meas)[2])
    red = cs.unpack_qp(np.asarray(jitted["swbc_prepare"](fixed, state, meas)[2]))[1]
    p_diag = np.diag(red.P).copy()
    (out / "main.c").write_text(_main(q, v, meas, motor, p_diag, sizes))
    (out / "Makefile").write_text(MAKEFILE)
    return Export(out, fns, motor, p_diag)


QP_PARTS = ("EQ", "RED", "MAP", "CHECK")
"""The names of ``CompiledStep.unpack_qp``'s four parts in the header's ``SWBC_QP_*``: the
full QP's equality rows, the reduced QP, the map back to X, the acceptance checks."""


def qp_layout(cs) -> str:
    """``#define SWBC_QP_<PART>_<FIELD> offset`` of each array in prepare's qp vector (its
    shape in a comment; row-major), and ``SWBC_NR``, the reduced QP's variable count."""
    import jax

    parts = cs.unpack_qp(np.arange(cs.qp_size, dtype=float))
    lines = [f"#define SWBC_NR {cs.nr}   /* the reduced QP's variables: the torques u */\n"]
    for part, tree in zip(QP_PARTS, parts):
        for path, leaf in jax.tree_util.tree_leaves_with_path(tree):
            a = np.asarray(leaf)
            if a.size == 0:
                continue
            field = jax.tree_util.keystr(path).strip(".").upper()
            shape = " x ".join(map(str, a.shape)) or "1"
            lines.append(f"#define SWBC_QP_{part}_{field} {int(a.flat[0])}   /* {shape} */\n")
    return "".join(lines)


def _header(fns, sizes: dict, scenario: str, layout: str) -> str:
    head = emit.c_header(fns, "SAFEWBC_STEP_H").split("#include <stdint.h>\n", 1)
    macros = "".join(f"#define SWBC_{k}_SIZE {v}\n" if k not in ("NQ", "NV", "NU") else
                     f"#define SWBC_{k} {v}\n" for k, v in sizes.items())
    doc = (f"/* The safewbc-jax controller of scenario {scenario!r}, generated as C99.\n"
           "   The measurement vector: q (SWBC_NQ), v (SWBC_NV), the left and right soles'\n"
           "   normal forces (2, N), t (s). Not reentrant: the functions share static\n"
           "   buffers; call them from one thread. */\n")
    return head[0] + "#include <stdint.h>\n" + doc + macros + layout + head[1]


def _main(q, v, meas, motor, p_diag, sizes: dict) -> str:
    return (f'#include <math.h>\n#include <stdio.h>\n#include "{HEADER}"\n\n'
            + _array("Q", q) + _array("V", v) + _array("MEAS", meas)
            + _array("PYTHON_MOTOR", motor) + _array("PYTHON_RED_P_DIAG", p_diag) + """
/* one control step at a stored state: the stand, t = 0; prints the motor torques and
   their largest difference from Python's (XLA's) for the same step. Then the same step up
   to the QP (swbc_prepare), as for an own QP solver: the diagonal of the reduced QP's
   P (SWBC_NR x SWBC_NR, at SWBC_QP_RED_P in qp) against Python's */
int main(void) {
    static double fixed[SWBC_FIXED_SIZE], state[SWBC_STATE_SIZE], tally[SWBC_TALLY_SIZE];
    static double state1[SWBC_STATE_SIZE], tally1[SWBC_TALLY_SIZE];
    static double motor[SWBC_NU], u[SWBC_NU];
    static double prep[SWBC_PREP_SIZE], qp[SWBC_QP_SIZE];
    double worst = 0.0, worst_p = 0.0;
    swbc_start(Q, fixed);
    swbc_init(Q, V, state, tally);
    swbc_step(fixed, state, tally, MEAS, state1, tally1, motor, u);
    for (int i = 0; i < SWBC_NU; ++i) {
        double d = fabs(motor[i] - PYTHON_MOTOR[i]);
        if (!(d <= worst)) worst = d;
        printf("motor[%d] = %.17g\\n", i, motor[i]);
    }
    printf("largest difference from Python's: %.3g N m\\n", worst);
    swbc_prepare(fixed, state, MEAS, state1, prep, qp);
    for (int i = 0; i < SWBC_NR; ++i) {
        double p = qp[SWBC_QP_RED_P + i * (SWBC_NR + 1)];
        double d = fabs(p - PYTHON_RED_P_DIAG[i]) / fabs(PYTHON_RED_P_DIAG[i]);
        if (!(d <= worst_p)) worst_p = d;
        printf("reduced P[%d][%d] = %.17g\\n", i, i, p);
    }
    printf("largest relative difference from Python's: %.3g\\n", worst_p);
    return worst <= 1e-6 && worst_p <= 1e-9 ? 0 : 1;
}
""")


MAKEFILE = """# Builds the example and runs it: make (or make example; make clean)
CC ?= cc
CFLAGS ?= -O3 -std=c99 -ffp-contract=off -Wall -Wextra
LDLIBS = -lm

run: example
\t./example

example: main.c safewbc_step.c safewbc_step.h
\t$(CC) $(CFLAGS) -o $@ main.c safewbc_step.c $(LDLIBS)

clean:
\trm -f example

.PHONY: run clean
"""
