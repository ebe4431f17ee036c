"""``safewbc tune``: controller parameters (any barrier's poles, output gains and weights)
that keep every rollout of a push and perturbation distribution safe at the least cost,
checked afterwards on draws the search never saw.

The spec's ``[tune]`` table names the parameters (``tune.params``: any controller axis of
``[grid]`` with bounds and a log or linear scale; without it, the poles of ``tune.barrier``
in ``[pole_min, pole_max]``), the objective (``tune.objective``: a weighted sum of
``metrics.json`` names, tracking RMS of every output by default) and the search
(``tune.method``: "cmaes" or "grid"). The distribution is the spec's: its push axes in
``[grid]`` (every combination), the fixed ``[push]``, ``[perturb]`` and ``sweep.repeats``
perturbation draws per push setting. Every candidate of every generation meets the same
draws (common random numbers), so candidates differ by their parameters only.

**The constraint.** A rollout is *unsafe* when it falls, when any enforced barrier's
minimum is below ``-violation_tol``, or when it was lost (an error, a NaN barrier
minimum). A candidate is *safe* when none of its rollouts is unsafe. Candidates are ranked
by violation first: every safe candidate ranks above every unsafe one; safe candidates by
their mean objective; unsafe ones by their unsafe fraction, then by how deep their worst
violation goes (:func:`rank_value`). CMA-ES uses only this order.

**Theorem 1** is enforced before any rollout. For a barrier whose first pole is tuned, the
least admissible p1 over the distribution's start states (``admissible.first_pole_bound``)
raises that parameter's lower bound (repair); any candidate still inadmissible at a start
state (higher relative degrees) is refused, ranked last, and not rolled out.

**Budget and stop.** ``--budget`` counts the search's rollouts; a generation that would go
past it is not started, and CMA-ES stops early when it converges. Each generation is an
ordinary sweep directory ``WORK/gen-NNN`` written chunk by chunk, and ``WORK/tuning.json``
is rewritten after each; a rerun replays the finished generations from their tables (the
search is deterministic for a seed) and resumes the first unfinished one.

**Validation.** The best candidate then runs ``validate`` fresh rollouts (``WORK/validate``):
rollout k takes push setting k mod (number of push settings) and a perturbation drawn with
seed ``seed + 1``, which the search never used. Its unsafe rate with a Wilson 95% interval,
mean objective and worst barrier margins go to the report, the summary and the params
TOML's header: the figures to deploy on.
"""

from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

from safewbc_jax.sweeps import inputs
from safewbc_jax.sweeps import spec as spec_mod
from safewbc_jax.sweeps.report import weighted_objective
from safewbc_jax.sweeps.spec import Axis, SpecError, SweepSpec, TuneParam
from safewbc_jax.sweeps.stats import wilson_interval

UNSAFE_BASE = 1e6     # rank_value of an unsafe candidate starts here (objectives stay below)
REFUSED = 4 * UNSAFE_BASE
VALIDATE_SEED_OFFSET = 1
MAX_GENERATIONS = 1000   # a guard: every generation refused costs no rollouts


@dataclasses.dataclass
class Candidate:
    """One candidate's parameters and its outcome over the distribution."""

    params: dict          # tuned parameter name -> value
    n: int = 0            # rollouts
    unsafe: int = 0
    violations: int = 0   # rollouts with any enforced barrier below -violation_tol
    falls: int = 0
    lost: int = 0         # rollouts with an error or a NaN barrier minimum
    hmin: dict = dataclasses.field(default_factory=dict)    # barrier -> worst min h
    objective: float = float("nan")   # mean weighted objective over the rollouts
    refused: str = ""     # why Theorem 1 refused it (not rolled out)
    generation: int = 0

    @property
    def safe(self) -> bool:
        return not self.refused and self.n > 0 and self.unsafe == 0 and np.isfinite(self.objective)


def rank_value(c: Candidate, tol: float) -> float:
    """The value the search minimises: the mean objective of a safe candidate;
    UNSAFE_BASE x (1 + unsafe fraction) plus a term below one rollout's step that grows
    with the deepest violation for an unsafe one; REFUSED for a refused one."""
    if c.refused:
        return REFUSED
    if c.safe:
        return float(c.objective)
    deficit = sum(max(0.0, -(h + tol)) for h in c.hmin.values() if np.isfinite(h))
    frac = c.unsafe / max(c.n, 1) if c.n else 1.0
    return UNSAFE_BASE * (1.0 + frac + 0.5 / max(c.n, 1) * (1.0 - np.exp(-1e3 * deficit)))


