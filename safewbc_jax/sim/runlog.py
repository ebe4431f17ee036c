"""A run's per-step log: one preallocated array per field, filled by step index.

    log = RunLog(n_steps)
    log.put(k, tau=0.1, u=cmd.u, **{"y_com": y})     # step k's row of each field
    arrays = log.arrays()                            # {field: (steps logged, ...)}

A field's shape and dtype come from its first value (strings are kept as objects until
``arrays``); its array holds a row for every
step of the run from then on. ``arrays`` returns the rows of the steps logged (a run that
fell stops early), so the log costs no appends and no stacking at the end.
"""

from __future__ import annotations

import numpy as np


class RunLog:
    """The per-step fields of a run of at most ``n_steps`` control steps."""

    def __init__(self, n_steps: int):
        if int(n_steps) != n_steps or n_steps < 0:
            raise ValueError(f"n_steps = {n_steps!r}: must be an integer >= 0")
        self.n_steps = int(n_steps)
        self.fields: dict[str, np.ndarray] = {}
        self.steps = 0          # rows logged: 1 + the largest step index put

    def put(self, k: int, **values) -> None:
        """Step ``k``'s value of each named field. A field seen for the first time is
        allocated for the whole run; a value of another shape than the field's first is
        refused (ValueError naming the field)."""
        if not 0 <= k < self.n_steps:
            raise IndexError(f"step {k} outside the run's {self.n_steps} steps")
        for name, value in values.items():
            a = self.fields.get(name)
            value = np.asarray(value)
            if a is None:       # strings as objects: a later one may be longer
                dtype = object if value.dtype.kind in "US" else value.dtype
                a = self.fields[name] = np.zeros((self.n_steps,) + value.shape, dtype)
            elif value.shape != a.shape[1:]:
                raise ValueError(f"log field {name!r}: a value of shape {value.shape}, "
                                 f"the field's is {a.shape[1:]}")
            a[k] = value
        self.steps = max(self.steps, k + 1)

    def arrays(self) -> dict[str, np.ndarray]:
        """{field: its rows of the steps logged}, in the order the fields first came
        (strings as a numpy string array)."""
        return {name: (np.array(a[:self.steps].tolist()) if a.dtype == object
                       else a[:self.steps]) for name, a in self.fields.items()}
