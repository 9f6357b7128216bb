"""Figures of the experiments (matplotlib, Agg backend: no display needed)."""

from __future__ import annotations

import math

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from .report import DOF_NAMES, DOF_UNITS  # noqa: E402

_GREEK = {"alpha": "α", "beta": "β", "gamma": "γ"}


def plot_fig5(stats: list[dict], crlb: dict, path, log_y: bool = False) -> None:
    """Six panels (alpha, beta, gamma, X, Y, Z): std of the error over the non-failed trials
    versus sigma, one line per method, the Cramer-Rao bound dashed (the paper's Fig. 5)."""
    methods = list(dict.fromkeys(s["method"] for s in stats))
    fig, axes = plt.subplots(2, 3, figsize=(13, 7.5), constrained_layout=True)
    markers = "osD^v<>phx*+"
    for k, ax in enumerate(axes.ravel()):
        for j, m in enumerate(methods):
            pts = sorted((s["sigma_px"], s["std"][k]) for s in stats
                         if s["method"] == m and math.isfinite(s["sigma_px"]))
            if not pts:
                continue
            x, y = np.array(pts).T
            ax.plot(x, y, marker=markers[j % len(markers)], ms=4, lw=1.3, label=m)
        if crlb:
            xs = sorted(crlb)
            ax.plot(xs, [crlb[s][k] for s in xs], "k--", lw=1.2, label="CRLB")
        name = DOF_NAMES[k]
        ax.set_title(f"{_GREEK.get(name, name)} ({DOF_UNITS[k]})")
        ax.set_xlabel("noise σ (px)")
        ax.set_ylabel(f"std of error ({DOF_UNITS[k]})")
        if log_y:
            ax.set_yscale("log")
        ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=8)
    fig.suptitle("Accuracy versus image noise (std over non-failed trials; failures in "
                 "summary.md)")
    fig.savefig(path, dpi=110)
    plt.close(fig)
