"""The field table (issue 10): what each method does on sets of worn holders, with its verdict.

Input: the output folders of ``cutterpose experiment images`` (``trials.csv`` with the errors of
every pose, refused ones included, and ``verdicts.csv`` with the measurement's own verdict), one
per image set (e.g. ``sharp``, ``new``, ``worn``). Per set and method the table gives

* how many images were measured and accepted, how many refused (and why, grouped), how many gave
  no pose at all;
* over the accepted images: bias (mean error) and standard deviation per DOF, the 95th
  percentile of the geodesic rotation error and of the translation error norm, and their maxima;
* the accepted images that the robot should not have been given: translation error > 1 mm or
  rotation error > 0.5 deg (the issue's hard limit), counted;
* over the refused images with a pose: their median translation error, to show whether the
  refusals were needed;
* whether the error budget describes the actual error (``budgets.csv``), over every image with
  a pose, accepted or refused: the errors within its 3-sigma figures, the median of
  ``|e_k| / sigma_k`` per DOF (0.674 when the budget is the error's covariance) and the median
  squared Mahalanobis distance (5.35, the median of chi-square with 6 degrees of freedom). A
  budget much wider than the errors refuses good poses; a narrower one accepts bad ones;
* on a set that shows each holder from several poses (``render-set --views``): how many
  holders a robot that retakes a refused measurement gets within 1, 2, ... views, and the
  errors of the view it would use.

Convention:
    Errors as in PROTOCOL.md (estimate - truth, degrees and mm); nothing is dropped: an image
    without a pose counts as refused.
"""

from __future__ import annotations

import csv
import json
import math
import re
from collections import Counter
from pathlib import Path

import numpy as np

from ..errors import InputError
from .report import BUDGET_STD_COLUMNS, DOF_NAMES, DOF_UNITS, ERR_COLUMNS, read_trials_csv

__all__ = ["field_stats", "field_markdown", "BAD_TRANS_MM", "BAD_ROT_DEG", "read_verdicts",
           "read_budgets", "csv_number"]

#: an accepted pose beyond these is a wrong pose handed to the robot (issue 10)
BAD_TRANS_MM = 1.0
BAD_ROT_DEG = 0.5


def read_verdicts(folder: Path) -> dict:
    path = folder / "verdicts.csv"
    if not path.is_file():
        raise InputError(f"{folder}: no verdicts.csv (run `cutterpose experiment images` into it)")
    with open(path, newline="") as fh:
        return {(int(r["trial"]), r["method"]): (r["accepted"] == "1", r["reason"])
                for r in csv.DictReader(fh)}


def _reason_class(reason: str) -> str:
    """A refusal reason without its numbers, to group them."""
    head = reason.split(":")[0] if reason.startswith(("FeatureError", "ImageError")) else reason
    return re.sub(r"[-+]?\d+(\.\d+)?", "#", head)[:70]


def field_stats(folder, name: str | None = None) -> list[dict]:
    """Statistics per method of one ``experiment images`` output folder (module docstring)."""
    folder = Path(folder)
    verdicts = read_verdicts(folder)
    budgets = read_budgets(folder)
    views = _read_views(folder)
    rows = read_trials_csv(folder / "trials.csv")
    out = []
    for m in dict.fromkeys(r["method"] for r in rows):
        sel = [r for r in rows if r["method"] == m]
        acc = np.array([verdicts.get((int(r["trial"]), m), (False, ""))[0] for r in sel])
        E = np.array([[float(r[c]) for c in ERR_COLUMNS] for r in sel], float)
        rot = np.array([float(r["rot_err_deg"]) for r in sel])
        trans = np.array([float(r["trans_err_mm"]) for r in sel])
        has = np.all(np.isfinite(E), axis=1)
        a = acc & has
        bad = a & ((trans > BAD_TRANS_MM) | (rot > BAD_ROT_DEG))
        reasons = Counter(_reason_class(verdicts.get((int(r["trial"]), m), (False, "?"))[1])
                          for r, ok in zip(sel, acc) if not ok)
        ref_pose = ~acc & has
        honesty = _budget_honesty(budgets, sel, m, E, rot, trans, acc)
        retake = _retakes(views, sel, acc & has, rot, trans)
        out.append({
            "set": name or folder.name, "method": m, "n": len(sel),
            "accepted": int(a.sum()), "refused": int((~acc).sum()),
            "no_pose": int((~has).sum()),
            "bias": _agg(E[a], np.mean), "std": _agg(E[a], lambda x, axis: x.std(axis, ddof=1)),
            "rot_p95_deg": _pct(rot[a], 95), "trans_p95_mm": _pct(trans[a], 95),
            "rot_max_deg": float(rot[a].max()) if a.any() else math.nan,
            "trans_max_mm": float(trans[a].max()) if a.any() else math.nan,
            "accepted_bad": int(bad.sum()),
            "refused_trans_median_mm": _pct(trans[ref_pose], 50),
            "refusals": dict(reasons.most_common()),
            **honesty, **retake,
        })
    return out


