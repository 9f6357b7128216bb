"""The real-image experiment (paper section 3.2, Table 2) on an image set.

An image set is a folder with ``truth.json`` (PROTOCOL.md, exchange formats). Each image goes
through the image processing once (:func:`cutterpose.image.features.detect_features`); every method
then solves from the same corners (:func:`cutterpose.pipeline.measure_features`): the
correspondence-free methods in contour order, the PnP methods after the contour-order
assignment of :func:`cutterpose.pipeline.order_for_model`. A method whose pose the quality
verdict refuses, or an image the image processing rejects, is a failed row with the reason in
``failures.csv``; nothing is dropped.

Outputs in ``out``: ``trials.csv`` (protocol columns, ``sigma_px`` empty), ``summary.md`` /
``summary.json`` (the shared report writers), ``corners.csv`` (per image: difficulty, RMS of the
detected corners against the true ones with and without the gradient refinement, threshold
used, segmentation: the paper's ``contour`` or the model-guided fallback ``model``; the holder
and view of a set rendered with ``--views``) and
``failures.csv`` (trial, method, reason), ``verdicts.csv`` (trial, method, accepted 0/1,
reason: the measurement's own verdict, whatever the truth says) and ``budgets.csv`` (trial,
method, the error budget's 3-sigma position at the grasp point and angle, its std per DOF and
the squared Mahalanobis distance of the actual error under it; empty without a pose: to check
that the budget describes the actual error, :mod:`cutterpose.experiments.field`).
"""

from __future__ import annotations

import csv
import math
import os
from dataclasses import replace
from pathlib import Path

import numpy as np

from ..errors import CutterposeError
from ..geometry.holder import Holder
from ..image import FeatureParams, detect_features, load_image
from ..image_set import load_image_set
from ..parallel import run_jobs
from ..pipeline import QualityLimits, measure_features
from .report import (
    BUDGET_STD_COLUMNS,
    ERR_COLUMNS,
    csv_cell,
    summarize,
    trial_rows,
    write_summary,
    write_trials_csv,
)

__all__ = ["load_image_set", "run_images", "corner_rms"]

PNP_METHODS = ("dlt", "epnp", "rpnp", "aspnp", "opnp")


def corner_rms(detected_px: np.ndarray, true_px: np.ndarray) -> float:
    """RMS distance of detected corners (contour order) to the true ones (model order), under
    the best cyclic shift and direction."""
    d = np.asarray(detected_px, float)
    t = np.asarray(true_px, float)
    best = math.inf
    for seq in (d, d[::-1]):
        for k in range(len(seq)):
            e = np.sqrt(np.mean(np.sum((np.roll(seq, -k, axis=0) - t) ** 2, axis=1)))
            best = min(best, float(e))
    return best


def _one_image(args):
    i, entry, folder, camera, holder, methods, params, limits, edge_look = args
    R = np.asarray(entry["R_cam_holder"], float)
    t = np.asarray(entry["t_cam_holder_mm"], float)
    out = {"trial": i, "rows": [], "failures": [], "corners": None, "verdicts": [],
           "budgets": []}
    info = {"trial": i, "file": entry["file"], "difficulty": entry.get("difficulty", ""),
            "threshold": "", "segmentation": "", "rms_refined_px": math.nan,
            "rms_threshold_px": math.nan, "reason": "",
            "holder_index": entry.get("holder_index", ""), "view": entry.get("view", "")}
    nan_R, nan_t = np.full((3, 3), np.nan), np.full(3, np.nan)

    def all_failed(reason):
        for m in methods:
            out["rows"] += trial_rows(i, math.nan, m, R, t, nan_R, nan_t, math.nan)
            out["failures"].append((i, m, reason))
            out["verdicts"].append((i, m, 0, reason))
            out["budgets"].append((i, m, "", ""))
        info["reason"] = reason
        out["corners"] = info

    try:
        img = load_image(Path(folder) / entry["file"])
        feats = detect_features(img, camera, holder, params)
    except CutterposeError as e:
        all_failed(f"{type(e).__name__}: {e}")
        return out
    info["threshold"] = feats.threshold
    info["segmentation"] = feats.segmentation
    if entry.get("corners_px") is not None:
        true_px = np.asarray(entry["corners_px"], float)
        info["rms_refined_px"] = corner_rms(feats.corners_px, true_px)
        # the paper's corners: the thresholded contour's lines, no gradient refinement
        from ..image.lines import intersect_consecutive
        info["rms_threshold_px"] = corner_rms(
            camera.distort_px(intersect_consecutive(feats.lines_threshold_ideal)), true_px)
    for m in methods:
        meas = measure_features(feats, camera, holder, m, limits, edge_look)
        ms = meas.timings_ms.get("solve", math.nan)
        if meas.pose is not None:
            rows = trial_rows(i, math.nan, m, R, t, meas.pose.R, meas.pose.t_mm, ms)
        else:
            rows = trial_rows(i, math.nan, m, R, t, nan_R, nan_t, ms)
        out["budgets"].append((i, m, *_budget_cells(meas.quality.budget, rows[0])))
        out["verdicts"].append((i, m, int(meas.ok), "" if meas.ok else meas.quality.reason))
        if not meas.ok:
            for r in rows:
                r["failed"] = 1
            out["failures"].append((i, m, meas.quality.reason))
        elif rows[0]["failed"]:
            out["failures"].append((i, m, f"gross error: rot {rows[0]['rot_err_deg']:.2f} deg, "
                                          f"trans {rows[0]['trans_err_mm']:.2f} mm"))
        out["rows"] += rows
    out["corners"] = info
    return out


