"""``safewbc tune-poles``: the poles of one A-ECBF with no violation over a spec's push
distribution and the least tracking cost, by successive batched sweeps.

The spec gives the scenario, the fixed parameters ([params]), the distribution a setting
must survive (the push axes of [grid], the fixed [push], [perturb] and sweep.repeats) and
the search ([tune]: barrier, rounds, points, shrink, pole_min, pole_max, objective). Its
pole axes of the tuned barrier, when present, give the first round's box; otherwise
[pole_min, pole_max].

Round i lays ``points`` log-spaced values per pole over the current box, keeps the
candidates that are Theorem-1 admissible at every start state of the distribution, and
rolls every candidate out on the whole distribution, all candidates meeting the same
perturbation draws. A candidate is *safe* when no rollout violates the barrier (min h <
-violation_tol) or falls; the best is the safe one with the least mean objective, or,
when none is safe, the one with the fewest unsafe rollouts and then the largest worst
margin. The next box is centred on the best so far (log scale), ``shrink`` times as wide.
Each round is an ordinary sweep directory under ``--work`` (a rerun resumes it), and the
result is a params TOML for ``safewbc run SCENARIO --params FILE``.
"""

from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path

import numpy as np

from safewbc_jax.sweeps import spec as spec_mod
from safewbc_jax.sweeps.spec import Axis, SpecError, SweepSpec
from safewbc_jax.sweeps.stats import wilson_interval


@dataclasses.dataclass
class Candidate:
    poles: tuple
    n: int
    unsafe: int
    violations: int
    falls: int
    hmin: float
    objective: float
    round: int

    @property
    def safe(self) -> bool:
        return self.unsafe == 0

    def key(self):
        """Sort key: safe first, fewest unsafe, then least objective, then largest margin."""
        obj = self.objective if np.isfinite(self.objective) else np.inf
        hm = self.hmin if np.isfinite(self.hmin) else -np.inf
        return (self.unsafe / max(self.n, 1), obj if self.safe else -hm, -hm)


@dataclasses.dataclass
class TuneResult:
    barrier: str
    best: Candidate
    rounds: list
    out: Path
    work: Path
    lower_bound_p1: float
    scenario: str
    run_args: str = ""       # what ``safewbc run`` needs besides --params (the user's safe sets)
    unit: str = "m"          # of the barrier's h

    def summary(self) -> str:
        b = self.best
        lo, hi = wilson_interval(b.unsafe, b.n)
        poles = ", ".join(f"{p:.4g}" for p in b.poles)
        head = (f"tuned poles of {self.barrier}: [{poles}]  (round {b.round}; Theorem-1 bound "
                f"p1 >= {self.lower_bound_p1:.4g} over the start states)")
        stats = (f"  over {b.n} rollouts: {b.violations} violations, {b.falls} falls "
                 f"(unsafe rate 95% CI [{lo:.3f}, {hi:.3f}]), worst min h {b.hmin * 1e3:.2f} "
                 f"m{self.unit}, "
                 f"mean objective {b.objective:.4g}")
        warn = "" if b.safe else ("\n  WARNING: no candidate was free of violations and falls; "
                                  "this is the least bad one")
        return (f"{head}\n{stats}{warn}\nwrote {self.out} (safewbc run {self.scenario}"
                f"{self.run_args} --params {self.out}); rounds in {self.work}")


def _pole_axes(name: str, r: int) -> tuple:
    return tuple(Axis(f"poles.{name}.p{i + 1}", "pole", name, (), i) for i in range(r))


def _initial_box(spec: SweepSpec, name: str, r: int):
    lo = np.full(r, spec.tune["pole_min"])
    hi = np.full(r, spec.tune["pole_max"])
    for a in spec.axes:
        if a.target == name and a.kind in ("poles", "pole"):
            idx = range(r) if a.kind == "poles" else [a.index]
            for i in idx:
                lo[i], hi[i] = max(min(a.values), lo[i]), min(max(a.values), hi[i])
    return np.log(lo), np.log(hi)


def _distribution(spec: SweepSpec, name: str):
    """(axes, rows) of the distribution: the spec's push axes (every combination)."""
    other = [a for a in spec.axes if not (a.target == name and a.kind in ("poles", "pole"))]
    bad = [a.name for a in other if a.kind != "push"]
    if bad:
        raise SpecError(f"{spec.path}: tune-poles tunes the poles of {name!r} over the push "
                        f"distribution; grid axes {bad} are neither (give fixed values in "
                        "[params])")
    if not other:
        return (), np.zeros((1, 0))
    g = np.meshgrid(*[np.asarray(a.values) for a in other], indexing="ij")
    return tuple(other), np.stack([x.reshape(-1) for x in g], axis=1)


