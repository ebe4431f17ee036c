"""``safewbc report DIR``: the figures and summary of a sweep directory.

A rollout *violates* the target barrier b when min_t h_b < -violation_tol (the spec's
tolerance); a fallen rollout is counted separately (its barrier minimum covers the time
before the fall). Rates come with Wilson 95% intervals.

Figures (only those the swept axes allow):

* ``poles_heatmap.png``  worst-case min h and violation rate over the two poles of the
  target barrier (a line with intervals when only one pole varies);
* ``push_violation.png`` violation and fall rates against push magnitude and direction;
* ``tracking_vs_margin.png`` tracking error of each output against the safety margin
  (min h), per rollout and per setting;
* ``axes.png``           violation rate and tracking error against every other swept axis;
* ``summary.md``         counts, overall rates, the best and worst settings.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from safewbc_jax.ui.plots import pyplot
from safewbc_jax.sweeps import table as table_mod
from safewbc_jax.sweeps.stats import wilson_interval


def load(out) -> tuple[table_mod.Manifest, dict]:
    """(manifest, columns) of a sweep directory; TableError when nothing finished yet."""
    man = table_mod.read_manifest(out)
    cols = table_mod.read_columns(out)
    if not cols:
        raise table_mod.TableError(f"{out}: no finished chunk yet; run safewbc sweep first")
    return man, cols


def outcome(man: table_mod.Manifest, cols: dict) -> dict:
    """Per-rollout booleans: violated (target barrier), fell, unsafe (either), and the
    tracking objective (sum of the objective's tracking RMS)."""
    n = len(cols["rollout"])
    target = man.target
    tol = float(man.violation_tol)
    hmin = cols.get(f"barrier_min.{target}") if target else None
    if hmin is None:
        hmin = np.full(n, np.nan)
    fell = np.asarray(cols.get("fell", np.zeros(n, bool)), bool)
    violated = np.asarray(hmin < -tol) & ~np.isnan(hmin)
    weights = (man.objective_weights
               or dict.fromkeys(man.objective or [f"tracking_rms.{o}" for o in man.outputs],
                                1.0))
    weights = {c: w for c, w in weights.items() if c in cols}
    obj_names = list(weights)
    objective = weighted_objective(cols, weights) if weights else np.full(n, np.nan)
    return {"violated": violated, "fell": fell, "unsafe": violated | fell, "hmin": hmin,
            "objective": objective, "objective_names": obj_names}


def _term(man: table_mod.Manifest, name: str) -> str:
    w = man.objective_weights.get(name, 1.0)
    return name if w == 1.0 else f"{w:g} {name}"


def weighted_objective(cols: dict, weights: dict) -> np.ndarray:
    """Per rollout, sum of weight x metric column (``tune.objective``); NaN where a metric
    is NaN or missing from the table."""
    n = len(cols["rollout"])
    total = np.zeros(n)
    for name, w in weights.items():
        total = total + (w * np.asarray(cols[name], float) if name in cols else np.nan)
    return total


def axis_kinds(man: table_mod.Manifest) -> tuple[list, list]:
    """(controller axes, push axes) among the swept axes."""
    axes = list(man.axes)
    push = [a for a in axes if a.startswith("push.")]
    return [a for a in axes if a not in push], push


def group(cols: dict, keys: list) -> tuple[np.ndarray, np.ndarray]:
    """(unique rows of the key columns (g, len(keys)), group index per rollout)."""
    n = len(cols["rollout"])
    if not keys:
        return np.zeros((1, 0)), np.zeros(n, int)
    mat = np.stack([np.asarray(cols[k], float) for k in keys], axis=1)
    uniq, inv = np.unique(mat, axis=0, return_inverse=True)
    return uniq, inv.reshape(-1)


def group_stats(oc: dict, inv: np.ndarray, g: int) -> dict:
    """Per group: n, violations, falls, unsafe, Wilson intervals, worst and mean min h,
    mean objective."""
    n = np.bincount(inv, minlength=g)
    s = lambda x: np.bincount(inv, weights=np.asarray(x, float), minlength=g)  # noqa: E731
    k_v, k_f, k_u = s(oc["violated"]), s(oc["fell"]), s(oc["unsafe"])
    hmin = np.full(g, np.nan)
    obj = np.full(g, np.nan)
    for j in range(g):
        h = oc["hmin"][inv == j]
        if np.any(np.isfinite(h)):
            hmin[j] = np.nanmin(h)
        o = oc["objective"][inv == j]
        if np.any(np.isfinite(o)):
            obj[j] = np.nanmean(o)
    lo, hi = wilson_interval(k_v, n)
    ulo, uhi = wilson_interval(k_u, n)
    return {"n": n, "violations": k_v.astype(int), "falls": k_f.astype(int),
            "unsafe": k_u.astype(int), "rate": k_v / np.maximum(n, 1), "lo": lo, "hi": hi,
            "unsafe_rate": k_u / np.maximum(n, 1), "unsafe_lo": ulo, "unsafe_hi": uhi,
            "hmin": hmin, "objective": obj}


def _pole_columns(man, cols):
    t = man.target
    if not t:
        return []
    names = sorted(c for c in cols if c.startswith(f"poles.{t}.p"))
    return [c for c in names if len(np.unique(cols[c])) > 1]


def _err(rate, lo, hi):
    return np.vstack([rate - lo, hi - rate])


def poles_figure(man, cols, oc, path) -> bool:
    pc = _pole_columns(man, cols)
    if not pc:
        return False
    plt = pyplot()
    t = man.target
    if len(pc) == 1:
        uniq, inv = group(cols, pc)
        st = group_stats(oc, inv, len(uniq))
        x = uniq[:, 0]
        fig, ax = plt.subplots(1, 2, figsize=(10, 4))
        ax[0].plot(x, st["hmin"] * 1e3, "o-")
        ax[0].axhline(0, color="k", lw=0.8)
        ax[0].set(xscale="log", xlabel=pc[0], ylabel=f"worst min h_{t} (mm)")
        ax[1].errorbar(x, st["rate"], yerr=_err(st["rate"], st["lo"], st["hi"]), fmt="o-",
                       capsize=3)
        ax[1].set(xscale="log", xlabel=pc[0], ylabel="violation rate (Wilson 95%)",
                  ylim=(-0.02, 1.02))
    else:
        a, b = pc[0], pc[1]
        xa, xb = np.unique(cols[a]), np.unique(cols[b])
        ia = np.searchsorted(xa, cols[a])
        ib = np.searchsorted(xb, cols[b])
        cell = ia * len(xb) + ib
        st = group_stats(oc, cell, len(xa) * len(xb))
        fig, ax = plt.subplots(1, 2, figsize=(12, 5))
        for axis, key, label, cmap in ((ax[0], "hmin", f"worst min h_{t} (mm)", "RdYlGn"),
                                       (ax[1], "rate", "violation rate", "Reds")):
            val = st[key].reshape(len(xa), len(xb)) * (1e3 if key == "hmin" else 1.0)
            if key == "hmin":
                lim = np.nanmax(np.abs(val)) if np.any(np.isfinite(val)) else 1.0
                im = axis.imshow(val, origin="lower", cmap=cmap, vmin=-lim, vmax=lim, aspect="auto")
            else:
                im = axis.imshow(val, origin="lower", cmap=cmap, vmin=0, vmax=1, aspect="auto")
            fig.colorbar(im, ax=axis, label=label)
            n = st["n"].reshape(len(xa), len(xb))
            for i in range(len(xa)):
                for j in range(len(xb)):
                    if n[i, j] == 0:
                        continue
                    falls = st["falls"].reshape(n.shape)[i, j]
                    txt = (f"{val[i, j]:.1f}" if key == "hmin" else
                           f"{st['violations'].reshape(n.shape)[i, j]}/{n[i, j]}")
                    if falls and key != "hmin":   # a fall is not a violation: shown apart
                        txt += f"\n{falls} fell"
                    axis.text(j, i, txt, ha="center", va="center", fontsize=7)
            axis.set_xticks(range(len(xb)), [f"{v:.3g}" for v in xb], rotation=45)
            axis.set_yticks(range(len(xa)), [f"{v:.3g}" for v in xa])
            axis.set(xlabel=b, ylabel=a)
        ax[0].set_title(f"worst-case min h_{t} over rollouts (mm)")
        ax[1].set_title("violation rate (count / rollouts; falls noted)")
    tol_mm = 1e3 * float(man.violation_tol)
    fig.suptitle(f"{man.scenario}: barrier {t}, violation when min h < -{tol_mm:g} mm")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return True


def _sub(oc, sel):
    return {k: (v[sel] if isinstance(v, np.ndarray) and v.shape[:1] == sel.shape else v)
            for k, v in oc.items()}


def push_figure(man, cols, oc, path) -> bool:
    """Left: violation and fall rates against push magnitude (over every direction and
    timing). Right: violation rate against direction, one line per magnitude."""
    mags = np.unique(cols["push.magnitude"])
    dirs = np.unique(cols["push.direction"])
    if len(mags) < 2 and len(dirs) < 2:
        return False
    plt = pyplot()
    fig, ax = plt.subplots(1, 2, figsize=(12, 4.5))
    if len(mags) >= 2:
        ix = np.searchsorted(mags, cols["push.magnitude"])
        st = group_stats(oc, ix, len(mags))
        ax[0].errorbar(mags, st["rate"], yerr=_err(st["rate"], st["lo"], st["hi"]), fmt="o-",
                       capsize=3, label=f"violation of {man.target}")
        fr = st["falls"] / np.maximum(st["n"], 1)
        flo, fhi = wilson_interval(st["falls"], st["n"])
        ax[0].errorbar(mags, fr, yerr=_err(fr, flo, fhi), fmt="x--", capsize=3, label="fall")
        ax[0].set(xlabel="push magnitude (N)", ylabel="rate (Wilson 95%)", ylim=(-0.02, 1.02),
                  title="over every direction and timing")
        ax[0].legend(fontsize=8)
    else:
        ax[0].set_visible(False)
    if len(dirs) >= 2:
        for m in (mags if len(mags) <= 6 else mags[np.linspace(0, len(mags) - 1, 6).astype(int)]):
            sel = cols["push.magnitude"] == m
            ix = np.searchsorted(dirs, cols["push.direction"][sel])
            st = group_stats(_sub(oc, sel), ix, len(dirs))
            ax[1].errorbar(dirs, st["rate"], yerr=_err(st["rate"], st["lo"], st["hi"]), fmt="o-",
                           capsize=3, label=f"{m:g} N")
        ax[1].set(xlabel="push direction (deg; 0 = +x forward, 90 = +y left)",
                  ylabel="violation rate (Wilson 95%)", ylim=(-0.02, 1.02), xticks=dirs,
                  title="by magnitude")
        ax[1].legend(fontsize=8)
    else:
        ax[1].set_visible(False)
    fig.suptitle(f"{man.scenario}: pushes on the torso")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return True


def tracking_figure(man, cols, oc, path) -> bool:
    outs = [o for o in man.outputs if f"tracking_rms.{o}" in cols
            and np.any(np.isfinite(np.asarray(cols[f"tracking_rms.{o}"], float)))]
    if not outs or not np.any(np.isfinite(oc["hmin"])):
        return False
    plt = pyplot()
    fig, ax = plt.subplots(1, len(outs), figsize=(4.2 * len(outs), 4), squeeze=False)
    ctrl, _ = axis_kinds(man)
    uniq, inv = group(cols, ctrl)
    for axis, o in zip(ax[0], outs):
        y = np.asarray(cols[f"tracking_rms.{o}"], float)
        ok = ~oc["unsafe"]
        axis.scatter(oc["hmin"][ok] * 1e3, y[ok], s=8, alpha=0.5, label="safe")
        axis.scatter(oc["hmin"][~ok] * 1e3, y[~ok], s=10, marker="x", color="C3",
                     label="violated or fell")
        if ctrl and len(uniq) > 1:
            with np.errstate(all="ignore"), warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)   # all-NaN groups
                hm = np.array([np.nanmean(oc["hmin"][inv == j]) for j in range(len(uniq))])
                ym = np.array([np.nanmean(y[inv == j]) for j in range(len(uniq))])
            axis.scatter(hm * 1e3, ym, s=40, facecolors="none", edgecolors="k",
                         label="setting mean")
        axis.axvline(-1e3 * float(man.violation_tol), color="k", lw=0.8)
        axis.set(xlabel=f"safety margin min h_{man.target} (mm)",
                 ylabel=f"tracking RMS {o}", title=o)
        axis.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return True