@dataclasses.dataclass
class TuneConfig:
    """What to tune and how, from a spec's [tune] table and the command line."""

    params: tuple            # of TuneParam
    weights: dict            # objective metric -> weight
    method: str
    budget: int              # rollouts of the search
    validate: int            # held-out rollouts (0: none)
    population: int | None
    sigma: float
    rounds: int
    points: int
    shrink: float


def config(spec: SweepSpec, *, method=None, budget=None, validate=None,
           params=None) -> TuneConfig:
    """The tuning configuration: the spec's [tune] table, with ``method``, ``budget`` and
    ``validate`` from the command line when given; ``params`` (TuneParam tuple) replaces
    ``tune.params``. SpecError names what is wrong."""
    t = spec.tune
    params = params if params is not None else t.params or poles_preset(spec)
    method = method or t.method
    if method not in spec_mod.TUNE_METHODS:
        raise SpecError(f"--method {method!r}: one of {', '.join(spec_mod.TUNE_METHODS)}")
    n_dist = len(distribution(spec, params)[1]) * spec.repeats
    d = len(params)
    if method == "grid":
        per_gen = t.points ** d
        default_budget = t.rounds * per_gen * n_dist
    else:
        per_gen = t.population or 4 + int(np.floor(3 * np.log(d)))
        default_budget = 10 * per_gen * n_dist
    if budget is None:
        budget = default_budget if t.budget is None else t.budget
    if budget < per_gen * n_dist:
        raise SpecError(f"{spec.path}: a budget of {budget} rollouts is less than one "
                        f"generation ({per_gen} candidates x {n_dist} rollouts of the "
                        "distribution); raise --budget (tune.budget)")
    validate = t.validate if validate is None else int(validate)
    if validate < 0:
        raise SpecError(f"--validate {validate}: expected >= 0")
    return TuneConfig(tuple(params), dict(t.weights), method, int(budget), validate,
                      t.population, t.sigma, t.rounds, t.points, t.shrink)


def poles_preset(spec: SweepSpec) -> tuple:
    """The poles of ``tune.barrier`` as tuned parameters (log scale): the box
    [pole_min, pole_max], narrowed by the spec's pole axes of that barrier; with
    ``equal_poles``, one parameter ``poles.B`` over the intersection of the boxes."""
    name = spec.tune.barrier
    if not spec.barrier or not name or name not in spec.barriers:
        raise SpecError(f"{spec.path}: nothing to tune: give tune.params, or an enforced "
                        f"barrier whose poles to tune (sweep.barrier = true and tune.barrier "
                        f"one of {list(spec.barriers) or 'none'})")
    r = spec.pole_counts[name]
    lo = np.full(r, spec.tune.pole_min)
    hi = np.full(r, spec.tune.pole_max)
    for a in spec.axes:
        if a.target == name and a.kind in ("poles", "pole"):
            for i in (range(r) if a.kind == "poles" else [a.index]):
                lo[i], hi[i] = max(min(a.values), lo[i]), min(max(a.values), hi[i])
    if spec.tune.equal_poles:
        a, b = float(np.max(lo)), float(np.min(hi))
        return (TuneParam(Axis(f"poles.{name}", "poles", name, (a, b)), a, max(b, a * 1.0001),
                          "log"),)
    return tuple(TuneParam(Axis(f"poles.{name}.p{i + 1}", "pole", name, (lo[i], hi[i]), i),
                           float(lo[i]), float(hi[i]), "log") for i in range(r))


def distribution(spec: SweepSpec, params) -> tuple:
    """(axes, rows) of the distribution: the spec's push axes (every combination). A
    [grid] axis of a tuned parameter (or any pole axis of a barrier whose poles are tuned)
    is the sweep's, not the tuner's: it is left out. Any other axis must be a push, or a
    single value on something not tuned (a fixed setting)."""
    tuned = {p.axis.target for p in params if p.axis.kind in ("poles", "pole")}
    names = {p.name for p in params}
    targets = {p.axis.target for p in params}
    kept = [a for a in spec.axes if a.name not in names
             and not (a.kind in ("poles", "pole") and a.target in tuned)]
    bad = [a.name for a in kept if a.kind != "push" and (len(a.values) > 1
                                                         or a.target in targets)]
    if bad:
        raise SpecError(f"{spec.path}: tune runs over the push distribution; grid axes {bad} "
                        "are neither pushes nor tuned parameters, nor single fixed values of "
                        "something not tuned (give fixed values in [params], or tune them in "
                        "tune.params)")
    other = tuple(kept)
    return other, dataclasses.replace(spec, axes=other, rows=None).settings_array()


