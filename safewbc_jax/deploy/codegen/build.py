"""Build emitted C with the system compiler and call it on numpy arrays.

    path, _ = build(source_text)             # a shared library, cached by the source's hash
    fn = CCall(load(path), cfunction)        # fn(*inputs) -> outputs (numpy)

The build is cached in ``cache_dir()`` (``$SAFEWBC_C_CACHE``, else
``~/.cache/safewbc-jax/c``) under the SHA-256 of the source, the compiler and its flags, so a
second start loads the library without compiling.

Flags: ``CFLAGS``, the optimisation flags (``opt_flags``: with gcc, ``-O2`` with the loop
vectoriser and complete peeling of short loops, which gives the generated step at least
``-O3``'s speed from half its machine code and half its compile time; ``-O3`` with other
compilers) and, on x86-64, the highest microarchitecture level of the x86-64 psABI
(``-march=x86-64-v2``, or ``-v3`` without FMA) that this CPU has and the compiler takes
(``isa_flags``): wider vectors (AVX2) for the generated loops. Floating-point contraction
is off (``-ffp-contract=off``, which ISO C mode also implies for gcc but not for clang; and
no FMA instructions at all), and the generated C has no reductions the compiler may
reorder, so every level computes the same bits as the baseline build
(``tests/test_codegen.py``; ``tests/test_export_c.py`` finds no fused multiply-add in a
step's library); a cache shared by machines of different levels holds one library per
level.
"""

from __future__ import annotations

import ctypes
import functools
import hashlib
import math
import os
import platform
import shutil
import subprocess
import tempfile
from pathlib import Path

import numpy as np

from safewbc_jax.deploy.codegen.emit import CFunction

CFLAGS = ("-std=c99", "-fPIC", "-fno-math-errno", "-ffp-contract=off")
# What gcc's -O3 adds beyond these doubles the generated step's machine code and its
# compile time and makes it no faster (benchmarks/README.md, "The C step's optimisation
# flags"). No optimisation level changes a result here: none reassociates or contracts.
OPT_GCC = ("-O2", "-ftree-vectorize", "-fvect-cost-model=dynamic", "-fpeel-loops")
OPT_OTHER = ("-O3",)
MAX_UNITS = 8
MAX_OUT_SETS = 64     # output sets whose addresses a CCall keeps (one per lane of a lockstep)
_CTYPES = {"double": ctypes.c_double, "float": ctypes.c_float, "int32_t": ctypes.c_int32,
           "int64_t": ctypes.c_int64, "uint8_t": ctypes.c_uint8, "uint32_t": ctypes.c_uint32}


def compiler() -> str | None:
    """The system C compiler (``$CC``, else cc, gcc or clang on the PATH), or None."""
    for cand in (os.environ.get("CC"), "cc", "gcc", "clang"):
        if cand and shutil.which(cand):
            return cand
    return None


@functools.lru_cache(maxsize=1)
def works() -> bool:
    """Whether ``compiler()`` exists and builds a shared library with ``CFLAGS`` (a tiny
    one, once per process): a toolchain without its C library or linker fails here, not
    at the first generated step."""
    cc = compiler()
    return cc is not None and _builds(cc, (*CFLAGS, *_opt_flags(cc)))


def opt_flags() -> tuple[str, ...]:
    """The optimisation flags of a build: ``OPT_GCC`` where the compiler is gcc and takes
    them, else ``OPT_OTHER`` (clang, other compilers)."""
    cc = compiler()
    return OPT_OTHER if cc is None else _opt_flags(cc)


@functools.lru_cache(maxsize=4)
def _opt_flags(cc: str) -> tuple[str, ...]:
    macros = _macros(cc, ())
    gcc = "__GNUC__" in macros and "__clang__" not in macros
    return OPT_GCC if gcc and _builds(cc, (*CFLAGS, *OPT_GCC)) else OPT_OTHER


@functools.lru_cache(maxsize=8)
def _macros(cc: str, flags: tuple) -> frozenset:
    """The names of the macros ``cc`` predefines with ``flags`` (empty where it fails)."""
    r = subprocess.run([cc, *flags, "-dM", "-E", "-x", "c", os.devnull],
                       capture_output=True, text=True)
    if r.returncode != 0:
        return frozenset()
    return frozenset(ln.split()[1] for ln in r.stdout.splitlines() if ln.startswith("#define "))


