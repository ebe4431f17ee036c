"""OpenBLAS thread control for the solvers' host-side LAPACK (``blas_threads``)."""

from __future__ import annotations

import contextlib

_OPENBLAS_API = (("scipy_openblas_get_num_threads", "scipy_openblas_set_num_threads"),
                 ("scipy_openblas_get_num_threads64_", "scipy_openblas_set_num_threads64_"),
                 ("openblas_get_num_threads", "openblas_set_num_threads"),
                 ("openblas_get_num_threads64_", "openblas_set_num_threads64_"))


def _openblas_handles():
    """(get, set) functions of every OpenBLAS library loaded in this process (Linux)."""
    import ctypes

    try:
        with open("/proc/self/maps") as f:
            paths = {line.split()[-1] for line in f if "openblas" in line.lower()
                     and ".so" in line}
    except OSError:
        return []
    out = []
    for path in sorted(paths):
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for get, set_ in _OPENBLAS_API:
            if hasattr(lib, get) and hasattr(lib, set_):
                out.append((getattr(lib, get), getattr(lib, set_)))
                break
    return out


@contextlib.contextmanager
def blas_threads(n: int = 1):
    """Limit every loaded OpenBLAS (scipy's, which jaxlib's CPU LAPACK kernels call, and
    numpy's) to ``n`` threads inside the block; the previous counts are restored after.

    Why: on a small CPU, OpenBLAS worker threads left spinning after a LAPACK call compete
    with XLA's thread pool, and a batch of controller QPs ran about 80 times slower
    (benchmarks/README.md, "Figures behind design choices"). Setting OPENBLAS_NUM_THREADS=1
    before numpy is imported does the same for a whole process. A no-op where no OpenBLAS
    is found."""
    handles = _openblas_handles()
    old = [get() for get, _ in handles]
    for _, set_ in handles:
        set_(int(n))
    try:
        yield len(handles)
    finally:
        for (_, set_), k in zip(handles, old):
            set_(int(k))


__all__ = ["blas_threads"]
