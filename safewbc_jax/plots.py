"""Figures of a run in the paper's style: actual (blue) against reference (red, dashed)."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def output_figures(log: dict, run: dict, labels: dict, out_dir: Path) -> list[Path]:
    """One PNG per output: each component's actual and reference against time."""
    plt = _plt()
    files = []
    t = log["t"]
    for nm in run["outputs"]:
        ya, yd = log[f"y_{nm}"], log[f"yd_{nm}"]
        n = ya.shape[1]
        cols = 2 if n > 4 else 1
        rows = int(np.ceil(n / cols))
        fig, axes = plt.subplots(rows, cols, figsize=(6.5 * cols, 1.9 * rows + 0.6), sharex=True,
                                 squeeze=False)
        for i in range(n):
            ax = axes[i % rows, i // rows] if cols > 1 else axes[i, 0]
            ax.plot(t, ya[:, i], color="tab:blue", lw=1.3, label="actual")
            ax.plot(t, yd[:, i], color="tab:red", ls="--", lw=1.2, label="reference")
            ax.axvline(run["settle"], color="0.6", lw=0.8)
            ax.set_ylabel(labels.get(nm, [f"{nm}[{j}]" for j in range(n)])[i], fontsize=8)
            ax.grid(alpha=0.3)
        for ax in axes[-1]:
            ax.set_xlabel("t (s)")
        axes[0, 0].legend(loc="best", fontsize=8)
        fig.suptitle(f"{nm}: actual vs reference (motion starts at the grey line)", fontsize=10)
        fig.tight_layout()
        f = out_dir / f"tracking_{nm}.png"
        fig.savefig(f, dpi=110)
        plt.close(fig)
        files.append(f)
    return files


def barrier_figure(log: dict, run: dict, out_dir: Path, title: str) -> Path | None:
    """Barrier values h(t) of guarded and monitored safe sets against the boundary h = 0."""
    names = run["barriers"] + run["monitors"]
    if not names:
        return None
    plt = _plt()
    fig, ax = plt.subplots(figsize=(7, 3.2))
    for nm in names:
        style = "-" if nm in run["barriers"] else ":"
        tag = "A-ECBF on" if nm in run["barriers"] else "unguarded"
        ax.plot(log["t"], log[f"h_{nm}"], style, lw=1.4, label=f"{nm} ({tag})")
    ax.axhline(0.0, color="k", lw=1.0)
    ax.axhspan(ax.get_ylim()[0], 0.0, color="tab:red", alpha=0.08, label="unsafe")
    ax.axvline(run["settle"], color="0.6", lw=0.8)
    ax.set_xlabel("t (s)")
    ax.set_ylabel("h (m)")
    ax.set_title(title, fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    f = out_dir / "barriers.png"
    fig.savefig(f, dpi=110)
    plt.close(fig)
    return f