def _base_value(base, p: TuneParam) -> float:
    """The spec's own value of a tuned parameter (the search's start)."""
    a = p.axis
    kind = a.name.split(".")[0]
    if a.kind == "pole":
        return float(np.asarray(base.poles[a.target])[a.index])
    if a.kind == "poles":
        return float(np.exp(np.mean(np.log(np.asarray(base.poles[a.target])))))
    if a.kind == "scale":
        return 1.0
    if a.kind == "gain":
        return float(np.mean(np.asarray(getattr(base, kind)[a.target])))
    return float(np.asarray(getattr(base, a.target)))


def _theorem1(spec, cfg, base, seed, n_draws, say):
    """Repair: raise the lower bound of each tuned first pole to Theorem 1's bound over the
    distribution's start states. Returns (params, {barrier: etas})."""
    from safewbc_jax.sweeps import admissible
    from safewbc_jax.sweeps.run import sim_model

    tuned = sorted({p.axis.target for p in cfg.params if p.axis.kind in ("poles", "pole")})
    if not spec.barrier or not tuned:
        return cfg.params, {}
    std = inputs.velocity_std(spec, sim_model())
    draws = inputs.perturbations(seed, np.arange(n_draws), std)
    etas, params = {}, list(cfg.params)
    for name in tuned:
        thr = np.full(n_draws, float(np.asarray(base.threshold[name])))
        e = admissible.start_etas(spec, name, thr, draws)
        if np.any(e[:, 0] < 0):
            raise SpecError(f"{spec.path}: h_{name}(x0) < 0 at a start state: the start is "
                            "unsafe and Theorem 1 does not apply; change the threshold")
        etas[name] = e
        bound = admissible.first_pole_bound(e)
        for i, p in enumerate(params):
            first = p.axis.kind == "poles" or p.axis.index == 0
            if p.axis.target == name and p.axis.kind in ("poles", "pole") and first and bound > 0:
                lo = bound * 1.0001
                if lo >= p.hi:
                    raise SpecError(f"{spec.path}: Theorem 1 needs {p.name} >= {bound:.4g} at "
                                    f"the perturbed start states, above its upper bound "
                                    f"{p.hi:.4g}; raise it or reduce [perturb]")
                if lo > p.lo:
                    say(f"[tune] Theorem 1: {p.name} >= {bound:.4g} at the start states; "
                        f"lower bound {p.lo:.4g} raised to {lo:.4g}")
                    params[i] = dataclasses.replace(p, lo=lo)
    return tuple(params), etas


def _refusal(cand_vals: np.ndarray, cfg_params, base, etas: dict) -> list:
    """Per candidate: "" or why Theorem 1 refuses its poles at a start state."""
    from safewbc_jax.sweeps import admissible

    out = [""] * len(cand_vals)
    if not etas:
        return out
    pb = inputs.params_batch(base, tuple(p.axis for p in cfg_params), cand_vals)
    for name, e in etas.items():
        ok = admissible.admissible_mask(name, np.asarray(pb.poles[name]), e)
        for c in np.flatnonzero(~ok):
            out[c] = out[c] or f"Theorem 1 refuses the poles of {name} at a start state"
    return out