def _read_views(folder: Path) -> dict:
    """{trial: (holder, view)} from ``corners.csv`` for a set rendered with ``--views``."""
    path = folder / "corners.csv"
    if not path.is_file():
        return {}
    with open(path, newline="") as fh:
        return {int(r["trial"]): (int(r["holder_index"]), int(r["view"]))
                for r in csv.DictReader(fh) if r.get("holder_index") not in (None, "")}


def _retakes(views: dict, sel: list, acc, rot, trans) -> dict:
    """What a robot that retakes a refused measurement gets, on a set that shows each holder
    from several poses (views in their order: the first look, then the retakes): per ``k``,
    the holders with an accepted view among their first ``k``; and the errors of the view it
    would use (the first accepted), with how many of those are beyond 1 mm / 0.5 deg."""
    if not views:
        return {}
    trials = [int(r["trial"]) for r in sel]
    by_holder: dict = {}
    for j, t in enumerate(trials):
        if t in views:
            h, v = views[t]
            by_holder.setdefault(h, []).append((v, j))
    if not by_holder:
        return {}
    k_max = max(len(v) for v in by_holder.values())
    within = [0] * k_max
    used = []
    for vs in by_holder.values():
        vs.sort()
        first = next((k for k, (_, j) in enumerate(vs) if acc[j]), None)
        if first is not None:
            for k in range(first, k_max):
                within[k] += 1
            used.append(vs[first][1])
    used = np.array(used, int)
    return {"holders": len(by_holder), "accepted_within_views": within,
            "retake_rot_max_deg": float(rot[used].max()) if len(used) else math.nan,
            "retake_trans_max_mm": float(trans[used].max()) if len(used) else math.nan,
            "retake_trans_p95_mm": _pct(trans[used], 95),
            "retake_rot_p95_deg": _pct(rot[used], 95),
            "retake_bad": int(((trans[used] > BAD_TRANS_MM) | (rot[used] > BAD_ROT_DEG)).sum())
            if len(used) else 0}


def read_budgets(folder: Path) -> dict:
    """``budgets.csv`` as {(trial, method): row}; {} when absent (older runs)."""
    path = folder / "budgets.csv"
    if not path.is_file():
        return {}
    with open(path, newline="") as fh:
        return {(int(r["trial"]), r["method"]): r for r in csv.DictReader(fh)}


def csv_number(row: dict, col: str) -> float:
    v = row.get(col, "") if row else ""
    return float(v) if v not in ("", None) else math.nan


def _budget_honesty(budgets: dict, sel: list, m: str, E, rot, trans, acc) -> dict:
    """Does the budget describe the actual error? Over every image with a pose and a budget
    (accepted and refused alike): how many errors lie within the 3-sigma figures (rotation and
    translation at the grasp point, the origin by default), the median ``|e_k| / sigma_k`` per
    DOF (0.674 for a budget that is the error's covariance; smaller: the budget is wider than
    the errors), and the median squared Mahalanobis distance (5.35 for 6 DOF)."""
    b = [budgets.get((int(r["trial"]), m)) for r in sel]
    S = np.array([[csv_number(x, c) for c in BUDGET_STD_COLUMNS] for x in b], float).reshape(-1, 6)
    d2 = np.array([csv_number(x, "mahalanobis2") for x in b], float)
    pos3 = np.array([csv_number(x, "position_3sigma_mm") for x in b], float)
    ang3 = np.array([csv_number(x, "angle_3sigma_deg") for x in b], float)
    ok = np.all(np.isfinite(E), axis=1) & np.all(np.isfinite(S), axis=1) & (S > 0).all(axis=1)
    if not ok.any():
        return {"budget_n": 0}
    z = np.abs(E[ok]) / S[ok]
    cov = (rot[ok] <= ang3[ok]) & (trans[ok] <= pos3[ok])
    acc_ok = acc[ok]
    return {"budget_n": int(ok.sum()), "budget_covered": int(cov.sum()),
            "budget_covered_accepted": int((cov & acc_ok).sum()),
            "budget_accepted": int(acc_ok.sum()),
            "z_median": np.median(z, axis=0).tolist(),
            "z_max": z.max(axis=0).tolist(),
            "mahalanobis2_median": _pct(d2[ok][np.isfinite(d2[ok])], 50)}