# The compiler's macros for -march=native that each x86-64 psABI level requires (its
# features as gcc and clang name them), and the flags it is built with. v3 is built without
# FMA: gcc 12 forms fused multiply-adds in vectorised loops of the generated step despite
# -ffp-contract=off, which changes last bits. v4 (AVX-512) is left out: AVX-512F has fused
# multiply-adds of its own, which -mno-fma does not remove (benchmarks/README.md).
_LEVELS = (
    ("x86-64-v3", ("__AVX__", "__AVX2__", "__BMI__", "__BMI2__", "__F16C__", "__FMA__",
                   "__LZCNT__", "__MOVBE__"), ("-march=x86-64-v3", "-mno-fma")),
    ("x86-64-v2", ("__SSE3__", "__SSSE3__", "__SSE4_1__", "__SSE4_2__", "__POPCNT__"),
     ("-march=x86-64-v2",)),
)


def isa_level(macros) -> str | None:
    """The highest x86-64 level whose features are all among ``macros`` (the names the
    compiler defines), each level including the ones below it; None below v2."""
    have = set(macros)
    best = None
    for name, need, _ in reversed(_LEVELS):
        if not have.issuperset(need):
            break
        best = name
    return best


def isa_flags() -> tuple[str, ...]:
    """The flags of the highest level this CPU has (as ``-march=native`` shows it to the
    compiler) that the compiler also builds with (``("-march=x86-64-v3", "-mno-fma")``,
    say); () on other machines, without a compiler, or where the compiler knows no level
    names (gcc < 11)."""
    cc = compiler()
    return () if cc is None else _isa_flags(cc)


@functools.lru_cache(maxsize=4)
def _isa_flags(cc: str) -> tuple[str, ...]:
    if platform.machine().lower() not in ("x86_64", "amd64"):
        return ()
    level = isa_level(_macros(cc, ("-march=native",)))
    names = [name for name, _, _ in _LEVELS]
    for _, _, flags in (_LEVELS[names.index(level):] if level else ()):
        if _builds(cc, (*CFLAGS, *flags)):
            return flags
    return ()


@functools.lru_cache(maxsize=16)
def _builds(cc: str, flags: tuple) -> bool:
    """Whether ``cc`` with ``flags`` builds a tiny shared library (once per process)."""
    with tempfile.TemporaryDirectory() as tmp:
        src = Path(tmp) / "probe.c"
        src.write_text("#include <math.h>\ndouble swbc_probe(double x) { return sqrt(x); }\n")
        r = subprocess.run([cc, *flags, "-shared", "-o", str(Path(tmp) / "probe.so"),
                            str(src), "-lm"], capture_output=True, text=True)
    return r.returncode == 0


def cache_dir() -> Path:
    env = os.environ.get("SAFEWBC_C_CACHE")
    return Path(env) if env else Path.home() / ".cache" / "safewbc-jax" / "c"


def build(source: str, native: bool = False, isa: bool = True,
          opt: tuple[str, ...] | None = None) -> tuple[Path, bool]:
    """The shared library of ``source``: built with ``CFLAGS``, ``opt`` (default
    ``opt_flags()``) and ``-march=native`` where ``native``, else ``isa_flags()`` where
    ``isa``. Returns (its path, whether it was compiled now rather than found in the
    cache). Raises RuntimeError with the compiler's message where the build fails, or
    where there is no C compiler."""
    cc = compiler()
    if cc is None:
        raise RuntimeError("no C compiler found (set CC, or install cc, gcc or clang)")
    flags = [*CFLAGS, *(_opt_flags(cc) if opt is None else opt),
             *(["-march=native"] if native else _isa_flags(cc) if isa else ())]
    key = hashlib.sha256("\0".join([source, cc, *flags]).encode()).hexdigest()[:24]
    out = cache_dir() / f"step_{key}.so"
    if out.exists():
        return out, False
    out.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        src = Path(tmp) / "step.c"
        src.write_text(source)
        so = Path(tmp) / "step.so"
        _compile(cc, flags, src, so, units())
        part = out.with_suffix(f".{os.getpid()}.part")
        shutil.copyfile(so, part)
        os.replace(part, out)          # atomic: a concurrent start sees all or nothing
    return out, True


def units() -> int:
    """How many translation units a build compiles in parallel: one per CPU this process
    may run on, at most ``MAX_UNITS``."""
    try:
        n = len(os.sched_getaffinity(0))
    except AttributeError:             # not on Linux
        n = os.cpu_count() or 1
    return max(1, min(n, MAX_UNITS))