def evaluate(spec, weights, cols, n_per: int, cands: list) -> None:
    """Fill each candidate's outcome from a generation's table (candidate c owns the
    rollouts with setting // settings-per-candidate == c)."""
    tol = spec.violation_tol
    n = len(cols["rollout"])
    fell = np.asarray(cols.get("fell", np.zeros(n, bool)), bool)
    err = np.asarray(cols.get("error", np.full(n, "", object)), object) != ""
    hs = {b: np.asarray(cols[f"barrier_min.{b}"], float) for b in spec.barriers
          if f"barrier_min.{b}" in cols}
    viol = np.zeros(n, bool)
    lost = err.copy()
    for h in hs.values():
        viol |= h < -tol
        lost |= np.isnan(h)
    obj = weighted_objective(cols, weights)
    owner = np.asarray(cols["setting"]) // n_per
    for c, cand in enumerate(cands):
        sel = owner == c
        cand.n = int(sel.sum())
        cand.falls = int(fell[sel].sum())
        cand.violations = int(viol[sel].sum())
        cand.lost = int(lost[sel].sum())
        cand.unsafe = int((fell | viol | lost)[sel].sum())
        cand.hmin = {b: (float(np.nanmin(h[sel])) if np.any(np.isfinite(h[sel])) else float("nan"))
                     for b, h in hs.items()}
        o = obj[sel]
        cand.objective = float(np.mean(o)) if o.size and np.all(np.isfinite(o)) else float("nan")


@dataclasses.dataclass
class TuneResult:
    best: Candidate
    validation: dict | None
    generations: list
    out: Path
    work: Path
    scenario: str
    method: str
    used: int
    stop: str
    run_args: str = ""
    baseline: Candidate | None = None
    units: dict = dataclasses.field(default_factory=dict)

    def summary(self) -> str:
        b = self.best
        vals = ", ".join(f"{k} = {v:.4g}" for k, v in b.params.items())
        lines = [f"tuned ({self.method}, {len(self.generations)} generations, {self.used} "
                 f"rollouts; {self.stop}): {vals}",
                 f"  search: {b.unsafe}/{b.n} unsafe, mean objective {b.objective:.4g}"
                 + ("" if b.safe else "  (WARNING: no candidate was safe on every draw; "
                    "this is the least unsafe)")]
        z = self.baseline
        if z is not None:
            lines.append("  baseline (the spec's values): " + (
                f"refused: {z.refused}" if z.refused else
                f"{z.unsafe}/{z.n} unsafe, mean objective {z.objective:.4g}"))
        v = self.validation
        if v:
            lines.append(f"  validation on {v['n']} held-out rollouts: {v['unsafe']} unsafe "
                         f"(rate {v['rate']:.3f}, Wilson 95% CI [{v['ci'][0]:.3f}, "
                         f"{v['ci'][1]:.3f}]), mean objective {v['objective']:.4g}, worst "
                         f"min h {format_margins(v['hmin'], self.units, 4)}")
        lines.append(f"wrote {self.out} (safewbc run {self.scenario}{self.run_args} --params "
                     f"{self.out}); generations in {self.work}")
        return "\n".join(lines)


def _make_search(cfg: TuneConfig, params, base, seed):
    from safewbc_jax.sweeps import search

    if cfg.method == "grid":
        return search.GridRefine(len(params), cfg.points, cfg.rounds, cfg.shrink)
    return search.Cmaes(np.array([p.to_unit(v) for p, v in zip(params, _start(params, base))]),
                        cfg.sigma, cfg.population, seed)


def _start(params, base) -> np.ndarray:
    """The start value of each tuned parameter: ``start``, else the spec's own value,
    clipped into the bounds (the search's start)."""
    return np.array([float(np.clip(p.start if p.start is not None else _base_value(base, p),
                                   p.lo, p.hi)) for p in params])


@dataclasses.dataclass
class _Run:
    """What the generations and the validation of one tuning run share."""

    spec: SweepSpec
    cfg: TuneConfig
    params: tuple            # TuneParam, after Theorem 1's repair
    base: Any             # the spec's ControllerParams
    etas: dict               # barrier -> (draws, r) eta(x0) at the start states
    dist_axes: tuple
    dist_rows: np.ndarray
    n_draws: int             # rollouts a candidate gets: push settings x repeats
    work: Path
    seed: int
    sweep_kw: dict           # run_sweep's batch, executor, progress, quiet, engine, workers
    title: str
    say: Any
    units: dict              # barrier -> the unit of its h

    def rows(self, vals: np.ndarray, dist_index) -> list:
        return [tuple(v) + tuple(self.dist_rows[d]) for v in vals for d in dist_index]

    def roll(self, rows, folder: Path, seed: int, desc: str, **spec_changes) -> dict:
        """Roll ``rows`` (tuned values + push values) out as a sweep into ``folder``;
        its columns."""
        from safewbc_jax.sweeps import pool as pool_mod
        from safewbc_jax.sweeps.run import run_sweep
        from safewbc_jax.sweeps.table import read_columns

        axes = tuple(p.axis for p in self.params) + tuple(self.dist_axes)
        sub = dataclasses.replace(self.spec.with_rows(axes, rows), **spec_changes)
        kw = dict(self.sweep_kw)
        if kw["batch"] is None and kw["engine"] == "mujoco":
            # one chunk: its lockstep groups spread over every worker (a chunk of 16 would
            # be one group, on one worker); on Ray, chunks of one group each, a task per
            # CPU. The mjx engine keeps one compiled batch size
            kw["batch"] = pool_mod.LOCKSTEP if kw.get("ray") else sub.n_rollouts
        r = run_sweep(sub, folder, seed=seed, check_poles=True, desc=desc, **kw)
        if r.failed:            # a candidate's objective needs every one of its rollouts
            from safewbc_jax.sweeps.cluster import describe_failures

            raise RuntimeError(f"{folder}: " + describe_failures(r.failed, folder))
        return read_columns(folder)


