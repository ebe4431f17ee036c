"""How many kernels XLA:CPU runs for one call of a jitted function, and what XLA's cost
analysis says it computes.

On the CPU, XLA's thunk runtime pays a fixed cost for every operation of the compiled
program's entry computation that does work (a fusion, a dot, a custom call such as a
LAPACK factorisation, a copy, a while loop...), whatever its size: for the small
programs of one control step this cost, not the arithmetic, sets the latency. ``count``
reads the optimised HLO of the compiled program and counts those operations; operations
that only name or reshape data (parameters, constants, tuples and their elements,
bitcasts) are left out.
"""

from __future__ import annotations

import re

FREE = frozenset({"parameter", "constant", "get-tuple-element", "tuple", "bitcast"})
_OP = re.compile(r"=\s*\S+\s+([a-z][\w-]*)\(")


def count_text(hlo: str) -> dict:
    """{kind: count} of the working operations of the ENTRY computation of an HLO module
    text, with "total" their sum."""
    start = hlo.find("\nENTRY")
    if start < 0:
        raise ValueError("no ENTRY computation in the HLO text")
    body = hlo[start:hlo.find("\n}", start)]
    kinds: dict = {}
    for line in body.splitlines()[1:]:
        m = _OP.search(line)
        if m and m.group(1) not in FREE:
            kinds[m.group(1)] = kinds.get(m.group(1), 0) + 1
    kinds = dict(sorted(kinds.items(), key=lambda kv: -kv[1]))
    kinds["total"] = sum(kinds.values())
    return kinds


def count(fn, *args) -> dict:
    """``count_text`` of ``jax.jit(fn)`` compiled for ``args`` (``fn`` may be jitted
    already; it is lowered and compiled again, which the persistent compilation cache
    makes cheap where it is on)."""
    import jax

    jitted = fn if hasattr(fn, "lower") else jax.jit(fn)
    return count_text(jitted.lower(*args).compile().as_text() or "")


def cost(fn, *args) -> dict:
    """What one call of ``jax.jit(fn)`` at ``args`` costs by XLA's own analysis of the
    compiled program: {"flops", "bytes" (bytes accessed by its operations), "kernels"
    (``count_text``'s total)}. Deterministic for a jaxlib version and a backend. XLA
    counts a custom call (a LAPACK factorisation or triangular solve on the CPU) as no
    flops: its work is not in "flops"."""
    import jax

    jitted = fn if hasattr(fn, "lower") else jax.jit(fn)
    compiled = jitted.lower(*args).compile()
    analysis = compiled.cost_analysis() or {}
    if isinstance(analysis, (list, tuple)):     # older jaxlibs: one dict per program
        analysis = analysis[0]
    return {"flops": float(analysis.get("flops", 0.0)),
            "bytes": float(analysis.get("bytes accessed", 0.0)),
            "kernels": count_text(compiled.as_text() or "")["total"]}
