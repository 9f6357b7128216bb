"""Per-trial results and their summaries, in the formats of ``PROTOCOL.md``.

Every experiment (synthetic sweep, rendered images) produces rows of the protocol's
``trials.csv`` (one per trial and method) and summarises them the same way: standard deviation
per DOF over the non-failed trials and over all trials with a pose, bias, gross failures,
median and 95th percentile of the geodesic rotation and translation errors, median solve time.
Failures are counted, never dropped: a method that raised or refused is a failed row with empty
error columns.
"""

from __future__ import annotations

import csv
import json
import math
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from ..geometry.pose import pose_errors

TRIAL_COLUMNS = ["trial", "sigma_px", "method", "alpha_err_deg", "beta_err_deg", "gamma_err_deg",
                 "X_err_mm", "Y_err_mm", "Z_err_mm", "rot_err_deg", "trans_err_mm", "failed",
                 "time_ms"]
DOF_NAMES = ["alpha", "beta", "gamma", "X", "Y", "Z"]
DOF_UNITS = ["deg", "deg", "deg", "mm", "mm", "mm"]
ERR_COLUMNS = TRIAL_COLUMNS[3:9]
#: ``experiment images``' budgets.csv: the error budget's std per DOF, in ERR_COLUMNS' order
BUDGET_STD_COLUMNS = ("std_alpha_deg", "std_beta_deg", "std_gamma_deg", "std_X_mm", "std_Y_mm",
                      "std_Z_mm")


def trial_rows(trial, sigma_px, method: str, R_true, t_true_mm, R_est, t_est_mm,
               time_ms) -> list[dict]:
    """Protocol rows for a batch of trials of one method.

    ``R_est``/``t_est_mm`` hold NaN where the method gave no pose (it raised or refused); those rows
    are failed with empty error columns.
    """
    err = pose_errors(R_true, t_true_mm, R_est, t_est_mm)
    trial = np.atleast_1d(trial)
    sigma = np.broadcast_to(np.asarray(sigma_px, float), trial.shape)
    time_ms = np.broadcast_to(np.asarray(time_ms, float), trial.shape)
    rows = []
    for i in range(len(trial)):
        has_pose = bool(np.all(np.isfinite(err.dof[i])))
        row = {"trial": int(trial[i]), "sigma_px": float(sigma[i]), "method": method}
        for k, col in enumerate(ERR_COLUMNS):
            row[col] = float(err.dof[i, k]) if has_pose else math.nan
        row["rot_err_deg"] = float(err.rot_deg[i]) if has_pose else math.nan
        row["trans_err_mm"] = float(err.trans_mm[i]) if has_pose else math.nan
        row["failed"] = int(err.failed[i])
        row["time_ms"] = float(time_ms[i])
        rows.append(row)
    return rows


def csv_cell(v) -> str:
    """One CSV cell: text as is, integers plainly, other numbers to 9 digits, NaN / None
    empty."""
    if isinstance(v, str):
        return v
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if v is None or not math.isfinite(v):
        return ""
    return f"{v:.9g}"


def write_trials_csv(rows: Iterable[dict], path) -> None:
    """Write protocol rows; NaN (no pose, unknown sigma) is written as an empty cell."""
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(TRIAL_COLUMNS)
        for r in rows:
            w.writerow([csv_cell(r[c]) for c in TRIAL_COLUMNS])


def read_trials_csv(path) -> list[dict]:
    """Read a ``trials.csv`` back; empty cells become NaN."""
    out = []
    with open(path, newline="") as fh:
        for r in csv.DictReader(fh):
            row = {"trial": int(r["trial"]), "method": r["method"], "failed": int(r["failed"])}
            for c in TRIAL_COLUMNS:
                if c not in row:
                    row[c] = float(r[c]) if r[c] != "" else math.nan
            out.append(row)
    return out


def summarize(rows: list[dict]) -> list[dict]:
    """Statistics per (sigma, method), in first-seen method order and ascending sigma.

    Keys: ``sigma_px, method, n, failed, no_pose, std (6), std_all (6), bias (6),
    rot_median, rot_p95, trans_median, trans_p95, time_median_ms``. ``std`` is over the
    non-failed trials; ``std_all`` over every trial that has a pose (failed ones included).
    """
    methods = list(dict.fromkeys(r["method"] for r in rows))
    sig_keys = sorted({_sigma_key(r["sigma_px"]) for r in rows},
                      key=lambda s: (math.isnan(s), s))
    stats = []
    for s in sig_keys:
        for m in methods:
            sel = [r for r in rows if r["method"] == m and _same(_sigma_key(r["sigma_px"]), s)]
            if not sel:
                continue
            E = np.array([[r[c] for c in ERR_COLUMNS] for r in sel], float)
            failed = np.array([r["failed"] for r in sel], bool)
            has = np.all(np.isfinite(E), axis=1)
            good = has & ~failed
            rot = np.array([r["rot_err_deg"] for r in sel], float)[has]
            trans = np.array([r["trans_err_mm"] for r in sel], float)[has]
            tms = np.array([r["time_ms"] for r in sel], float)
            stats.append({
                "sigma_px": s, "method": m, "n": len(sel), "failed": int(failed.sum()),
                "no_pose": int((~has).sum()),
                "std": _std(E[good]), "std_all": _std(E[has]), "bias": _mean(E[good]),
                "rot_median": _pct(rot, 50), "rot_p95": _pct(rot, 95),
                "trans_median": _pct(trans, 50), "trans_p95": _pct(trans, 95),
                "time_median_ms": _pct(tms[np.isfinite(tms)], 50),
            })
    return stats


