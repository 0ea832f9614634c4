"""The evaluation's figures (matplotlib, Agg): Figs. 1-4 of the paper from the rows of a run."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .report import LABELS, MAPPERS

__all__ = ["plot_figures"]


def _finish(ax, xlabel: str, ylabel: str, title: str) -> None:
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title, fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)


def plot_figures(out: Path, fig1, fig2, fig3, fig4b, gauss, conflict_idx, cg, res, fig4d, title) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    files = []
    styles = {"rcu": "o-", "ndtom": "s-", "ndtom_ndt": "d-", "er": "^-"}

    def save(fig, name: str) -> None:
        fig.tight_layout()
        fig.savefig(out / name, dpi=110)
        plt.close(fig)
        files.append(out / name)

    fig, ax = plt.subplots(figsize=(6.4, 4))
    for m in MAPPERS:
        ax.plot([r["scan"] + 1 for r in fig1], [r[f"score_{m}"] for r in fig1], styles[m], ms=3, label=LABELS[m])
    ax.set_ylim(0, 1.05)
    _finish(ax, "clouds inserted", "mean L2 score vs batch map", f"Fig. 1: against the batch map ({res:g} m)")
    save(fig, "fig1_vs_batch.png")

    fig, ax = plt.subplots(figsize=(6.4, 4))
    for m in MAPPERS:
        ax.plot([r["cloud"] for r in fig2], [r[f"score_{m}"] for r in fig2], styles[m], ms=3, label=LABELS[m])
    ax.set_ylim(0, 1.05)
    _finish(ax, "cloud", "score of the cloud's NDT map in the final map", "Fig. 2: representation self-test")
    save(fig, "fig2_self_test.png")

    fig, ax = plt.subplots(figsize=(6.4, 4))
    x = [r["scan"] + 1 for r in fig3]
    ax.plot(x, [r["mean_logodds_occupied"] for r in fig3], "o-", ms=3, label="occupied cells (l > 0)")
    ax.plot(x, [r["mean_logodds_empty"] for r in fig3], "s-", ms=3, label="empty cells (l < 0)")
    ax.axhline(0, color="k", lw=0.8)
    _finish(ax, "clouds inserted", "mean log-odds (NDT-OM)", "Fig. 3: mean log-odds")
    save(fig, "fig3_logodds.png")

    fig, ax = plt.subplots(figsize=(6.4, 4))
    x = [r["scan"] + 1 for r in fig4b]
    ax.plot(x, [100 * r["fraction"] for r in fig4b], "o-", ms=3, label="% of NDT-OM Gaussians")
    ax.plot(x, [100 * r["fraction_of_rcu"] for r in fig4b], "s--", ms=3, label="% of RCU Gaussians")
    ax.plot(x, [100 * r["fraction_ndt"] for r in fig4b], "d-", ms=3, label="NDT miss model: % of its Gaussians")
    _finish(
        ax,
        "clouds inserted",
        "conflicting cells (%)",
        f"Fig. 4b: Gaussian in RCU, none in NDT-OM (final {fig4b[-1]['conflicting']} cells)",
    )
    save(fig, "fig4b_conflicting.png")

    fig, axes = plt.subplots(1, 2, figsize=(12, 5.2))
    nd = gauss["ndtom"]["mean"]
    rng = np.random.default_rng(0)
    sub = nd if len(nd) <= 150_000 else nd[rng.choice(len(nd), 150_000, replace=False)]
    ax = axes[0]
    ax.scatter(sub[:, 0], sub[:, 1], s=0.3, c="0.55", lw=0, label=f"NDT-OM Gaussians ({len(nd)})")
    if len(conflict_idx):
        cc = (conflict_idx + 0.5) * res
        ax.scatter(cc[:, 0], cc[:, 1], s=1.5, c="red", lw=0, label=f"conflicting cells ({len(conflict_idx)})")
    ax.set_title(f"NDT-OM {res:g} m, top view", fontsize=10)
    ax.set_aspect("equal", "datalim")
    ax.legend(fontsize=8, markerscale=6, loc="upper right")
    ax = axes[1]
    cm = cg["mean"]
    if len(cm):
        ax.scatter(cm[:, 0], cm[:, 1], s=1.0, c=cm[:, 2], cmap="viridis", lw=0)
    ax.set_title(
        f"Fig. 4d: coarsened x{fig4d['factor']} to {fig4d['coarse_resolution']:g} m: "
        f"{fig4d['fine_gaussians']} -> {fig4d['coarse_gaussians']} Gaussians",
        fontsize=10,
    )
    ax.set_aspect("equal", "datalim")
    fig.suptitle(title, fontsize=9)
    save(fig, "fig4_maps.png")
    return files
