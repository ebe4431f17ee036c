"""safewbc-jax: safe whole-body task-space control (A-ECBF inverse-dynamics QP) for Digit.

The controller's robot terms and QPs are float64: call ``safewbc_jax.enable_x64()`` once,
before building a model or a controller (the ``safewbc`` command and the examples do).
Importing the package changes no JAX setting; where 64-bit floats are needed and off,
``robot.from_mujoco`` (every path builds its model there) raises an error that says so.
Arrays made with an explicit float32 dtype (the accelerator option of the batched path)
stay float32. ``JAX_ENABLE_X64=1`` in the environment does the same as ``enable_x64()``.

Importing it sets two defaults for the libraries under JAX, each unless the user set it:
one OpenBLAS thread, and XLA:CPU's classic fusion emitters (``CPU_XLA_FLAGS``).
"""

import os

# OpenBLAS (numpy's, and scipy's, which jaxlib's CPU LAPACK kernels call) spins worker
# threads after each call; on a small CPU they compete with XLA's own thread pool. Measured
# on a 2-core machine: closed-loop MJX rollouts with the JAX QP solver ran 70x slower per
# step (71 ms against 1.1 ms at batch 2). The controller's matrices are far too small to
# gain from threaded BLAS, so one thread is the default unless the user set it. (Only
# effective when numpy is not imported yet; ``solvers.jax_qp.blas_threads`` sets it at
# run time.)
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

CPU_XLA_FLAGS = ("--xla_cpu_use_fusion_emitters=false",)
"""XLA:CPU flags this package adds to ``XLA_FLAGS`` on import, each unless ``XLA_FLAGS``
already names it (set it there, to true, to keep XLA's default). With the classic
emitters instead of XLA:CPU's newer MLIR fusion emitters, the closed loop of the batched
path (arms, batch 2) compiled in 38 CPU s instead of 56 and the deployed walking
controller started in 20 s instead of 32; the deployed step ran within 2% of its speed, the
batched loop at 0.82-1.04 of it in noisy runs (benchmarks/README.md, "XLA:CPU's fusion
emitters"). XLA reads ``XLA_FLAGS`` when JAX starts its CPU backend (the first JAX array
or compile), so the setting takes effect where this package is imported before that;
later it changes nothing. Only XLA:CPU reads these flags: a program compiled for an
accelerator is the same."""


def add_xla_flags(flags) -> None:
    """Append ``flags`` ("--name=value" strings) to the environment's ``XLA_FLAGS``, each
    unless ``XLA_FLAGS`` already names it. XLA reads them when JAX starts a backend: call
    this before the process's first JAX array or compile."""
    have = os.environ.get("XLA_FLAGS", "")
    named = {f.split("=", 1)[0].lstrip("-") for f in have.split()}
    extra = [f for f in flags if f.split("=", 1)[0].lstrip("-") not in named]
    if extra:
        os.environ["XLA_FLAGS"] = " ".join([have.strip(), *extra]).strip()


add_xla_flags(CPU_XLA_FLAGS)


def enable_x64() -> None:
    """Switch JAX to 64-bit floats for this process (``jax_enable_x64``), as the
    controller needs. It is JAX's global setting: it affects other JAX code in the
    process too, which is why importing the package does not do it."""
    import jax

    jax.config.update("jax_enable_x64", True)


def require_x64(what: str) -> None:
    """RuntimeError unless JAX's 64-bit floats are on, naming ``what`` needs them."""
    import jax

    if not jax.config.jax_enable_x64:  # type: ignore[attr-defined]
        raise RuntimeError(f"{what} needs JAX's 64-bit floats: call safewbc_jax.enable_x64() "
                           "first (or set JAX_ENABLE_X64=1)")


def use_cpu() -> None:
    """Run this process's JAX on the CPU (``jax_platforms = "cpu"``), whatever accelerator
    and JAX plugin the machine has: the single robot's step (``safewbc run``, a deployed
    controller) and the mujoco engine's sweep workers are CPU programs, and a CUDA backend
    would also take most of a GPU's memory in each of those processes. JAX reads it when it
    starts a backend: call this before the process's first JAX array or compile. A process
    whose backend is already up on another platform raises RuntimeError."""
    import jax
    from jax._src import xla_bridge

    if xla_bridge.backends_are_initialized():
        if jax.default_backend() != "cpu":
            raise RuntimeError("use_cpu(): JAX already runs on "
                               f"{jax.default_backend()!r} in this process; call it before "
                               "the first JAX array or compile")
        return
    jax.config.update("jax_platforms", "cpu")


def use_compile_cache(directory: str) -> None:
    """Keep this process's compiled XLA programs in ``directory`` (JAX's persistent
    compilation cache) and load them from there in later processes: every program, the
    small eager ones too (``jax_persistent_cache_min_compile_time_secs`` = 0). Those are a
    few hundred of about 20 ms each when a controller starts; compiled again, they cost a
    warm ``safewbc run arms`` 16 s where loading them costs 9 s (benchmarks/README.md)."""
    import jax

    jax.config.update("jax_compilation_cache_dir", directory)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