def axes_figure(man, cols, oc, path) -> bool:
    ctrl, _ = axis_kinds(man)
    pc = set(_pole_columns(man, cols))
    axes = [a for a in ctrl if a not in pc and len(np.unique(cols[a])) > 1]
    if not axes:
        return False
    plt = pyplot()
    fig, ax = plt.subplots(2, len(axes), figsize=(4.2 * len(axes), 7), squeeze=False)
    for j, a in enumerate(axes):
        xs, ix = np.unique(cols[a], return_inverse=True)
        st = group_stats(oc, ix.reshape(-1), len(xs))
        ax[0, j].errorbar(xs, st["unsafe_rate"], yerr=_err(st["unsafe_rate"], st["unsafe_lo"],
                                                             st["unsafe_hi"]), fmt="o-", capsize=3)
        ax[0, j].set(xlabel=a, ylabel="violation-or-fall rate (Wilson 95%)", ylim=(-0.02, 1.02))
        ax[1, j].plot(xs, st["objective"], "o-")
        ax[1, j].set(xlabel=a, ylabel="tracking objective (mean)")
        if np.all(xs > 0) and xs.max() / xs.min() > 20:
            ax[0, j].set_xscale("log")
            ax[1, j].set_xscale("log")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return True


def _table_md(headers, rows) -> list[str]:
    out = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    out += ["| " + " | ".join(r) + " |" for r in rows]
    return out