def default_work(out, title: str = "tune") -> Path:
    """The folder of a run's generations: OUT without .toml + "_tune" ("_rounds" where
    ``title`` is "tune-poles")."""
    out = Path(out)
    return out.with_name(out.stem + ("_rounds" if title == "tune-poles" else "_tune"))


def tune(spec: SweepSpec, out, *, cfg: TuneConfig | None = None, work=None, batch=None,
         seed=None, executor=None, progress=None, quiet=False, engine="mjx", workers=None,
         title="tune", ray: str | None = None) -> TuneResult:
    """Run (or resume) a tuning run of ``spec`` and write the params TOML ``out``.
    ``cfg``: :func:`config` of the spec when None. ``work``: the generations' folder
    (default OUT without .toml + "_tune"). ``batch``, ``executor``, ``engine``, ``workers``,
    ``progress``, ``quiet``: each generation's sweep's (``run_sweep``), with a tqdm bar per
    generation titled with the best objective so far. The mujoco engine's workers start
    once and serve every generation and the validation. ``ray``: every generation's chunks
    are tasks on that Ray cluster (``run_sweep``'s ``ray``)."""
    from safewbc_jax.sweeps import pool as pool_mod

    out = Path(out)
    if out.suffix != ".toml":
        raise ValueError(f"--out {out}: expected a .toml file (a params file for safewbc run)")
    cfg = cfg or config(spec)
    say = progress or ((lambda m: None) if quiet else
                       (lambda m: print(m, file=sys.stderr, flush=True)))
    work = Path(work) if work else default_work(out, title)
    seed = spec.seed if seed is None else int(seed)
    dist_axes, dist_rows = distribution(spec, cfg.params)
    n_draws = len(dist_rows) * spec.repeats
    base = inputs.base_params(spec)
    params, etas = _theorem1(spec, cfg, base, seed, n_draws, say)
    head = {"method": cfg.method, "seed": seed, "budget": cfg.budget,
            "params": [{"name": p.name, "lo": p.lo, "hi": p.hi, "scale": p.scale}
                       for p in params],
            "weights": cfg.weights, "barriers": list(spec.barriers),
            "violation_tol": spec.violation_tol, "draws": n_draws, "scenario": spec.scenario,
            "spec_path": spec.path, "fingerprint": spec.fingerprint()}
    state = work / "tuning.json"
    if state.exists():
        prev = json.loads(state.read_text())
        now = json.loads(json.dumps(head, default=float))
        if any(prev.get(k) != now[k] for k in head if k != "budget"):   # a larger budget
            raise SpecError(f"{work}: holds a tuning run of another spec, method or seed; "
                            "give another --work (or remove it)")
    work.mkdir(parents=True, exist_ok=True)
    own_pool = None
    if ray is not None:
        from safewbc_jax.sweeps import cluster

        cluster.connect(ray, quiet)
        engine = cluster.resolve_engine(engine)
    elif executor is None and pool_mod.resolve_engine(engine) == "mujoco":
        engine = "mujoco"       # one pool for every generation: its workers compile once
        executor = own_pool = pool_mod.PoolExecutor(
            spec, workers, lockstep=pool_mod.lockstep_width(batch))
    run = _Run(spec, cfg, params, base, etas, dist_axes, dist_rows, n_draws, work, seed,
               dict(batch=batch, executor=executor, progress=progress, quiet=quiet,
                    engine=engine, workers=workers, ray=ray), title, say, _units(spec))
    try:
        head["baseline"] = dataclasses.asdict(_baseline(run))
        gens, best, used, stop = _search(run, _make_search(cfg, params, base, seed), state,
                                         head)
        validation = _validate(run, best) if cfg.validate else None
    finally:
        if own_pool is not None:
            own_pool.close()
    run_args = _write_params(run, out, best, gens, used, stop, validation,
                             Candidate(**head["baseline"]))
    _write(state, head, gens, best, used, validation, stop)
    return TuneResult(best, validation, gens, out, work, spec.scenario, cfg.method, used,
                      stop, run_args, Candidate(**head["baseline"]), run.units)


