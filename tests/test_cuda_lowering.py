"""The batched closed loop as a GPU would run it, lowered for CUDA on this CPU machine.

``rollout.export(cfg, 1024, ("cuda",))`` lowers the function ``run_batch`` compiles with
``jax.export`` for CUDA: no GPU is needed and nothing compiles. Its StableHLO is the GPU
program: every cuSOLVER call (Cholesky, LU and the LU's pivots) must take the whole batch
of 1,024 in one call, every triangular solve too, and no CPU-only call (jaxlib's LAPACK
kernels, a host callback) may appear. Before the sub-batching of
``solvers/lapack_batched.py`` and the chunking were chosen by the platform lowered for,
this lowering showed ``cusolver_potrf_ffi`` on batches of 4, 12 and 75 and
``cusolver_getrf_ffi`` on batches of 18: each factorisation serialised into tens of calls.

The CPU lowering of the same function keeps its sub-batches (the deadlock guard of
``tests/test_lapack_batched.py``): the choice is the platform's, not the machine's.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from safewbc_jax.sim.mjx import rollout as R

pytestmark = pytest.mark.slow      # traces the MJX closed loop (~10-20 s a scenario)

BATCH = 1024
USER_SET = str(Path(__file__).resolve().parents[1] / "examples/bow_torso_lean.py:TORSO_LEAN")
# one program of each shape of the batched scenarios: no barrier (squat), one barrier
# row (bow with a user's safe set added) and walking. Left out: "push" is the walk's program
# (walking.make_scenario differs in the name and the default duration only, and the
# duration is a run-time value); "arms" is the standing QP with one barrier row too, of the
# same sizes as bow's with the user's safe set (the fist's output in place of the pitch),
# and bow alone is squat's QP
CASES = [("squat", ()), ("bow", (USER_SET,)), ("walk", ())]
assert {s for s, _ in CASES} | {"arms", "push"} == set(R.BATCHED_SCENARIOS)


def custom_calls(mlir: str):
    """(target, shape of the first operand) of each custom call of a StableHLO module."""
    out = []
    for m in re.finditer(r"custom_call @([\w.]+)\(([^)]*)\)[^\n]*?:\s*\(([^)]*)\)", mlir):
        shapes = re.findall(r"tensor<((?:\d+x)*)[a-z]+\d+>", m.group(3))
        shape = tuple(int(d) for d in shapes[0].split("x") if d) if shapes else ()
        out.append((m.group(1), shape))
    return out


def triangular_solves(mlir: str):
    """Operand shapes of each ``stablehlo.triangular_solve`` (the GPU's own op)."""
    out = []
    for line in mlir.splitlines():
        if "stablehlo.triangular_solve" in line:
            m = re.search(r":\s*\(tensor<((?:\d+x)+)", line)
            out.append(tuple(int(d) for d in m.group(1).split("x") if d))
    return out


def test_parser_reads_a_known_module():
    """The parsers on a module written here: a batched Cholesky and triangular solve."""
    import jax
    import jax.numpy as jnp
    import jax.scipy.linalg as jsl

    f = jax.jit(jax.vmap(lambda a, b: jsl.cho_solve((jnp.linalg.cholesky(a), True), b)))
    shape = jax.ShapeDtypeStruct((7, 5, 5), jnp.float64), jax.ShapeDtypeStruct((7, 5), jnp.float64)
    mlir = jax.export.export(f, platforms=["cuda"])(*shape).mlir_module()
    calls = custom_calls(mlir)
    assert ("cusolver_potrf_ffi", (7, 5, 5)) in calls
    assert triangular_solves(mlir) and all(s[0] == 7 for s in triangular_solves(mlir))


@pytest.mark.parametrize("scenario,safe_sets", CASES,
                         ids=[s + ("+user_safe_set" if u else "") for s, u in CASES])
def test_every_solver_call_takes_the_whole_batch(scenario, safe_sets):
    cfg = R.BatchConfig(scenario, safe_sets=safe_sets)
    mlir = R.export(cfg, BATCH, ("cuda",)).mlir_module()
    calls = custom_calls(mlir)
    targets = {t for t, _ in calls}
    assert {"cusolver_potrf_ffi", "cusolver_getrf_ffi"} <= targets, targets
    cpu_only = {t for t in targets if t.startswith("lapack_") or "callback" in t
                or not t.startswith(("cusolver_", "cublas_", "cu_"))}
    assert not cpu_only, f"calls that are not CUDA's: {sorted(cpu_only)}"
    assert "callback" not in mlir
    partial = sorted({(t, s) for t, s in calls if not s or s[0] != BATCH})
    assert not partial, f"calls on less than the batch of {BATCH}: {partial}"
    tri = triangular_solves(mlir)
    assert all(s[0] == BATCH for s in tri), sorted(set(tri))


def test_the_cpu_lowering_keeps_its_sub_batches():
    """The same function lowered for the CPU: jaxlib's LAPACK kernels on at most the
    64-rollout chunk, the mass matrix's Cholesky on sub-batches of it (the thread-pool
    guard), never on the whole batch."""
    cfg = R.BatchConfig("walk")
    mlir = R.export(cfg, BATCH, ("cpu",)).mlir_module()
    calls = [(t, s) for t, s in custom_calls(mlir) if t.startswith("lapack_")]
    assert {"lapack_dpotrf_ffi", "lapack_dgetrf_ffi"} <= {t for t, _ in calls}
    nv_sim = R.plant(cfg).nv_sim       # MJX's own Cholesky, on the whole chunk
    controller = [s for t, s in calls if not (t == "lapack_dpotrf_ffi" and s[-1] == nv_sim)]
    assert controller and all(s[0] <= R.CPU_CHUNK for s in controller), controller
    elimination = [s[0] for s in controller if s[-2:] == (36, 36)]      # M's Cholesky
    assert elimination and max(elimination) < R.CPU_CHUNK, controller
    assert not any(t.startswith("cusolver") for t, _ in custom_calls(mlir))


def float32_products(mlir: str):
    """(precision attribute or "", line) of each float32 ``dot_general`` or convolution of
    a StableHLO module."""
    out = []
    for line in mlir.splitlines():
        if ("stablehlo.dot_general" in line or "stablehlo.convolution" in line) and \
                re.search(r":\s*\(tensor<[\dx]*f32>", line):
            m = re.search(r"precision = \[([A-Z_, ]+)\]", line)
            out.append((m.group(1) if m else "", line.strip()[:160]))
    return out


def test_mixed_loop_runs_its_float32_products_at_full_precision():
    """The mixed mode's float32 stages (MJX's physics, the interior point) lowered for
    CUDA: every float32 product carries HIGHEST precision, so an Ampere or newer GPU does
    not run it in TF32 (JAX's default there)."""
    mlir = R.export(R.BatchConfig("squat", precision="mixed"), 8, ("cuda",)).mlir_module()
    products = float32_products(mlir)
    assert len(products) > 10, "the parser finds no float32 product in the mixed loop"
    loose = [line for prec, line in products if prec != "HIGHEST, HIGHEST"]
    assert not loose, f"{len(loose)} of {len(products)} float32 products below HIGHEST: {loose[:3]}"