def _compile(cc: str, flags: list, src: Path, so: Path, n: int) -> None:
    """``src`` as ``n`` translation units compiled at once (``emit.UNITS``), linked into
    the shared library ``so``; RuntimeError with the compiler's message on a failure."""
    objs = [src.with_name(f"unit{k}.o") for k in range(n)]
    # several units share their buffers as hidden globals: direct addressing, as the
    # static ones of one unit have (through the GOT they cost compile time and speed)
    unit = ([f"-DSWBC_UNITS={n}", f"-DSWBC_UNIT={k}", "-fvisibility=hidden"] if n > 1 else []
            for k in range(n))
    procs = [subprocess.Popen([cc, *flags, *u, "-c", "-o", str(o), str(src)],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for u, o in zip(unit, objs)]
    errs = [p.communicate()[1] for p in procs]
    if any(p.returncode for p in procs):
        err = next(e for p, e in zip(procs, errs) if p.returncode)
        raise RuntimeError(f"{cc} failed on the generated step:\n{err[-4000:]}")
    r = subprocess.run([cc, *flags, "-shared", "-o", str(so), *map(str, objs), "-lm"],
                       capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"{cc} failed to link the generated step:\n{r.stderr[-4000:]}")


class CCall:
    """One emitted function of a built library, called on numpy arrays: the inputs are
    converted to the jaxpr's dtypes (C-contiguous), the outputs are preallocated once and
    returned as fresh copies (``copy=False``: the same arrays each call)."""

    def __init__(self, lib: ctypes.CDLL, fn: CFunction, copy: bool = True):
        self.fn = fn
        self.c = getattr(lib, fn.name)
        self.c.restype = None
        # plain addresses (ints) in, as void pointers: no ctypes object per argument
        self.c.argtypes = [ctypes.c_void_p] * (len(fn.in_avals) + len(fn.out_avals))
        self.in_dtypes = [np.dtype(a.dtype) for a in fn.in_avals]
        self.in_shapes = [tuple(a.shape) for a in fn.in_avals]
        self.in_sizes = [math.prod(s) for s in self.in_shapes]
        self.outs = [np.zeros(a.shape, a.dtype) for a in fn.out_avals]
        self.out_ptrs = [o.ctypes.data for o in self.outs]
        self._out_sets: dict = {}
        # per input position, the last array passed there as is and its address: a step's
        # fixed vector, state and output views come back call after call, and numpy's
        # address lookup costs about a microsecond (the array is kept alive, so its id and
        # its data stay its own)
        self._last_in: list = [(None, 0)] * len(fn.in_avals)
        self.copy = copy

    def _addresses(self, out: tuple) -> list:
        """The addresses of an output set, checked and kept at its first use (the set is
        kept alive with them, so its id stays its own)."""
        got = self._out_sets.get(id(out))
        if got is None:
            for o, want in zip(out, self.outs):
                if o.size != want.size or o.dtype != want.dtype or not o.flags.c_contiguous:
                    raise ValueError(f"{self.fn.name}: an output array of shape {o.shape} "
                                     f"and dtype {o.dtype}, expected {want.shape} {want.dtype}")
            if len(self._out_sets) >= MAX_OUT_SETS:  # a caller making new sets: keep no old
                self._out_sets.clear()
            got = self._out_sets[id(out)] = (out, [o.ctypes.data for o in out])
        return got[1]

    def outputs(self) -> tuple:
        """A fresh set of output arrays, for ``__call__``'s ``out``."""
        return tuple(np.zeros(a.shape, a.dtype) for a in self.fn.out_avals)

    def __call__(self, *args, out: tuple | None = None):
        """The function on ``args``; ``out``: arrays of ``outputs``'s shapes to write the
        results into (and return), instead of the preallocated ones. An output array may
        be one of the inputs (the C function allows it)."""
        last = self._last_in
        if len(args) != len(last):
            raise ValueError(f"{self.fn.name}: {len(args)} inputs, expected {len(last)}")
        ptrs, keep = [], []
        for k, a in enumerate(args):
            if a is last[k][0]:
                ptrs.append(last[k][1])
                continue
            b = np.ascontiguousarray(a, dtype=self.in_dtypes[k])
            if b.size != self.in_sizes[k]:
                raise ValueError(f"{self.fn.name}: an input of shape {b.shape}, expected "
                                 f"{self.in_shapes[k]}")
            ptrs.append(b.ctypes.data)
            if b is a:
                last[k] = (a, ptrs[-1])
            else:
                keep.append(b)          # a converted copy: alive until the call returns
        if out is not None:
            self.c(*ptrs, *self._addresses(out))
            return out
        self.c(*ptrs, *self.out_ptrs)
        return tuple(o.copy() for o in self.outs) if self.copy else tuple(self.outs)


def load(path: Path) -> ctypes.CDLL:
    return ctypes.CDLL(str(path))
