"""Record the controller QPs of short deployment runs of every scenario into
tests/data/controller_qps.npz (the fixture the JAX solver is checked against PIQP on).

    python tests/data/record_qps.py

Every ``every``-th control step of each run is kept; arms runs with and without the
barrier give QPs with the A-ECBF row active and inactive. Arrays are stacked per field
(qp_P, qp_q, ...), with qp_status/qp_fallback from PIQP at record time and qp_scenario.
"""

from pathlib import Path

import numpy as np

import qp_fixture

from safewbc_jax.app.runner import run_scenario

OUT = Path(__file__).with_name("controller_qps.npz")
RUNS = [("squat", dict(duration=3.0), 30), ("bow", dict(duration=6.0), 50),
        ("arms", dict(duration=8.0), 30), ("arms", dict(duration=8.0, barrier=False), 40),
        ("walk", dict(duration=3.0), 16)]


def main():
    import tempfile

    parts = []
    for name, kw, every in RUNS:
        with tempfile.TemporaryDirectory() as tmp:
            run_scenario(name, out=tmp, quiet=True, record_qps_every=every, **kw)
            data = dict(np.load(Path(tmp) / "qps.npz"))
        data["qp_scenario"] = np.array([name + ("" if kw.get("barrier", True) else "_no_barrier")]
                                       * len(data["qp_step"]))
        parts.append(data)
    # Pad the inequality rows to a common count (squat and bow have no barrier row):
    # padding rows are 0 <= 1, hard.
    mi = max(p["qp_G"].shape[1] for p in parts)
    for p in parts:
        k = mi - p["qp_G"].shape[1]
        if k:
            n, _, nx = p["qp_G"].shape
            p["qp_G"] = np.concatenate([p["qp_G"], np.zeros((n, k, nx))], axis=1)
            p["qp_h"] = np.concatenate([p["qp_h"], np.ones((n, k))], axis=1)
            p["qp_soft"] = np.concatenate([p["qp_soft"], np.zeros((n, k))], axis=1)
    out = {key: np.concatenate([p[key] for p in parts]) for key in parts[0]}
    qp_fixture.save(OUT, out)
    print(f"wrote {OUT}: {len(out['qp_step'])} QPs, {OUT.stat().st_size / 1e6:.1f} MB")


if __name__ == "__main__":
    main()
