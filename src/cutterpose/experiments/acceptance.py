"""What the verdict's tolerance buys: acceptance and accepted errors against the angle tolerance.

The verdict accepts a pose when the error budget's worst-direction 3-sigma position at the
grasp point is within the position tolerance and its 3-sigma rotation within the angle
tolerance (:class:`cutterpose.budget.Tolerance`: 1 mm, 0.3 deg). A cell whose gripper takes a
different angle asks what another tolerance would give. From the output of ``cutterpose
experiment images`` (``trials.csv``, ``verdicts.csv``, ``budgets.csv``) this re-applies the
verdict at each angle tolerance, without measuring again, and gives per tolerance the images
accepted, the p95 and largest rotation and translation errors over them and the accepted ones
beyond 1 mm or 0.5 deg (:data:`cutterpose.experiments.field.BAD_TRANS_MM`,
:data:`~cutterpose.experiments.field.BAD_ROT_DEG`).

Two ceilings come with it, set by the poses and not by any verdict:

* ``ceiling_good``: images whose *actual* error is within 1 mm and 0.5 deg: the most a verdict
  that never hands the robot a wrong pose could accept;
* ``ceiling_p95_0p1``: images whose actual error is within 0.1 deg (and 1 mm), divided by 0.95:
  the most that could be accepted with a p95 rotation error of 0.1 deg over the accepted.

Convention:
    Errors as in PROTOCOL.md. An image refused for anything but the budget (no pose, no
    features, "pose too uncertain", ...) stays refused at every tolerance; an image without a
    budget has none to re-apply. Tolerances are 3-sigma figures, like the verdict's.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from ..budget import Tolerance
from ..errors import InputError
from .field import BAD_ROT_DEG, BAD_TRANS_MM, csv_number, read_budgets, read_verdicts
from .report import read_trials_csv

__all__ = ["acceptance_curve", "acceptance_markdown", "write_acceptance",
           "DEFAULT_TOLERANCES_DEG"]

DEFAULT_TOLERANCES_DEG = (0.2, 0.25, 0.3, 0.35, 0.4, 0.45, 0.5)
#: the verdict's own position tolerance (3 sigma at the grasp point, mm)
POSITION_TOL_MM = Tolerance().position_mm
#: the verdict's refusals that a tolerance decides (budget.ErrorBudget.reason)
BUDGET_REASON = "error budget:"


def acceptance_curve(folder, method: str = "dm+b", tolerances_deg=DEFAULT_TOLERANCES_DEG,
                     position_mm: float = POSITION_TOL_MM, name: str | None = None) -> dict:
    """The verdict re-applied at each angle tolerance (module doc) for one results folder.

    Returns
    -------
    dict : ``set``, ``method``, ``n``, ``accepted_by_verdict`` (the run's own verdicts),
        ``rows`` (one per tolerance: ``angle_tol_deg``, ``accepted``, ``rot_p95_deg``,
        ``trans_p95_mm``, ``rot_max_deg``, ``trans_max_mm``, ``accepted_bad``),
        ``ceiling_good`` and ``ceiling_p95_0p1``.
    """
    folder = Path(folder)
    verdicts = read_verdicts(folder)
    budgets = read_budgets(folder)
    sel = [r for r in read_trials_csv(folder / "trials.csv") if r["method"] == method]
    if not sel:
        raise InputError(f"{folder}: no trials of method {method!r}")
    keys = [(int(r["trial"]), method) for r in sel]
    rot = np.array([float(r["rot_err_deg"]) for r in sel])
    trans = np.array([float(r["trans_err_mm"]) for r in sel])
    has = np.isfinite(rot) & np.isfinite(trans)
    verdict = [verdicts.get(k, (False, "no verdict")) for k in keys]
    # refused for anything the tolerance does not decide: refused at every tolerance
    other = np.array([not ok and not reason.startswith(BUDGET_REASON) for ok, reason in verdict])
    pos3 = np.array([csv_number(budgets.get(k), "position_3sigma_mm") for k in keys])
    ang3 = np.array([csv_number(budgets.get(k), "angle_3sigma_deg") for k in keys])
    usable = has & ~other & np.isfinite(pos3) & np.isfinite(ang3)
    bad = (trans > BAD_TRANS_MM) | (rot > BAD_ROT_DEG)
    rows = []
    for tol in tolerances_deg:
        acc = usable & (pos3 <= position_mm) & (ang3 <= tol)
        r, t = rot[acc], trans[acc]
        rows.append({"angle_tol_deg": float(tol), "accepted": int(acc.sum()),
                     "rot_p95_deg": _pct(r, 95), "trans_p95_mm": _pct(t, 95),
                     "rot_max_deg": float(r.max()) if len(r) else math.nan,
                     "trans_max_mm": float(t.max()) if len(t) else math.nan,
                     "accepted_bad": int((acc & bad).sum())})
    good = has & ~bad
    fine = has & (rot <= 0.1) & (trans <= BAD_TRANS_MM)
    return {"set": name or folder.name, "method": method, "n": len(sel),
            "position_tol_mm": float(position_mm),
            "accepted_by_verdict": int(sum(ok for ok, _ in verdict)),
            "rows": rows, "ceiling_good": int(good.sum()),
            "ceiling_p95_0p1": min(len(sel), int(math.floor(fine.sum() / 0.95)))}


def _pct(a, q) -> float:
    return float(np.percentile(a, q)) if len(a) else math.nan


def _f(v, d=3) -> str:
    return "-" if not math.isfinite(v) else f"{v:.{d}f}"


def acceptance_markdown(curves: list[dict]) -> str:
    """One row per set and tolerance, then the ceilings."""
    lines = ["| set | method | images | angle tolerance (3 sigma) | accepted | p95 rot / trans "
             "over the accepted | max rot / trans | accepted > 1 mm or 0.5 deg |",
             "|---|---|---|---|---|---|---|---|"]
    for c in curves:
        for r in c["rows"]:
            lines.append(
                f"| {c['set']} | {c['method']} | {c['n']} | {r['angle_tol_deg']:.2f} deg | "
                f"{r['accepted']} ({100 * r['accepted'] / c['n']:.0f} %) | "
                f"{_f(r['rot_p95_deg'])} deg / {_f(r['trans_p95_mm'])} mm | "
                f"{_f(r['rot_max_deg'])} / {_f(r['trans_max_mm'])} | {r['accepted_bad']} |")
    lines += ["", "Ceilings set by the poses (no verdict can pass them):", "",
              "| set | method | images | actual error within 1 mm and 0.5 deg | most accepted "
              "with a p95 rotation error <= 0.1 deg | the run's own verdict accepted |",
              "|---|---|---|---|---|---|"]
    for c in curves:
        lines.append(f"| {c['set']} | {c['method']} | {c['n']} | {c['ceiling_good']} "
                     f"({100 * c['ceiling_good'] / c['n']:.0f} %) | {c['ceiling_p95_0p1']} "
                     f"({100 * c['ceiling_p95_0p1'] / c['n']:.0f} %) | "
                     f"{c['accepted_by_verdict']} |")
    return "\n".join(lines) + "\n"


def plot_acceptance(curves: list[dict], path) -> None:
    """Accepted share and the largest accepted rotation error against the angle tolerance."""
    from .plots import plt

    fig, (a1, a2) = plt.subplots(1, 2, figsize=(10, 4), constrained_layout=True)
    for c in curves:
        x = [r["angle_tol_deg"] for r in c["rows"]]
        label = f"{c['set']} ({c['method']})"
        a1.plot(x, [100 * r["accepted"] / c["n"] for r in c["rows"]], "o-", label=label)
        a2.plot(x, [r["rot_max_deg"] for r in c["rows"]], "o-", label=label)
    a1.axhline(90, color="k", ls="--", lw=0.8)
    a1.set(xlabel="angle tolerance, 3 sigma [deg]", ylabel="accepted [%]")
    a2.axhline(BAD_ROT_DEG, color="k", ls="--", lw=0.8)
    a2.set(xlabel="angle tolerance, 3 sigma [deg]",
           ylabel="largest accepted rotation error [deg]")
    for ax in (a1, a2):
        ax.axvline(Tolerance().angle_deg, color="grey", lw=0.8)   # the shipped line
        ax.grid(alpha=0.3)
    a1.legend(fontsize=8)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_acceptance(sets: dict, out, method: str = "dm+b",
                     tolerances_deg=DEFAULT_TOLERANCES_DEG, position_mm: float = POSITION_TOL_MM,
                     plot: bool = True) -> list[dict]:
    """``acceptance.md``, ``acceptance.json`` (and ``acceptance.png``) in ``out`` for
    ``{name: results folder}``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    curves = [acceptance_curve(folder, method, tolerances_deg, position_mm, name)
              for name, folder in sets.items()]
    (out / "acceptance.md").write_text(acceptance_markdown(curves))
    (out / "acceptance.json").write_text(json.dumps(curves, indent=1))
    if plot:
        plot_acceptance(curves, out / "acceptance.png")
    return curves
