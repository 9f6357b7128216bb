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
  refusals were needed.

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
from .report import DOF_NAMES, DOF_UNITS, ERR_COLUMNS, read_trials_csv

__all__ = ["field_stats", "field_markdown", "BAD_TRANS_MM", "BAD_ROT_DEG"]

#: an accepted pose beyond these is a wrong pose handed to the robot (issue 10)
BAD_TRANS_MM = 1.0
BAD_ROT_DEG = 0.5


def _read_verdicts(folder: Path) -> dict:
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
    verdicts = _read_verdicts(folder)
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
        })
    return out


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