def tune_poles(spec: SweepSpec, out, *, work=None, batch=None, seed=None, executor=None,
               progress=None, quiet=False, engine="mjx", workers=None) -> TuneResult:
    """``engine``, ``workers``: each round's sweep's (``run_sweep``). ``progress``: a
    callable for the messages and each round's per-chunk lines (no bar); None: the
    messages on stderr and each round's sweep as a tqdm bar "[tune] round i/N"
    (``run_sweep``); ``quiet``: neither."""
    from safewbc_jax.params import apply_overrides, load_overrides, to_toml
    from safewbc_jax.sweeps import admissible
    from safewbc_jax.sweeps.report import outcome
    from safewbc_jax.sweeps.run import run_sweep, sim_model
    from safewbc_jax.sweeps.table import read_columns

    out = Path(out)
    if out.suffix != ".toml":
        raise ValueError(f"--out {out}: expected a .toml file (a params file for safewbc run)")
    name = spec.tune.get("barrier")
    if not spec.barrier or not name or name not in spec.barriers:
        raise SpecError(f"{spec.path}: tune-poles needs an enforced barrier (sweep.barrier = "
                        f"true and tune.barrier one of {list(spec.barriers) or 'none'})")
    say = progress or ((lambda m: None) if quiet else
                       (lambda m: print(m, file=sys.stderr, flush=True)))
    work = Path(work) if work else out.with_name(out.stem + "_rounds")
    seed = spec.seed if seed is None else int(seed)
    r = spec.pole_counts[name]
    dist_axes, dist_rows = _distribution(spec, name)
    d_settings = len(dist_rows)
    d_rollouts = d_settings * spec.repeats
    p_axes = _pole_axes(name, r)

    # Theorem 1 at every start state of the distribution (the perturbation draws are the
    # same for every candidate: rollout k of a candidate uses draw k mod d_rollouts).
    base = spec_mod.base_params(spec)
    std = spec_mod.velocity_std(spec, sim_model())
    draws = spec_mod.perturbations(seed, np.arange(d_rollouts), std)
    thr = np.full(d_rollouts, float(np.asarray(base.threshold[name])))
    etas = admissible.start_etas(spec, name, thr, draws)
    if np.any(etas[:, 0] < 0):
        raise SpecError(f"{spec.path}: h_{name}(x0) < 0 at a start state: the start is "
                        "unsafe and Theorem 1 does not apply; change the threshold")
    p1_bound = admissible.first_pole_bound(etas)
    lo, hi = _initial_box(spec, name, r)
    lo[0] = max(lo[0], np.log(max(p1_bound, 1e-12) * 1.0001)) if p1_bound > 0 else lo[0]
    if lo[0] >= hi[0]:
        raise SpecError(f"{spec.path}: Theorem 1 needs p1 >= {p1_bound:.4g} at the perturbed "
                        f"start states, above the search box's upper end {np.exp(hi[0]):.4g}; "
                        "raise tune.pole_max or reduce [perturb]")
    dim = 1 if spec.tune.get("equal_poles") else r
    say(f"[tune] {name}: {r} poles{' (equal)' if dim == 1 else ''}, {spec.tune['rounds']} rounds "
        f"of {spec.tune['points']}^{dim} candidates x {d_rollouts} rollouts; Theorem 1 needs "
        f"p1 >= {p1_bound:.4g}")

    history: list[Candidate] = []
    rounds = []
    best = None
    for i in range(spec.tune["rounds"]):
        axes_vals = [np.exp(np.linspace(lo[j], hi[j], spec.tune["points"])) for j in range(r)]
        if spec.tune.get("equal_poles"):
            # one dimension: p1 = ... = pr over the intersection of the boxes
            a, b = np.max(lo), np.min(hi)
            cand = np.repeat(np.exp(np.linspace(a, max(a, b), spec.tune["points"]))[:, None], r, 1)
        else:
            cand = np.stack([x.reshape(-1) for x in np.meshgrid(*axes_vals, indexing="ij")],
                            axis=1)
        cand = np.unique(np.round(cand, 10), axis=0)
        ok = admissible.admissible_mask(name, cand, etas)
        cand = cand[ok]
        if len(cand) == 0:
            raise SpecError(f"{spec.path}: round {i + 1}: no Theorem-1 admissible candidate in "
                            f"the box {np.exp(lo)}..{np.exp(hi)}")
        rows = [tuple(c) + tuple(d) for c in cand for d in dist_rows]
        sub = dataclasses.replace(spec.with_rows(p_axes + dist_axes, rows),
                                  noise_period=d_rollouts, target=name)
        rdir = work / f"round-{i + 1}"
        say(f"[tune] round {i + 1}: {len(cand)} candidates, poles in "
            + " x ".join(f"[{np.exp(lo[j]):.3g}, {np.exp(hi[j]):.3g}]" for j in range(r)))
        run_sweep(sub, rdir, batch=batch, seed=seed, executor=executor, progress=progress,
                  check_poles=True, quiet=quiet, engine=engine, workers=workers,
                  desc=f"[tune] round {i + 1}/{spec.tune['rounds']}:")
        man = json.loads((rdir / "sweep.json").read_text())
        cols = read_columns(rdir)
        oc = outcome(man, cols)
        setting = cols["setting"] // d_settings          # candidate index
        round_c = []
        for c in range(len(cand)):
            sel = setting == c
            h = oc["hmin"][sel]
            o = oc["objective"][sel]
            round_c.append(Candidate(
                poles=tuple(float(x) for x in cand[c]), n=int(sel.sum()),
                unsafe=int(oc["unsafe"][sel].sum()), violations=int(oc["violated"][sel].sum()),
                falls=int(oc["fell"][sel].sum()),
                hmin=float(np.nanmin(h)) if np.any(np.isfinite(h)) else float("nan"),
                objective=float(np.nanmean(o)) if np.any(np.isfinite(o)) else float("nan"),
                round=i + 1))
        history += round_c
        best = min(history, key=Candidate.key)
        rb = min(round_c, key=Candidate.key)
        rounds.append({"round": i + 1, "box": [np.exp(lo).tolist(), np.exp(hi).tolist()],
                       "candidates": [dataclasses.asdict(c) for c in round_c],
                       "round_best": dataclasses.asdict(rb)})
        say(f"[tune] round {i + 1}: best so far {best.poles} ({best.unsafe}/{best.n} unsafe, "
            f"objective {best.objective:.4g})")
        centre = np.log(best.poles)
        half = spec.tune["shrink"] * (hi - lo) / 2
        lo = np.maximum(centre - half, np.log(spec.tune["pole_min"]))
        hi = np.minimum(centre + half, np.log(spec.tune["pole_max"]))
        if p1_bound > 0:
            lo[0] = max(lo[0], np.log(p1_bound * 1.0001))
        hi = np.maximum(hi, lo + 1e-9)

    # the params file: every parameter, with the tuned poles
    tuned = apply_overrides(base, {"poles": {name: list(best.poles)}}, "tuned poles")
    lo_ci, hi_ci = wilson_interval(best.unsafe, best.n)
    # the user's safe sets must be given to ``safewbc run`` again (the params name them)
    run_args = "".join(f" --safe-set {r}" for r in spec.safe_sets)
    from safewbc_jax import scenarios

    unit = next((s.unit for s in scenarios.get_scenario(spec.scenario, True, spec.safe_sets)
                 .safe_sets if s.name == name), "m")
    header = [f"# safewbc tune-poles {spec.path}: poles of the {name!r} A-ECBF",
              f"# best of {len(history)} candidates in {len(rounds)} rounds; over {best.n} "
              f"rollouts of the distribution:",
              f"#   {best.violations} violations, {best.falls} falls (unsafe rate 95% Wilson CI "
              f"[{lo_ci:.3f}, {hi_ci:.3f}]),",
              f"#   worst min h {best.hmin * 1e3:.3f} m{unit}, mean {' + '.join(spec.tune['objective'])} "
              f"= {best.objective:.6g}",
              f"# Theorem 1 at the start states needs p1 >= {p1_bound:.6g}.",
              f"# Use: safewbc run {spec.scenario}{run_args} --params {out}", ""]
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n".join(header) + to_toml(tuned))
    # read back as `safewbc run --params` will
    back = apply_overrides(base, load_overrides(out), str(out))
    assert np.allclose(np.asarray(back.poles[name]), best.poles)
    work.mkdir(parents=True, exist_ok=True)
    (work / "tuning.json").write_text(json.dumps(
        {"barrier": name, "best": dataclasses.asdict(best), "p1_bound": p1_bound,
         "rounds": rounds, "seed": seed}, indent=2, default=float))
    return TuneResult(name, best, rounds, out, work, p1_bound, spec.scenario, run_args, unit)
