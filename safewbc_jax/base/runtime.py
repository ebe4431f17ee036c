"""The process's runtime settings for the package: JAX's 64-bit floats, the CPU platform,
the persistent compilation cache, and two defaults set on import for the libraries under
JAX (one OpenBLAS thread, XLA:CPU's classic fusion emitters). ``safewbc_jax`` re-exports
every public name of this module."""

from __future__ import annotations

import os
from collections.abc import Iterable

# OpenBLAS (numpy's, and scipy's, which jaxlib's CPU LAPACK kernels call) spins worker
# threads after each call; on a small CPU they compete with XLA's own thread pool, and the
# closed-loop MJX rollouts with the JAX QP solver ran 70 times slower per step
# (benchmarks/README.md, "Figures behind design choices"). The controller's matrices are far
# too small to gain from threaded BLAS, so one thread is the default unless the user set it.
# (Only effective when numpy is not imported yet; ``solvers.jax_qp.blas_threads`` sets it at
# run time.)
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

CPU_XLA_FLAGS = ("--xla_cpu_use_fusion_emitters=false",)
"""XLA:CPU flags this package adds to ``XLA_FLAGS`` on import, each unless ``XLA_FLAGS``
already names it (set it there, to true, to keep XLA's default). With the classic emitters
instead of XLA:CPU's newer MLIR fusion emitters, the closed loop of the batched path and the
deployed controller compile about a third faster, at about the same speed
(benchmarks/README.md, "XLA:CPU's fusion emitters"). XLA reads ``XLA_FLAGS`` when JAX starts
its CPU backend (the first JAX array or compile), so the setting takes effect where this
package is imported before that; later it changes nothing. Only XLA:CPU reads these flags: a
program compiled for an
accelerator is the same."""


def add_xla_flags(flags: Iterable[str]) -> None:
    """Append flags to the environment's ``XLA_FLAGS``, each unless ``XLA_FLAGS`` already
    names it.

    XLA reads them when JAX starts a backend: call this before the process's first JAX
    array or compile.

    Args:
        flags: "--name=value" strings. A flag whose name ``XLA_FLAGS`` already holds,
            whatever its value there, is left out.
    """
    have = os.environ.get("XLA_FLAGS", "")
    named = {f.split("=", 1)[0].lstrip("-") for f in have.split()}
    extra = [f for f in flags if f.split("=", 1)[0].lstrip("-") not in named]
    if extra:
        os.environ["XLA_FLAGS"] = " ".join([have.strip(), *extra]).strip()


add_xla_flags(CPU_XLA_FLAGS)


def enable_x64() -> None:
    """Switch JAX to 64-bit floats for this process (``jax_enable_x64``), as the
    controller needs.

    It is JAX's global setting: it affects other JAX code in the process too, which is
    why importing the package does not do it.
    """
    import jax

    jax.config.update("jax_enable_x64", True)


def require_x64(what: str) -> None:
    """Check that JAX's 64-bit floats are on.

    Args:
        what: what needs them, for the error message (e.g. "the controller model").

    Raises:
        RuntimeError: JAX's 64-bit floats are off; the message names ``what`` and how to
            turn them on (``enable_x64``).
    """
    import jax

    if not jax.config.jax_enable_x64:  # type: ignore[attr-defined]
        raise RuntimeError(f"{what} needs JAX's 64-bit floats: call safewbc_jax.enable_x64() "
                           "first (or set JAX_ENABLE_X64=1)")


def use_cpu() -> None:
    """Run this process's JAX on the CPU (``jax_platforms = "cpu"``), whatever accelerator
    and JAX plugin the machine has.

    In a CPU program a CUDA backend would still take most of a GPU's memory in each
    process. JAX reads the setting when it starts a
    backend: call this before the process's first JAX array or compile. Where the backend
    is already up on the CPU, it does nothing.

    Raises:
        RuntimeError: JAX already runs on another platform in this process.
    """
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
    """Keep this process's compiled XLA programs in JAX's persistent compilation cache and
    load them from there in later processes.

    Every program is kept, the small eager ones too
    (``jax_persistent_cache_min_compile_time_secs`` = 0): a few hundred of them when a
    controller starts, cheaper loaded than compiled again (benchmarks/README.md, "A warm
    start: the compilation cache").

    Args:
        directory: the cache's directory (``jax_compilation_cache_dir``).
    """
    import jax

    jax.config.update("jax_compilation_cache_dir", directory)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