def _agg(E, fn):
    return fn(E, axis=0).tolist() if len(E) > 1 else [math.nan] * 6


def _pct(a, q):
    return float(np.percentile(a, q)) if len(a) else math.nan


def _c(v, d=3):
    return "-" if v is None or not math.isfinite(v) else f"{v:.{d}f}"


def field_markdown(stats: list[dict]) -> str:
    """The field table: one row per set and method, then the refusal reasons."""
    dof = [f"{n} [{u}]" for n, u in zip(DOF_NAMES, DOF_UNITS)]
    head = ("| set | method | n | accepted | refused | bias " + " / ".join(DOF_NAMES)
            + " | std " + " / ".join(DOF_NAMES) + " | p95 rot [deg] | p95 trans [mm] "
            "| max rot / trans | accepted > 1 mm or 0.5 deg |")
    lines = [head, "|" + "---|" * 11]
    for s in stats:
        lines.append(
            f"| {s['set']} | {s['method']} | {s['n']} | {s['accepted']} | {s['refused']} | "
            + " / ".join(_c(v) for v in s["bias"]) + " | "
            + " / ".join(_c(v) for v in s["std"]) + " | "
            f"{_c(s['rot_p95_deg'])} | {_c(s['trans_p95_mm'])} | "
            f"{_c(s['rot_max_deg'])} / {_c(s['trans_max_mm'])} | {s['accepted_bad']} |")
    lines += ["", f"Units: {', '.join(dof)}. Bias and std over the accepted images.", "",
              "Refusals (reason without its numbers: count); median translation error of the "
              "refused poses:", ""]
    for s in stats:
        if s["refused"]:
            rs = "; ".join(f"{k}: {v}" for k, v in s["refusals"].items())
            lines.append(f"- {s['set']} / {s['method']}: {rs} (refused poses: median "
                         f"{_c(s['refused_trans_median_mm'], 2)} mm)")
    hon = [s for s in stats if s.get("budget_n")]
    if hon:
        lines += ["", "The error budget against the actual error, over every image with a pose "
                  "and a budget (accepted and refused): errors within the 3-sigma figures; the "
                  "median |error| / std per DOF (0.67 when the budget is the error's "
                  "covariance, smaller when it is wider) and its maximum; the median squared "
                  "Mahalanobis distance (5.35 for 6 DOF).", "",
                  "| set | method | with budget | within 3 sigma (all; accepted) | median "
                  "\\|e\\|/std " + " / ".join(DOF_NAMES) + " | max \\|e\\|/std | median "
                  "Mahalanobis^2 |",
                  "|" + "---|" * 7]
        for s in hon:
            lines.append(
                f"| {s['set']} | {s['method']} | {s['budget_n']} | {s['budget_covered']}/"
                f"{s['budget_n']}; {s['budget_covered_accepted']}/{s['budget_accepted']} | "
                + " / ".join(_c(v, 2) for v in s["z_median"]) + " | "
                + " / ".join(_c(v, 1) for v in s["z_max"]) + " | "
                f"{_c(s['mahalanobis2_median'], 1)} |")
    ret = [s for s in stats if s.get("holders")]
    if ret:
        lines += ["", "Retakes (sets that show each holder from several poses): the holders "
                  "with an accepted measurement among their first k views, and the errors of "
                  "the view a robot that retakes until accepted would use.", "",
                  "| set | method | holders | accepted within 1 / 2 / ... views | p95 rot / "
                  "trans of the used view | max rot / trans | used > 1 mm or 0.5 deg |",
                  "|" + "---|" * 7]
        for s in ret:
            lines.append(
                f"| {s['set']} | {s['method']} | {s['holders']} | "
                + " / ".join(str(v) for v in s["accepted_within_views"]) + " | "
                f"{_c(s['retake_rot_p95_deg'])} / {_c(s['retake_trans_p95_mm'])} | "
                f"{_c(s['retake_rot_max_deg'])} / {_c(s['retake_trans_max_mm'])} | "
                f"{s['retake_bad']} |")
    return "\n".join(lines) + "\n"


def write_field(sets: dict[str, Path], out) -> list[dict]:
    """Field table of several result folders (``{set name: folder}``) into ``out`` (``field.md``,
    ``field.json``)."""
    stats = [s for name, folder in sets.items() for s in field_stats(folder, name)]
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "field.md").write_text(field_markdown(stats))
    (out / "field.json").write_text(json.dumps(stats, indent=1, allow_nan=True) + "\n")
    return stats