def format_margins(hmin: dict, units: dict, digits: int) -> str:
    """"barrier value unit, ..." of worst barrier minima, "(no barrier)" without any."""
    return ", ".join(f"{k} {h:.{digits}g} {units.get(k, '')}".rstrip()
                     for k, h in hmin.items()) or "(no barrier)"


def _units(spec) -> dict:
    """Barrier name -> the unit of its h ("m", "rad", ...)."""
    from safewbc_jax import scenarios

    sc = scenarios.get_scenario(spec.scenario, True, spec.safe_sets)
    return {s.name: s.unit for s in sc.safe_sets}


def _baseline(run: _Run) -> Candidate:
    """The tuned parameters at their start values (the spec's own, clipped to the
    bounds) on the search's draws (``WORK/baseline``): what tuning is measured against.
    Its rollouts are not counted in the budget."""
    vals = _start(run.params, run.base)[None]
    c = Candidate({p.name: float(v) for p, v in zip(run.params, vals[0])})
    c.refused = _refusal(vals, run.params, run.base, run.etas)[0]
    if not c.refused:
        cols = run.roll(run.rows(vals, range(len(run.dist_rows))), run.work / "baseline",
                        run.seed, f"[{run.title}] baseline:", noise_period=run.n_draws)
        evaluate(run.spec, run.cfg.weights, cols, len(run.dist_rows), [c])
    return c


def _search(run: _Run, search, state: Path, head: dict):
    """The generations: ask, refuse, roll out, rank, tell; ``tuning.json`` after each.
    Returns (generations, best candidate, rollouts used, why it stopped)."""
    spec, cfg, params, tol = run.spec, run.cfg, run.params, run.spec.violation_tol
    run.say(f"[{run.title}] {len(params)} parameters ({', '.join(p.name for p in params)}) "
            f"by {cfg.method}: {search.population} candidates a generation x {run.n_draws} "
            f"rollouts, budget {cfg.budget} rollouts")
    history, gens = [], []
    used, stop, g = 0, "", 0
    best = None
    while True:
        if g >= MAX_GENERATIONS:
            stop = f"{MAX_GENERATIONS} generations"
            break
        if search.done():
            stop = "converged" if cfg.method == "cmaes" else "rounds done"
            break
        x = search.ask()
        vals = np.stack([p.to_value(x[:, j]) for j, p in enumerate(params)], axis=1)
        cands = [Candidate({p.name: float(v) for p, v in zip(params, row)}, generation=g + 1)
                 for row in vals]
        why = _refusal(vals, params, run.base, run.etas)
        for c, w in zip(cands, why):
            c.refused = w
        live = [i for i, w in enumerate(why) if not w]
        cost = len(live) * run.n_draws
        if used + cost > cfg.budget:
            stop = f"budget: generation {g + 1} would need {cost} more rollouts"
            break
        g += 1
        if live:
            bo = f"{best.objective:.4g}" if best is not None and best.safe else "none safe yet"
            cols = run.roll(run.rows(vals[live], range(len(run.dist_rows))),
                            run.work / f"gen-{g:03d}", run.seed,
                            f"[{run.title}] gen {g}, best {bo}:", noise_period=run.n_draws)
            evaluate(spec, cfg.weights, cols, len(run.dist_rows), [cands[i] for i in live])
            used += cost
        values = [rank_value(c, tol) for c in cands]
        search.tell(x, values)
        history += cands
        best = min(history, key=lambda c: rank_value(c, tol))
        n_unsafe = sum(c.unsafe for c in cands)
        gens.append({"generation": g, "rollouts": cost, "unsafe": n_unsafe,
                     "candidates": [dataclasses.asdict(c) for c in cands],
                     "values": values, "best": dataclasses.asdict(best)})
        _write(state, head, gens, best, used, None, "running")
        run.say(f"[{run.title}] generation {g}: {sum(c.safe for c in cands)}/{len(cands)} "
                f"candidates safe, {n_unsafe}/{cost} rollouts unsafe; best so far "
                + ", ".join(f"{k} = {v:.4g}" for k, v in best.params.items())
                + (f" (objective {best.objective:.4g})" if best.safe else
                   f" ({best.unsafe}/{best.n} unsafe)"))
    if best is None:
        raise SpecError(f"{spec.path}: the budget ran out before the first generation")
    return gens, best, used, stop


