"""Figures of a run in the paper's style: actual (blue) against reference (red, dashed)."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def pyplot():
    """matplotlib.pyplot on the Agg backend (files only, no display needed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def output_figures(log: dict, run: dict, labels: dict, out_dir: Path) -> list[Path]:
    """One PNG per output: each component's actual and reference against time."""
    plt = pyplot()
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
    plt = pyplot()
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


def walking_figures(log: dict, run: dict, out_dir: Path, window: float = 2.5) -> list[Path]:
    """The paper's ALIP tracking figure: z_CoM and the swing foot's position, actual
    (blue) against reference (red, dashed), over the whole walk and over a ``window`` (s)
    from its middle; then the ALIP state about the stance foot (L^alip, the prediction
    of its end-of-step value, the planned step) with the step switches marked."""
    plt = pyplot()
    t, tau = log["t"], log["tau"]
    walk = tau >= 0
    if not np.any(walk):
        return []
    files = []
    rows = [("com z (m)", log["y_com"][:, 2], log["yd_com"][:, 2])]
    for i, a in enumerate("xyz"):
        rows.append((f"swing {a} (m)", log["y_swing_pos"][:, i], log["yd_swing_pos"][:, i]))
    mid = t[walk][0] + 0.5 * (t[walk][-1] - t[walk][0])
    spans = {"walking_tracking.png": (t[walk][0] - 0.2, t[-1]),
             "walking_tracking_zoom.png": (mid - 0.5 * window, mid + 0.5 * window)}
    switches = t[1:][np.diff(log["stance"]) != 0]
    for fname, (t0, t1) in spans.items():
        sel = (t >= t0) & (t <= t1)
        fig, axes = plt.subplots(len(rows), 1, figsize=(8, 1.8 * len(rows) + 0.6), sharex=True)
        for ax, (lab, ya, yd) in zip(axes, rows):
            ax.plot(t[sel], ya[sel], color="tab:blue", lw=1.2, label="actual")
            ax.plot(t[sel], yd[sel], color="tab:red", ls="--", lw=1.1, label="reference")
            for s in switches[(switches >= t0) & (switches <= t1)]:
                ax.axvline(s, color="0.85", lw=0.6, zorder=0)
            ax.set_ylabel(lab, fontsize=8)
            ax.grid(alpha=0.3)
        axes[0].legend(loc="best", fontsize=8)
        axes[-1].set_xlabel("t (s)")
        fig.suptitle("ALIP walking: task-space tracking (grey lines: domain switches)", fontsize=10)
        fig.tight_layout()
        f = out_dir / fname
        fig.savefig(f, dpi=110)
        plt.close(fig)
        files.append(f)
    diag = log.get("gait_diagnostics")
    if diag is not None and diag.ndim == 2 and diag.shape[1] >= 11:      # the ALIP gait's
        fig, axes = plt.subplots(3, 1, figsize=(8, 6.2), sharex=True)
        for i, axis in enumerate("xy"):
            ax = axes[i]
            ax.plot(t[walk], diag[walk, 2 + i], color="tab:blue", lw=1.1,
                    label="L about stance foot")
            ax.plot(t[walk], diag[walk, 9 + i], color="tab:orange", lw=1.0,
                    label="predicted at end of step")
            ax.set_ylabel(f"L^alip_{axis} (kg m2/s)", fontsize=8)
            ax.grid(alpha=0.3)
        axes[0].legend(fontsize=8)
        axes[2].plot(t[walk], diag[walk, 5], lw=1.0, label="u_x")
        axes[2].plot(t[walk], diag[walk, 6], lw=1.0, label="u_y")
        axes[2].set_ylabel("planned step (m)", fontsize=8)
        axes[2].legend(fontsize=8)
        axes[2].grid(alpha=0.3)
        axes[2].set_xlabel("t (s)")
        fig.suptitle("ALIP state and foot placement (heading frame)", fontsize=10)
        fig.tight_layout()
        f = out_dir / "walking_alip.png"
        fig.savefig(f, dpi=110)
        plt.close(fig)
        files.append(f)
    return files
