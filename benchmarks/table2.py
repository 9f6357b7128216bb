"""Table 2 of the paper next to ours, from an ``experiment images`` run (docs/notes/images.md).

Runs (or, with ``--report-only``, only reads) ``cutterpose experiment images`` outputs and prints
markdown: std per DOF per method over the non-failed images and over all images with a pose,
next to the paper's Table 2; the lost images grouped by reason; the corner RMS per difficulty
(refined vs the paper's threshold lines) and which segmentation produced the corners.

Usage::

    python benchmarks/table2.py SET_DIR --out results/images [--workers 2]
    python benchmarks/table2.py SET_DIR --out results/images_paper_seg --paper-segmentation
    python benchmarks/table2.py SET_DIR --out results/images --report-only
"""

from __future__ import annotations

import argparse
import csv
import re
from collections import Counter
from pathlib import Path

import numpy as np

METHODS = "dm,dm+,dlt,epnp,rpnp,aspnp,opnp,opencv-ippe-lm"
#: the paper's Table 2: std of alpha, beta, gamma [deg], X, Y, Z [mm] on 100 real images
PAPER = {"aspnp": (0.04, 0.10, 0.03, 0.15, 0.11, 0.18), "dlt": (0.07, 0.09, 0.03, 0.15, 0.12, 0.19),
         "epnp": (0.07, 0.09, 0.03, 0.15, 0.11, 0.17), "opnp": (0.04, 0.10, 0.03, 0.15, 0.11, 0.18),
         "rpnp": (0.11, 0.10, 0.03, 0.16, 0.13, 0.41), "dm": (0.10, 0.14, 0.03, 0.14, 0.11, 0.19)}
ERR = ["alpha_err_deg", "beta_err_deg", "gamma_err_deg", "X_err_mm", "Y_err_mm", "Z_err_mm"]


def _fmt(v) -> str:
    return " ".join("-" if not np.isfinite(x) else f"{x:.3f}" for x in v)


def _reason_class(reason: str) -> str:
    """A short class of a failure reason (the full text is in failures.csv)."""
    r = reason.split(" | model fit: ")[-1]
    for pat, name in ((r"off the direction of its family", "segment off its family"),
                      (r"gradient edge found along only", "edge hidden/damaged (edge support)"),
                      (r"moved \d+ px from the model", "refined line left the fitted model"),
                      (r"outline found", "pocket outline mostly missing"),
                      (r"corner residual RMS", "verdict: corner residual RMS"),
                      (r"px off the model", "verdict: one corner off the model"),
                      (r"planar ambiguity", "verdict: planar ambiguity"),
                      (r"outside the working range", "verdict: outside working range"),
                      (r"too uncertain", "verdict: std too large"),
                      (r"gross error", "gross error (accepted pose, >2 deg / >10 mm)"),
                      (r"characteristic segments", "segmentation: segment count"),
                      (r"not on the contour", "hidden corner (contour check)"),
                      (r"nearly parallel", "consecutive segments parallel")):
        if re.search(pat, r):
            return name
    return r[:60]


def _q(x, p) -> str:
    return f"{np.nanpercentile(x, p):.3f}" if np.isfinite(x).any() else "-"


def std_table(rows, corners, difficulties=None) -> list[str]:
    """Table 2 rows: std per DOF per method over the non-failed images and over all with a
    pose (of the given difficulties only, if any), with the paper's row."""
    diff = {c["trial"]: c["difficulty"] for c in corners}
    if difficulties:
        rows = [r for r in rows if diff.get(r["trial"]) in difficulties]
    methods = list(dict.fromkeys(r["method"] for r in rows))
    lines = ["| method | n ok / n | std alpha, beta, gamma deg; X, Y, Z mm (non-failed) | "
             "std (all with a pose) | paper Table 2 |", "|---|---|---|---|---|"]
    for m in methods:
        sel = [r for r in rows if r["method"] == m]
        E = np.array([[float(r[c]) if r[c] else np.nan for c in ERR] for r in sel])
        failed = np.array([r["failed"] == "1" for r in sel])
        has = np.all(np.isfinite(E), axis=1)
        good = has & ~failed
        s_ok = E[good].std(axis=0, ddof=1) if good.sum() > 1 else np.full(6, np.nan)
        s_all = E[has].std(axis=0, ddof=1) if has.sum() > 1 else np.full(6, np.nan)
        p = PAPER.get(m)
        lines.append(f"| {m} | {good.sum()} / {len(sel)} | {_fmt(s_ok)} | {_fmt(s_all)} | "
                     + (" ".join(f"{x:.2f}" for x in p) if p else "-") + " |")
    return lines


