"""Where the generated C step's time goes: the deployed ``prepare`` of a scenario, as the C
engine writes it, cut into part functions of about ``--lines`` lines each, with a
time-stamp counter read around every part. It prints each part's cycles per call with
its code and data warm, and after a write of 8 MB of other data before each call (about
what MuJoCo's step and TSID's leave behind in ``controller_step.py``'s loop), the
largest parts first, with what they compute (their runtime routines and products).

    python benchmarks/c_profile.py [--scenario squat] [--lines 25] [--top 12]
        [--calls 400] [--json]

x86-64 only (``__rdtsc``); the counter ticks at the CPU's base clock. Pin the process to
one idle core (``taskset -c 0``). The instrumented build is the engine's source with the
counters added, built as the engine builds it (``build.build``: ``opt_flags`` and the CPU's
x86-64 level, cached by its own source's hash).
"""

from __future__ import annotations

import argparse
import ctypes
import json
import re

PART = re.compile(r"SWBC_PART void swbc_prepare_part(\d+)\(void\) \{\n(.*?)\n\}\n#endif",
                  re.S)


def instrumented(source: str) -> tuple[str, int]:
    """The source with a counter around each call of a prepare part (their number). The
    counters are defined with prepare's entry point, in the one unit that has it, and
    visible outside the library."""
    calls = re.findall(r"    (swbc_prepare_part(\d+))\(\);", source)
    source = source.replace("#if SWBC_MAIN", "#include <x86intrin.h>\n#if SWBC_MAIN\n"
                            '__attribute__((visibility("default"))) '
                            f"uint64_t swbc_prof[{len(calls)}];", 1)
    for name, k in calls:
        source = source.replace(f"    {name}();", f"    {{ uint64_t t0_ = __rdtsc(); {name}(); "
                                f"swbc_prof[{k}] += __rdtsc() - t0_; }}", 1)
    return source, len(calls)


def summary(body: str) -> str:
    """What a part computes, in a few words: its runtime calls and its products' sizes."""
    calls = re.findall(r"swbc_(cholesky|lu|trisolve)\(", body)
    loops = body.count("for (")
    words = [f"{calls.count(c)} {c}" for c in ("cholesky", "lu", "trisolve") if c in calls]
    return ", ".join(words + [f"{loops} loops"])


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenario", default="squat")
    ap.add_argument("--lines", type=int, default=25, help="lines of C per part")
    ap.add_argument("--top", type=int, default=12)
    ap.add_argument("--calls", type=int, default=400)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)

    import numpy as np

    import safewbc_jax
    from safewbc_jax.control.step import Measurement
    from safewbc_jax.deploy.codegen import build, emit
    from safewbc_jax.deploy.codegen.export import stand_state
    from safewbc_jax.deploy.controller import Controller

    safewbc_jax.enable_x64()
    emit.PART_LINES = args.lines
    q, v = stand_state()
    ctl = Controller(args.scenario, engine="c")
    ctl.start(q, v, warm_up=False)
    cs = ctl.compiled
    source, n = instrumented(cs.c_source)
    lib = build.load(build.build(source)[0])
    prepare = build.CCall(lib, cs.prepare.fn)
    prof = (ctypes.c_uint64 * n).in_dll(lib, "swbc_prof")
    fixed = cs.pack_fixed(ctl.params, ctl.start_data, ctl.run_values)
    state = np.asarray(cs.layouts.state.pack(ctl.state))
    meas = cs.flat_measurement(Measurement(q, v, 0.3, np.zeros(2)))
    other = np.zeros(1 << 20)                  # 8 MB
    cycles = {}
    for mode in ("warm", "after 8 MB"):
        for _ in range(100):
            prepare(fixed, state, meas)
        for k in range(n):
            prof[k] = 0
        for _ in range(args.calls):
            if mode != "warm":
                other += 1.0
            prepare(fixed, state, meas)
        cycles[mode] = np.array([prof[k] for k in range(n)], float) / args.calls
    bodies = dict(PART.findall(source))
    order = np.argsort(-cycles["after 8 MB"])[:args.top]
    out = {"scenario": args.scenario, "parts": n,
           "total_cycles": {m: int(c.sum()) for m, c in cycles.items()},
           "top": [{"part": int(k), **{m: int(c[k]) for m, c in cycles.items()},
                    "what": summary(bodies.get(str(k), ""))} for k in order]}
    if args.json:
        print(json.dumps(out))
        return out
    tot = out["total_cycles"]
    print(f"{args.scenario}: {n} parts; cycles per call warm {tot['warm']:,}, after an 8 MB "
          f"write {tot['after 8 MB']:,}")
    for r in out["top"]:
        print(f"  part {r['part']:4d}: warm {r['warm']:8,}  after 8 MB {r['after 8 MB']:8,}"
              f"  ({r['what']})")
    return out


if __name__ == "__main__":
    main()
