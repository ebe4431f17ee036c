"""Time several calls side by side in one process, in alternating rounds.

On a shared, noisy machine a figure is only worth its comparison with another taken in
the same minutes. So each round times every call in turn, and the order reverses from one
round to the next. Each call is warmed up, then timed ``calls`` times, and the round keeps
the median. Used by ``iree_step.py`` and ``step_parts.py``.
"""

from __future__ import annotations

import resource
import time

import numpy as np

WARM_UP = 20


def alternating_p50(fns: dict, rounds: int, calls: int, gap_s: float = 0.0):
    """({name: [p50 µs of each round]}, {name: [voluntary, involuntary] context switches
    per call}) of the zero-argument callables ``fns``, each called ``calls`` times per
    round, with a busy wait of ``gap_s`` s after each call (outside the timing)."""
    p50 = {k: [] for k in fns}
    switches = {k: [0, 0] for k in fns}
    names = list(fns)
    for r in range(rounds):
        for name in (names if r % 2 == 0 else names[::-1]):
            f = fns[name]
            for _ in range(WARM_UP):
                f()
            ts = []
            r0 = resource.getrusage(resource.RUSAGE_SELF)
            for _ in range(calls):
                t0 = time.perf_counter()
                f()
                t1 = time.perf_counter()
                ts.append(t1 - t0)
                while gap_s and time.perf_counter() - t1 < gap_s:
                    pass
            r1 = resource.getrusage(resource.RUSAGE_SELF)
            switches[name][0] += r1.ru_nvcsw - r0.ru_nvcsw
            switches[name][1] += r1.ru_nivcsw - r0.ru_nivcsw
            p50[name].append(float(np.median(ts)) * 1e6)
    n = rounds * calls
    return p50, {k: [round(a / n, 2), round(b / n, 2)] for k, (a, b) in switches.items()}