def _rate(k, n, lo, hi):
    return f"{k}/{n} = {k / max(n, 1):.3f} [{lo:.3f}, {hi:.3f}]"


def summary(man: table_mod.Manifest, cols: dict, oc: dict, figures: list, out: Path,
            top: int = 5) -> str:
    n = len(cols["rollout"])
    done = len(table_mod.finished_chunks(Path(out)))
    lines = [f"# Sweep report: {man.scenario}", ""]
    lines += [f"- spec: `{man.spec_path}` (fingerprint {man.fingerprint}), seed "
              f"{man.seed}, batch {man.batch}",
              f"- rollouts in the table: {n} of {man.n_rollouts} "
              f"({done}/{man.n_chunks} chunks)"
              + ("" if n == man.n_rollouts else " -- **partial**: rerun the sweep to finish"),
              f"- swept axes: {', '.join(man.axes) or 'none'}",
              f"- target barrier: `{man.target}`; a rollout violates it when min h < "
              f"-{man.violation_tol}; barriers enforced: "
              f"{', '.join(man.barriers) or 'none'}",
              "- tracking objective: "
              f"{' + '.join(_term(man, c) for c in oc['objective_names']) or 'none'}", ""]
    tot = group_stats(oc, np.zeros(n, int), 1)
    flo, fhi = wilson_interval(int(tot["falls"][0]), n)
    lines += ["## Overall (95% Wilson intervals)", "",
              "- barrier violations: "
              f"{_rate(int(tot['violations'][0]), n, tot['lo'][0], tot['hi'][0])}",
              f"- falls: {_rate(int(tot['falls'][0]), n, flo, fhi)}",
              f"- worst min h: {tot['hmin'][0] * 1e3:.2f} mm" if np.isfinite(tot["hmin"][0])
              else "- worst min h: n/a",
              f"- QPs failed (held torque): {int(np.sum(cols.get('qp_failed', 0)))}, relaxed "
              f"(fallback): {int(np.sum(cols.get('fallbacks', 0)))}", ""]
    ctrl, push = axis_kinds(man)
    keys = ctrl or push
    what = "controller settings (over pushes and perturbations)" if ctrl else "push conditions"
    uniq, inv = group(cols, keys)
    st = group_stats(oc, inv, len(uniq))
    headers = keys + ["rollouts", "violations (rate [95% CI])", "falls", "worst min h (mm)",
                      "mean tracking objective"]

    def row(j):
        return ([f"{v:.4g}" for v in uniq[j]] +
                [str(st["n"][j]), _rate(st["violations"][j], st["n"][j], st["lo"][j], st["hi"][j]),
                 str(st["falls"][j]), f"{st['hmin'][j] * 1e3:.2f}", f"{st['objective'][j]:.4g}"])

    obj = np.where(np.isfinite(st["objective"]), st["objective"], np.inf)
    hm = np.where(np.isfinite(st["hmin"]), st["hmin"], -np.inf)
    best = np.lexsort((-hm, obj, st["unsafe_rate"]))
    worst = np.lexsort((hm, -st["unsafe_rate"]))
    if keys and len(uniq) > 1:
        lines += [f"## Best {min(top, len(uniq))} {what}", "",
                  "Fewest violations and falls first, then the least tracking objective, then "
                  "the largest worst-case margin (the order tune-poles uses).", ""]
        lines += _table_md(headers, [row(j) for j in best[:top]]) + [""]
        lines += [f"## Worst {min(top, len(uniq))} {what}", "",
                  "Most violations and falls first, then the smallest worst-case margin.", ""]
        lines += _table_md(headers, [row(j) for j in worst[:top]]) + [""]
    if ctrl and push:
        pu, pinv = group(cols, push)
        ps = group_stats(oc, pinv, len(pu))
        lines += ["## By push condition", ""]
        lines += _table_md(push + ["rollouts", "violations (rate [95% CI])", "falls"],
                           [[f"{v:.4g}" for v in pu[j]] +
                            [str(ps["n"][j]), _rate(ps["violations"][j], ps["n"][j], ps["lo"][j],
                                                    ps["hi"][j]), str(ps["falls"][j])]
                            for j in range(len(pu))]) + [""]
    if figures:
        lines += ["## Figures", ""] + [f"![{f}]({f})" for f in figures] + [""]
    return "\n".join(lines)


def make_report(out, dest=None) -> dict:
    """Write the figures and summary.md of sweep directory ``out`` into ``dest`` (default
    ``out``); of a tuning folder (``tuning.json``), ``tune_report.make_tune_report``'s.
    Returns {"figures": [...], "summary": path, "rollouts": n}."""
    from safewbc_jax.sweeps import tune_report

    if tune_report.is_tuning(out):
        return tune_report.make_tune_report(out, dest)
    out = Path(out)
    dest = Path(dest) if dest else out
    dest.mkdir(parents=True, exist_ok=True)
    man, cols = load(out)
    oc = outcome(man, cols)
    figures = []
    for name, fn in (("poles_heatmap.png", poles_figure), ("push_violation.png", push_figure),
                     ("tracking_vs_margin.png", tracking_figure), ("axes.png", axes_figure)):
        if fn(man, cols, oc, dest / name):
            figures.append(name)
    text = summary(man, cols, oc, figures, out)
    (dest / "summary.md").write_text(text)
    return {"figures": figures, "summary": str(dest / "summary.md"),
            "rollouts": len(cols["rollout"])}