def _sigma_key(s):
    return round(float(s), 6) if s is not None and math.isfinite(float(s)) else math.nan


def _same(a, b):
    return (math.isnan(a) and math.isnan(b)) or a == b


def _std(E):
    return (E.std(axis=0, ddof=1) if len(E) > 1 else np.full(6, np.nan)).tolist()


def _mean(E):
    return (E.mean(axis=0) if len(E) else np.full(6, np.nan)).tolist()


def _pct(a, q):
    return float(np.percentile(a, q)) if len(a) else math.nan


def _cell(v, digits=3):
    return "-" if v is None or not math.isfinite(v) else f"{v:.{digits}f}"


def summary_markdown(stats: list[dict], crlb: dict | None = None, title: str = "Summary",
                     notes: str = "") -> str:
    """Markdown tables of :func:`summarize`'s output.

    ``crlb`` maps a sigma to the 6 bound values (std of an efficient estimator); it is shown as a
    ``CRLB`` row under each sigma.
    """
    head = ("| sigma px | method | " + " | ".join(f"{d} {u}" for d, u in zip(DOF_NAMES, DOF_UNITS))
            + " | failed | median ms |")
    sep = "|" + "---|" * (head.count("|") - 1)
    lines = [f"# {title}", ""]
    if notes:
        lines += [notes, ""]
    lines += ["## Standard deviation of the error per DOF (non-failed trials)", "",
              "A gross failure is rotation error > 2 deg or translation error > 10 mm, or no pose. "
              "`failed` counts them out of `n`.", "", head, sep]
    last = None
    for st in stats:
        s = st["sigma_px"]
        if crlb is not None and last is not None and not _same(last, s):
            lines += _crlb_row(last, crlb)
        last = s
        lines.append(f"| {_cell(s, 1)} | {st['method']} | "
                     + " | ".join(_cell(v) for v in st["std"])
                     + f" | {st['failed']}/{st['n']} | {_cell(st['time_median_ms'], 2)} |")
    if crlb is not None and last is not None:
        lines += _crlb_row(last, crlb)
    if crlb:
        lines += ["", "## Efficiency: std / CRLB per DOF (non-failed trials; 1.00 is the bound)",
                  "", "| sigma px | method | " + " | ".join(DOF_NAMES) + " | worst |",
                  "|---|---|" + "---|" * 7]
        for st in stats:
            b = crlb.get(st["sigma_px"])
            if not b:
                continue
            r = [a / c if c > 0 else math.nan for a, c in zip(st["std"], b)]
            worst = max((abs(x - 1) for x in r if math.isfinite(x)), default=math.nan)
            lines.append(f"| {_cell(st['sigma_px'], 1)} | {st['method']} | "
                         + " | ".join(_cell(x, 2) for x in r) + f" | {_cell(worst + 1, 2)} |")
    lines += ["", "## Over all trials with a pose (failed included), bias, error quantiles", "",
              "| sigma px | method | std_all " + " ".join(DOF_NAMES) + " | bias "
              + " ".join(DOF_NAMES) + " | no pose | rot med / p95 deg | trans med / p95 mm |",
              "|---|---|---|---|---|---|---|"]
    for st in stats:
        lines.append(
            f"| {_cell(st['sigma_px'], 1)} | {st['method']} | "
            + " ".join(_cell(v) for v in st["std_all"]) + " | "
            + " ".join(_cell(v, 4) for v in st["bias"])
            + f" | {st['no_pose']} | {_cell(st['rot_median'])} / {_cell(st['rot_p95'])} | "
            f"{_cell(st['trans_median'])} / {_cell(st['trans_p95'])} |")
    return "\n".join(lines) + "\n"


def _crlb_row(s, crlb):
    b = crlb.get(s)
    if b is None:
        return []
    return [f"| {_cell(s, 1)} | *CRLB* | " + " | ".join(_cell(v) for v in b) + " | | |"]


def write_summary(stats: list[dict], out_dir, crlb: dict | None = None,
                  title: str = "Summary", notes: str = "") -> None:
    """``summary.md`` (for people) and ``summary.json`` (for programs) in ``out_dir``."""
    out_dir = Path(out_dir)
    md = summary_markdown(stats, crlb, title, notes)
    (out_dir / "summary.md").write_text(md)
    payload = {"stats": stats, "crlb": [{"sigma_px": k, "std": v} for k, v in (crlb or {}).items()]}
    (out_dir / "summary.json").write_text(json.dumps(_finite(payload), indent=1))


def _finite(o):
    """JSON has no NaN: write null instead."""
    if isinstance(o, dict):
        return {k: _finite(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_finite(v) for v in o]
    if isinstance(o, (np.floating, float)):
        return float(o) if math.isfinite(o) else None
    if isinstance(o, np.integer):
        return int(o)
    return o
