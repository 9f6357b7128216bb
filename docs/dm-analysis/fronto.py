"""Initial-pose error against the tilt of the holder (issue 4: "the paper's construction degrades
as the view becomes fronto-parallel").

Usage: ``nice .venv/bin/python docs/dm-analysis/fronto.py [--trials 400] [--sigma 1.0]``
Writes ``docs/dm-analysis/fronto.png`` and prints the table of median / 90 % rotation errors per
tilt bin for ``initial-paper`` and ``initial`` (sphere).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from cutterpose.experiments.synthetic import generate_trials  # noqa: E402
from cutterpose.geometry.holder import default_holder  # noqa: E402
from cutterpose.geometry.pose import geodesic_deg  # noqa: E402
from cutterpose.solvers.vanishing import solve, solve_paper  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--trials", type=int, default=400)
    ap.add_argument("--sigma", type=float, default=1.0)
    a = ap.parse_args()
    tr = generate_trials(a.trials, a.sigma, seed=4)
    holder = default_holder()
    # tilt: angle between the holder normal and the optical axis
    tilt = np.degrees(np.arccos(np.clip(tr.R_cam_holder[:, 2, 2], -1, 1)))
    err = {}
    for name, fn in (("initial-paper", solve_paper), ("initial (sphere)", solve)):
        e = np.full(a.trials, 180.0)
        for i in range(a.trials):
            est = fn(np.roll(tr.points_px[i], 5, axis=0), tr.camera, holder)
            if est:
                e[i] = geodesic_deg(tr.R_cam_holder[i], est.R_cam_holder)
        err[name] = e
    bins = [0, 15, 30, 45, 60, 90]
    print(f"sigma = {a.sigma} px, {a.trials} trials; rotation error of the initial pose (deg)")
    print("| tilt (deg) | n | " + " | ".join(f"{k} median / 90 %" for k in err) + " |")
    print("|---|---|" + "---|" * len(err))
    for lo, hi in zip(bins[:-1], bins[1:]):
        m = (tilt >= lo) & (tilt < hi)
        if not m.any():
            continue
        cells = [f"{np.median(e[m]):.2f} / {np.percentile(e[m], 90):.2f}" for e in err.values()]
        print(f"| {lo}-{hi} | {m.sum()} | " + " | ".join(cells) + " |")
    fig, ax = plt.subplots(figsize=(6, 4))
    for k, e in err.items():
        ax.semilogy(tilt, np.maximum(e, 1e-3), ".", ms=3, label=k)
    ax.axhline(2.0, color="k", lw=0.8, ls="--", label="gross failure (2 deg)")
    ax.set_xlabel("tilt of the holder plane (deg)")
    ax.set_ylabel("rotation error of the initial pose (deg)")
    ax.set_title(f"initial pose vs tilt, sigma = {a.sigma} px")
    ax.legend(fontsize=8)
    fig.tight_layout()
    out = Path(__file__).with_name("fronto.png")
    fig.savefig(out, dpi=120)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
