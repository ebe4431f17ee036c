"""Storage format of tests/data/controller_qps.npz, the recorded controller QPs.

The float fields are stored in float32 and P (symmetric) as its upper triangle only, to
keep the file small; ``load`` gives every QP field back in float64 with P full. The stored
numbers *are* the fixture: both solvers are checked against each other on exactly these
QPs.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

PATH = Path(__file__).with_name("controller_qps.npz")
FLOATS = ("qp_P", "qp_q", "qp_A", "qp_b", "qp_G", "qp_h", "qp_lb", "qp_ub", "qp_soft")


def save(path, data: dict) -> None:
    out = dict(data)
    P = np.asarray(out.pop("qp_P"))
    if not np.allclose(P, np.swapaxes(P, -1, -2), rtol=0, atol=1e-9 * np.abs(P).max()):
        raise ValueError("P is not symmetric")
    iu = np.triu_indices(P.shape[-1])
    out["qp_P_upper"] = P[:, iu[0], iu[1]]
    for key in FLOATS:
        key = "qp_P_upper" if key == "qp_P" else key
        out[key] = np.asarray(out[key]).astype(np.float32)
    np.savez_compressed(path, **out)


def load(path=PATH) -> dict:
    with np.load(path) as d:
        out = {k: d[k] for k in d.files}
    up = out.pop("qp_P_upper").astype(np.float64)
    n = int(round((np.sqrt(8 * up.shape[1] + 1) - 1) / 2))
    iu = np.triu_indices(n)
    P = np.zeros((up.shape[0], n, n))
    P[:, iu[0], iu[1]] = up
    P[:, iu[1], iu[0]] = up
    out["qp_P"] = P
    for key in FLOATS:
        out[key] = out[key].astype(np.float64)
    return out
