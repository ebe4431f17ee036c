"""``safewbc report WORK`` of a tuning run (a folder with ``tuning.json``, written by
``safewbc tune`` or ``tune-poles``).

* ``tuning_progress.png``: per generation, the best safe objective of the generation and the
  best so far, and the fraction of the generation's rollouts that were unsafe;
* ``tuning_params.png``: each tuned parameter's candidates per generation (safe and unsafe
  marked) and the best so far;
* ``summary.md``: the settings, a row per generation, the result and its validation on
  held-out draws with the Wilson 95% interval.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from safewbc_jax.ui.plots import pyplot

TUNING = "tuning.json"


def is_tuning(out) -> bool:
    return (Path(out) / TUNING).is_file()


def _safe(c: dict) -> bool:
    return (not c["refused"] and c["n"] > 0 and c["unsafe"] == 0
            and np.isfinite(c["objective"]))


def progress_figure(t: dict, path: Path) -> None:
    plt = pyplot()
    gens = t["generations"]
    g = [x["generation"] for x in gens]
    best_gen = [min([c["objective"] for c in x["candidates"] if _safe(c)], default=np.nan)
                for x in gens]
    so_far = [x["best"]["objective"] if _safe(x["best"]) else np.nan for x in gens]
    rate = [x["unsafe"] / x["rollouts"] if x["rollouts"] else np.nan for x in gens]
    fig, ax = plt.subplots(2, 1, figsize=(7, 6), sharex=True)
    ax[0].plot(g, best_gen, "o", label="best safe candidate of the generation")
    ax[0].plot(g, so_far, "-", label="best so far")
    z = t.get("baseline") or {}
    if z and _safe(z):
        ax[0].axhline(z["objective"], color="grey", ls="--", label="baseline (the spec's values)")
    ax[0].set(ylabel="objective (mean over the draws)", title=f"{t['method']} on "
              f"{Path(t['spec_path']).name}: {t['used']} rollouts")
    ax[0].legend(fontsize=8)
    ax[1].plot(g, rate, "s-", color="C3")
    ax[1].set(xlabel="generation", ylabel="unsafe rollouts (fraction)", ylim=(-0.02, 1.02))
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def params_figure(t: dict, path: Path) -> None:
    plt = pyplot()
    ps = t["params"]
    fig, axs = plt.subplots(len(ps), 1, figsize=(7, 2.2 * len(ps) + 0.6), sharex=True,
                            squeeze=False)
    for ax, p in zip(axs[:, 0], ps):
        for x in t["generations"]:
            for c in x["candidates"]:
                ok = _safe(c)
                ax.plot(x["generation"], c["params"][p["name"]], "o" if ok else "x",
                        color="C2" if ok else "C3", ms=4, alpha=0.7)
        ax.plot([x["generation"] for x in t["generations"]],
                [x["best"]["params"][p["name"]] for x in t["generations"]], "k-",
                label="best so far")
        ax.set(ylabel=p["name"], ylim=(p["lo"] * (0.9 if p["scale"] == "log" else 1),
                                       p["hi"] * (1.1 if p["scale"] == "log" else 1)))
        if p["scale"] == "log":
            ax.set_yscale("log")
    axs[0, 0].set_title("candidates (o safe, x unsafe) and the best so far")
    axs[-1, 0].set_xlabel("generation")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def summary(t: dict, figures: list) -> str:
    b = t["best"]
    obj = " + ".join(f"{w:g} {k}" for k, w in t["weights"].items())
    lines = [f"# Tuning: {Path(t['spec_path']).name}", "",
             f"- scenario {t['scenario']}, method {t['method']}, seed {t['seed']}",
             f"- {len(t['params'])} parameters: " + ", ".join(
                 f"{p['name']} in [{p['lo']:.4g}, {p['hi']:.4g}] ({p['scale']})"
                 for p in t["params"]),
             f"- objective: {obj}; unsafe: a fall, a lost rollout, or an enforced barrier "
             f"({', '.join(t['barriers']) or 'none'}) below -{t['violation_tol']:g}",
             f"- {len(t['generations'])} generations, {t['used']} of {t['budget']} rollouts "
             f"({t['draws']} per candidate); stopped: {t['stop']}", "",
             "| generation | candidates | safe | unsafe rollouts | best safe objective "
             "| best so far |",
             "|---|---|---|---|---|---|"]
    for x in t["generations"]:
        safe = [c for c in x["candidates"] if _safe(c)]
        bg = min((c["objective"] for c in safe), default=float("nan"))
        bs = x["best"]["objective"] if _safe(x["best"]) else float("nan")
        lines.append(f"| {x['generation']} | {len(x['candidates'])} | {len(safe)} | "
                     f"{x['unsafe']}/{x['rollouts']} | {bg:.5g} | {bs:.5g} |")
    z = t.get("baseline")
    if z:
        lines += ["", "Baseline, the tuned parameters at the spec's values ("
                  + ", ".join(f"{k} = {v:.4g}" for k, v in z["params"].items()) + ") on the "
                  "search's draws: " + (f"refused ({z['refused']})" if z["refused"] else
                                        f"{z['unsafe']}/{z['n']} unsafe, mean objective "
                                        f"{z['objective']:.6g}") + "."]
    lines += ["", "## Result", ""]
    lines += [f"- {k} = {v:.6g}" for k, v in b["params"].items()]
    lines.append(f"- search: {b['unsafe']}/{b['n']} rollouts unsafe, mean objective "
                 f"{b['objective']:.6g}, worst min h "
                 + (", ".join(f"{k} {h:.4g}" for k, h in b["hmin"].items()) or "none"))
    v = t.get("validation")
    if v:
        lines += ["", f"## Validation on {v['n']} held-out rollouts (seed {v['seed']})", "",
                  f"- unsafe: {v['unsafe']} ({v['violations']} violations, {v['falls']} falls, "
                  f"{v['lost']} lost); rate {v['rate']:.4f}, Wilson 95% interval "
                  f"[{v['ci'][0]:.4f}, {v['ci'][1]:.4f}]",
                  f"- mean objective {v['objective']:.6g}",
                  "- worst min h: " + (", ".join(f"{k} {h:.6g}" for k, h in v["hmin"].items())
                                       or "none")]
    else:
        lines += ["", "Not validated on held-out draws" + (" yet." if t["stop"] == "running"
                                                          else " (validate = 0).")]
    lines += ["", "## Figures", ""] + [f"![{f}]({f})" for f in figures]
    return "\n".join(lines) + "\n"


def make_tune_report(out, dest=None) -> dict:
    """Figures and summary.md of tuning folder ``out`` (into ``dest``, default ``out``)."""
    out = Path(out)
    dest = Path(dest) if dest else out
    dest.mkdir(parents=True, exist_ok=True)
    t = json.loads((out / TUNING).read_text())
    if not t["generations"]:
        raise ValueError(f"{out}: no finished generation yet")
    figures = []
    for name, fn in (("tuning_progress.png", progress_figure),
                     ("tuning_params.png", params_figure)):
        fn(t, dest / name)
        figures.append(name)
    (dest / "summary.md").write_text(summary(t, figures))
    n = sum(x["rollouts"] for x in t["generations"]) + (t["validation"] or {}).get("n", 0)
    return {"figures": figures, "summary": str(dest / "summary.md"), "rollouts": n}