def per_difficulty(rows, corners, method="dm+") -> list[str]:
    """std and mean error per DOF of one method per difficulty (non-failed images)."""
    diff = {c["trial"]: c["difficulty"] for c in corners}
    lines = [f"| {method}: difficulty | n ok | std alpha beta gamma X Y Z | mean (bias) |",
             "|---|---|---|---|"]
    for d in sorted(set(diff.values())):
        sel = [r for r in rows if r["method"] == method and diff[r["trial"]] == d
               and r["failed"] == "0"]
        E = np.array([[float(r[c]) for c in ERR] for r in sel]).reshape(-1, 6)
        s = E.std(axis=0, ddof=1) if len(E) > 1 else np.full(6, np.nan)
        mu = E.mean(axis=0) if len(E) else np.full(6, np.nan)
        lines.append(f"| {d} | {len(E)} | {' '.join(f'{x:.3f}' for x in s)} | "
                     f"{' '.join(f'{x:.3f}' for x in mu)} |")
    return lines


def report(out: Path, subset=("easy", "dim", "blurred", "occluded")) -> str:
    rows = list(csv.DictReader(open(out / "trials.csv")))
    corners = list(csv.DictReader(open(out / "corners.csv")))
    fails = list(csv.DictReader(open(out / "failures.csv")))
    lines = ["All images:", ""] + std_table(rows, corners)
    if subset:
        lines += ["", f"Without wear ({', '.join(subset)}; the paper's holder was new):", ""]
        lines += std_table(rows, corners, set(subset))
    lines += [""] + per_difficulty(rows, corners)
    # failures: images lost by the image processing, then per method
    lost = [c for c in corners if c["reason"]]
    lines += ["", f"Images lost by the image processing: {len(lost)} of {len(corners)}", ""]
    for k, v in Counter((c["difficulty"], _reason_class(c["reason"])) for c in lost).most_common():
        lines.append(f"- {k[0]}: {k[1]}: {v}")
    lost_ids = {c["trial"] for c in lost}
    per = Counter((f["method"], _reason_class(f["reason"])) for f in fails
                  if f["trial"] not in lost_ids)
    if per:
        lines += ["", "Poses refused or wrong with features found (method: reason: images):", ""]
        for (m, why), v in sorted(per.items()):
            lines.append(f"- {m}: {why}: {v}")
    # corners per difficulty
    lines += ["", "| difficulty | n | lost | contour / model segmentation | corner RMS px refined "
              "median / p95 / max | paper threshold lines median |", "|---|---|---|---|---|---|"]
    by: dict = {}
    for c in corners:
        by.setdefault(c["difficulty"], []).append(c)
    for d, cs in sorted(by.items()):
        a = np.array([float(c["rms_refined_px"]) for c in cs])
        b = np.array([float(c["rms_threshold_px"]) for c in cs])
        seg = Counter(c.get("segmentation", "") for c in cs if not c["reason"])
        lines.append(f"| {d} | {len(cs)} | {sum(1 for c in cs if c['reason'])} | "
                     f"{seg.get('contour', 0)} / {seg.get('model', 0)} | {_q(a, 50)} / {_q(a, 95)}"
                     f" / {_q(a, 100)} | {_q(b, 50)} |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("folder")
    ap.add_argument("--out", default="results/images")
    ap.add_argument("--methods", default=METHODS)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--paper-segmentation", action="store_true",
                    help="no model-guided fallback (the paper's segmentation or nothing)")
    ap.add_argument("--report-only", action="store_true")
    a = ap.parse_args()
    out = Path(a.out)
    if not a.report_only:
        from cutterpose.experiments.images import run_images
        from cutterpose.image import FeatureParams

        params = FeatureParams(model_fallback="none" if a.paper_segmentation else "homography")
        run_images(a.folder, a.methods.split(","), out, workers=a.workers, params=params)
    text = report(out)
    (out / "table2.md").write_text(text + "\n")
    print(text)


if __name__ == "__main__":
    main()