def _validate(run: _Run, best: Candidate) -> dict:
    """The best candidate on ``validate`` held-out rollouts (see the module text)."""
    vseed = run.seed + VALIDATE_SEED_OFFSET
    n = run.cfg.validate
    cand = np.array([[best.params[p.name] for p in run.params]])
    rows = run.rows(cand, [k % len(run.dist_rows) for k in range(n)])
    cols = run.roll(rows, run.work / "validate", vseed, f"[{run.title}] validation:",
                    repeats=1, noise_period=None)
    c = Candidate(dict(best.params))
    evaluate(run.spec, run.cfg.weights, cols, n, [c])
    lo, hi = wilson_interval(c.unsafe, c.n)
    return {"n": c.n, "seed": vseed, "unsafe": c.unsafe, "violations": c.violations,
            "falls": c.falls, "lost": c.lost, "rate": c.unsafe / max(c.n, 1), "ci": [lo, hi],
            "objective": c.objective, "hmin": c.hmin}


def _write_params(run: _Run, out: Path, best, gens, used, stop, validation, baseline) -> str:
    """The params TOML: every parameter, the tuned ones set, and a header with the search's
    and the validation's figures. Returns the extra ``safewbc run`` arguments."""
    from safewbc_jax.control.params import apply_overrides, load_overrides, to_toml

    spec, cfg = run.spec, run.cfg
    one = inputs.params_batch(run.base, tuple(p.axis for p in run.params),
                                np.array([[best.params[p.name] for p in run.params]]))
    unbatch = lambda v: {k: x[0] for k, x in v.items()} if isinstance(v, dict) else v[0]  # noqa: E731
    tuned = type(one)(**{f.name: unbatch(getattr(one, f.name))
                         for f in dataclasses.fields(one)})
    run_args = "".join(f" --safe-set {r}" for r in spec.safe_sets)
    header = [f"# safewbc {run.title} {spec.path} ({cfg.method}, seed {run.seed}): "
              + ", ".join(f"{k} = {v:.6g}" for k, v in best.params.items()),
              f"# search: {len(gens)} generations, {used} rollouts ({stop}); best over "
              f"{best.n} rollouts: {best.unsafe} unsafe, mean objective "
              f"{' + '.join(f'{w:g} {k}' for k, w in cfg.weights.items())} = "
              f"{best.objective:.6g}",
              "# baseline, the spec's values on the search's draws: " + (
                  f"refused ({baseline.refused})" if baseline.refused else
                  f"{baseline.unsafe} of {baseline.n} unsafe, mean objective "
                  f"{baseline.objective:.6g}")]
    if validation:
        v = validation
        header += [f"# validation on {v['n']} held-out rollouts (seed {v['seed']}): "
                   f"{v['unsafe']} unsafe, rate {v['rate']:.4f} (Wilson 95% CI "
                   f"[{v['ci'][0]:.4f}, {v['ci'][1]:.4f}]), mean objective {v['objective']:.6g}",
                   f"#   worst min h: {format_margins(v['hmin'], run.units, 6)}"]
    else:
        header.append("# not validated on held-out draws (validate = 0)")
    header += [f"# Use: safewbc run {spec.scenario}{run_args} --params {out}", ""]
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n".join(header) + to_toml(tuned))
    apply_overrides(run.base, load_overrides(out), str(out))     # reads back as `run` will
    return run_args


def _write(path: Path, head, gens, best, used, validation, stop) -> None:
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps({**head, "generations": gens, "best": dataclasses.asdict(best),
                               "used": used, "validation": validation, "stop": stop},
                              indent=1, default=float))
    tmp.replace(path)
