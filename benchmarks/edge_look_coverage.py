"""Does the error budget cover the actual error? Per ``experiment images`` output folder and
method: of the images with a pose (accepted or refused) and of the accepted ones, the fraction
whose translation error is within the budget's 3-sigma position at the grasp point (the origin)
and whose rotation error is within its 3-sigma angle; and the median solve time
(docs/notes/edge_band.md, "Calibrating the look").

Usage: python benchmarks/edge_look_coverage.py RESULTS_DIR [RESULTS_DIR ...]
"""

from __future__ import annotations

import csv
import sys
from pathlib import Path

import numpy as np


def coverage(folder: Path) -> list[str]:
    trials = {(r["trial"], r["method"]): r for r in csv.DictReader(open(folder / "trials.csv"))}
    verdicts = {(r["trial"], r["method"]): r["accepted"] == "1"
                for r in csv.DictReader(open(folder / "verdicts.csv"))}
    out = []
    budgets = list(csv.DictReader(open(folder / "budgets.csv")))
    for m in dict.fromkeys(b["method"] for b in budgets):
        rows = [b for b in budgets if b["method"] == m and b["position_3sigma_mm"]]
        t = np.array([float(trials[(b["trial"], m)]["trans_err_mm"]) for b in rows])
        r = np.array([float(trials[(b["trial"], m)]["rot_err_deg"]) for b in rows])
        bp = np.array([float(b["position_3sigma_mm"]) for b in rows])
        ba = np.array([float(b["angle_3sigma_deg"]) for b in rows])
        acc = np.array([verdicts[(b["trial"], m)] for b in rows])
        ok = np.isfinite(t) & np.isfinite(r)
        cov = ok & (t <= bp) & (r <= ba)
        ms = np.array([float(trials[(b["trial"], m)]["time_ms"]) for b in rows])
        out.append(f"{folder.name} {m}: budget covers {int(cov.sum())}/{int(ok.sum())} poses "
                   f"(position {int((ok & (t <= bp)).sum())}, angle {int((ok & (r <= ba)).sum())})"
                   f"; accepted {int((cov & acc).sum())}/{int((ok & acc).sum())}; median 3-sigma "
                   f"{np.median(bp[ok]):.3f} mm / {np.median(ba[ok]):.3f} deg; median solve "
                   f"{np.median(ms):.0f} ms")
    return out


if __name__ == "__main__":
    for d in sys.argv[1:]:
        print("\n".join(coverage(Path(d))))
