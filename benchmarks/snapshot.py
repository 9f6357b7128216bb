"""The same measurements before and after a change of the code: every registered method on a
fixed image set, through the Python API, stored in full precision and compared.

Usage (``SETS_DIR`` holds the rendered sets ``new``, ``mix``, ``worn``, ``field``, ``pbr``, each
from ``cutterpose render-set``; docs/results/method_shape.md gives the commands)::

    PYTHONPATH=<old>/src python benchmarks/snapshot.py SETS_DIR before.json [--sharp]
    PYTHONPATH=<new>/src python benchmarks/snapshot.py SETS_DIR after.json [--sharp]
    python benchmarks/snapshot.py --compare before.json after.json

Per measurement: the pose (DOFs and rotation, full precision), the verdict, its reason and note,
the std, RMS residual, ambiguity and the error budget (3-sigma figures, radius, each part's
figures, the covariance). ``--sharp``: the corner methods only, with a sharp edge
(``edge_break_mm=0``), where they are accepted and their own checks run. ``--compare``: poses,
std and budget figures to 1e-9 (relative to max(1, |x|)), verdicts, reasons and notes
identical; exit 1 on any difference.
"""

from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path

import numpy as np

SETS = ["new", "mix", "worn", "field", "pbr"]
EXTRA = ["epnp+lm", "opnp+lm"]


def _f(x):
    x = float(x)
    return x if math.isfinite(x) else repr(x)


def record(m) -> dict:
    q = m.quality
    d = {"ok": bool(q.ok), "reason": q.reason, "note": q.note,
         "pose_dof": None if m.pose is None else [_f(v) for v in m.pose.dof],
         "R": None if m.pose is None else [_f(v) for v in np.ravel(m.pose.R)],
         "std": [_f(v) for v in m.std_dof], "rms_px": _f(q.rms_px),
         "ambiguity": _f(q.ambiguity_ratio)}
    b = q.budget
    if b is not None:
        d["budget"] = {"pos3": _f(b.position_3sigma_mm), "ang3": _f(b.angle_3sigma_deg),
                       "radius": _f(b.radius_mm), "radius_std": _f(b.radius_std_mm),
                       "parts": {k: [_f(v[0]), _f(v[1])] for k, v in b.per_part_3sigma.items()},
                       "cov": [_f(v) for v in np.ravel(b.dof_cov)]}
    return d


def snapshot(sets_dir: Path, out: str, sharp: bool = False) -> None:
    from cutterpose.geometry.camera import default_camera
    from cutterpose.geometry.holder import default_holder
    from cutterpose.image import FeatureParams
    from cutterpose.methods import available_methods
    from cutterpose.pipeline import measure

    cam, holder = default_camera("table1"), default_holder()
    methods = list(available_methods()) + EXTRA
    limits = None
    if sharp:  # the corner methods on a sharp edge: their accepted verdicts and line check
        from cutterpose.pipeline import QualityLimits

        methods = [m for m in methods if m not in ("dm+r", "dm+b")]
        limits = QualityLimits(edge_break_mm=0.0)
    res = {"methods": methods, "images": {}}
    t0 = time.time()
    for s in (["new", "mix"] if sharp else SETS):
        folder = sets_dir / s
        if not folder.exists():
            continue
        for img in sorted(folder.glob("img_*.png")):
            key = f"{s}/{img.name}"
            chains = {"field": None}
            if s == "new":
                chains["paper"] = FeatureParams.paper()
            for chain, params in chains.items():
                for meth in methods:
                    m = measure(img, cam, holder, meth, params, limits)
                    res["images"][f"{key}|{chain}|{meth}"] = record(m)
            print(key, f"{time.time() - t0:.0f}s", flush=True)
    Path(out).write_text(json.dumps(res, indent=0))


def _close(a, b, tol):
    if isinstance(a, str) or isinstance(b, str):
        return a == b
    return abs(a - b) <= tol * max(1.0, abs(a), abs(b))


def compare(pa: str, pb: str) -> int:
    A, B = json.loads(Path(pa).read_text()), json.loads(Path(pb).read_text())
    bad = 0
    keys = sorted(set(A["images"]) | set(B["images"]))
    n_ok = 0
    for k in keys:
        a, b = A["images"].get(k), B["images"].get(k)
        if a is None or b is None:
            print("missing", k)
            bad += 1
            continue
        diffs = []
        for f in ("ok", "reason", "note"):
            if a[f] != b[f]:
                diffs.append(f"{f}: {a[f]!r} != {b[f]!r}")
        for f in ("pose_dof", "R", "std", "rms_px", "ambiguity"):
            va, vb = a[f], b[f]
            if (va is None) != (vb is None):
                diffs.append(f"{f} presence")
            elif va is not None:
                la = va if isinstance(va, list) else [va]
                lb = vb if isinstance(vb, list) else [vb]
                if not all(_close(x, y, 1e-9) for x, y in zip(la, lb)):
                    diffs.append(f"{f}: {va} != {vb}")
        ba, bb = a.get("budget"), b.get("budget")
        if (ba is None) != (bb is None):
            diffs.append("budget presence")
        elif ba is not None:
            for f in ("pos3", "ang3", "radius", "radius_std"):
                if not _close(ba[f], bb[f], 1e-9):
                    diffs.append(f"budget {f}: {ba[f]} != {bb[f]}")
            if ba["parts"].keys() != bb["parts"].keys():
                diffs.append("budget parts")
            else:
                for part, fa in ba["parts"].items():
                    if not all(_close(x, y, 1e-9) for x, y in zip(fa, bb["parts"][part])):
                        diffs.append(f"budget part {part}: {fa} != {bb['parts'][part]}")
            if not all(_close(x, y, 1e-9) for x, y in zip(ba["cov"], bb["cov"])):
                diffs.append("budget covariance")
        if diffs:
            bad += 1
            print(k, "; ".join(diffs)[:400])
        n_ok += a["ok"]
    print(f"{len(keys)} measurements compared, {n_ok} accepted, {bad} differ")
    return 1 if bad else 0


if __name__ == "__main__":
    if sys.argv[1] == "--compare":
        sys.exit(compare(sys.argv[2], sys.argv[3]))
    snapshot(Path(sys.argv[1]), sys.argv[2], sharp="--sharp" in sys.argv)