def _budget_cells(budget, row: dict) -> list[str]:
    """budgets.csv cells of one pose: the 3-sigma figures, the std per DOF and the squared
    Mahalanobis distance of the actual error, ``e^T C^-1 e`` (chi-square with 6 degrees of
    freedom when the budget is the error's true covariance: median 5.35, 95 % below 12.6);
    empty where there is no budget (or no pose)."""
    if budget is None:
        return [""] * (3 + len(BUDGET_STD_COLUMNS))
    e = np.array([row[c] for c in ERR_COLUMNS], float)
    d2 = math.nan
    if np.all(np.isfinite(e)) and np.all(np.isfinite(budget.dof_cov)):
        try:
            d2 = float(e @ np.linalg.solve(budget.dof_cov, e))
        except np.linalg.LinAlgError:
            pass
    return ([f"{budget.position_3sigma_mm:.4f}", f"{budget.angle_3sigma_deg:.4f}"]
            + [csv_cell(float(v)) for v in budget.std_dof] + [csv_cell(d2)])


def run_images(folder, methods: list[str], out, workers: int = 1, params=None,
               limit: int | None = None, progress=None, scheduler=None,
               limits=None, edge_look=None) -> list[dict]:
    """Run every method on every image of a set; write the outputs (module doc) into ``out``.

    Images run in this process, in ``workers`` processes or on the Dask cluster at
    ``scheduler`` (:mod:`cutterpose.parallel`; the workers read the images, so the set must be
    at the same path on every worker, e.g. a shared file system); the outputs are the same.

    ``edge_look``: an edge look calibrated in the cell
    (:func:`cutterpose.calibration.edge_look.load_edge_look`) for ``dm+b``.

    Returns the summary statistics (:func:`cutterpose.experiments.report.summarize`).
    """
    from ..methods import get_method

    for m in methods:
        get_method(m)  # unknown names fail before any work
    camera, holder, entries = load_image_set(folder)
    if limit is not None:
        entries = entries[:limit]
    params = params or FeatureParams()
    limits = limits or QualityLimits()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    # the folder as the workers will see it: absolute, as on a shared file system
    jobs = [(i, e, str(Path(folder).resolve()), camera, holder, list(methods), params, limits,
             edge_look) for i, e in enumerate(entries)]
    count = [0]

    def done(i, _):
        count[0] += 1
        if progress:
            progress(count[0], len(jobs))

    results = run_jobs(_one_image, jobs, workers, scheduler, done)
    rows = [r for res in results for r in res["rows"]]
    order = {m: k for k, m in enumerate(methods)}
    rows.sort(key=lambda r: (order[r["method"]], r["trial"]))
    write_trials_csv(rows, out / "trials.csv")
    with open(out / "failures.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["trial", "method", "reason"])
        for res in results:
            w.writerows(res["failures"])
    with open(out / "verdicts.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["trial", "method", "accepted", "reason"])
        for res in results:
            w.writerows(res["verdicts"])
    with open(out / "budgets.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["trial", "method", "position_3sigma_mm", "angle_3sigma_deg",
                    *BUDGET_STD_COLUMNS, "mahalanobis2"])
        for res in results:
            w.writerows(res["budgets"])
    cols = ["trial", "file", "difficulty", "threshold", "segmentation", "rms_refined_px",
            "rms_threshold_px", "reason", "holder_index", "view"]
    with open(out / "corners.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, cols)
        w.writeheader()
        for res in results:
            w.writerow(res["corners"])
    stats = summarize(rows)
    write_summary(stats, out, title=f"Image set {Path(folder).name}: Table 2 figures",
                  notes=_notes(results, holder))
    return stats


def _q(x, q) -> str:
    if not np.isfinite(x).any():
        return "-"
    # an image whose corners were not all found has an infinite RMS: a quantile that falls
    # between two of them is inf (numpy's interpolation would give inf - inf = NaN)
    with np.errstate(invalid="ignore"):
        v = np.nanpercentile(x, q)
    return "inf" if np.isnan(v) else f"{v:.3f}"


def _notes(results, holder: Holder) -> str:
    info = [r["corners"] for r in results]
    by = {}
    for c in info:
        by.setdefault(c["difficulty"] or "-", []).append(c)
    lines = [f"{len(info)} images; detected corners vs true corners (RMS px, median per "
             "difficulty; refined = gradient refinement, threshold = the paper's contour lines):",
             "", "| difficulty | n | lost | refined median | refined p95 | threshold median |",
             "|---|---|---|---|---|---|"]
    for k, cs in sorted(by.items()):
        a = np.array([c["rms_refined_px"] for c in cs], float)
        b = np.array([c["rms_threshold_px"] for c in cs], float)
        lost = sum(1 for c in cs if c["reason"])
        lines.append(f"| {k} | {len(cs)} | {lost} | {_q(a, 50)} | {_q(a, 95)} | {_q(b, 50)} |")
    return "\n".join(lines)


def default_workers() -> int:
    return max(1, min(2, os.cpu_count() or 1))


def no_refine(params: FeatureParams | None = None) -> FeatureParams:
    """The paper's processing without the gradient refinement."""
    return replace(params or FeatureParams(), refine=False)
