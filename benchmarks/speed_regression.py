"""Accuracy guard for the speed work (issue 13): ``measure``'s corners and poses on a fixed image
list, recorded once and compared after every optimisation.

Images: the analytic presets easy, worn, occluded, hard, cutter and field at three poses each
(seeds 1-3; never the held-back seeds 900/901), the Table 1 camera, 4112 x 3008; plus every image
of the Mitsuba sets ``/work/data/pbr_*`` that exist (read only). Renders are cached as PNG in
``--cache`` (lossless: the same pixels as the render).

Per image it records the seen corners (observed px, NaN where not seen), the seen mask, and per
method (``dm+``, ``dm`` and, since the eleventh session, the default ``dm+b`` with the edge
break not declared, as ``measure`` runs it) the pose (6 DOF), the verdict and the per-stage
times; ``dm+b`` also its budget's std per DOF. ``--check`` compares with the
recording: corners within ``--tol-px`` (0.02 px), poses within ``--tol-mm`` (0.005 mm) and
``--tol-deg`` (0.001 deg), the same seen corners and the same verdict; it exits 1 otherwise.

The recording is of the code it was made with: re-record it right before the speed work it
is to guard. The one in the repository was made in the eleventh session (148 images: the 18
analytic ones and the dev pbr sets ``pbr_new_s200``, ``pbr_sharp_s100``, ``pbr_worn_s300``,
``dm+b`` included); the check is exact (0 differences) on the same machine and libraries.

Usage::

    python benchmarks/speed_regression.py --record benchmarks/speed_reference.json
    python benchmarks/speed_regression.py --check benchmarks/speed_reference.json

Convention:
    Poses as ``(alpha, beta, gamma [deg], X, Y, Z [mm])`` of ``T_cam_holder``
    (:mod:`cutterpose.geometry.pose`); corners in observed pixels of the full image.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_v] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

cv2.setNumThreads(1)

from cutterpose.geometry.camera import camera_from_dict, default_camera  # noqa: E402
from cutterpose.geometry.holder import default_holder  # noqa: E402
from cutterpose.geometry.pose import Pose  # noqa: E402
from cutterpose.image import load_image  # noqa: E402
from cutterpose.pipeline import QualityLimits, measure  # noqa: E402

PRESETS = ("easy", "worn", "occluded", "hard", "cutter", "field")
#: (alpha, beta, gamma deg, X, Y, Z mm), seed: within the real rig's working range
POSES = (((3.0, -4.0, 5.0, 10.0, -8.0, 610.0), 1),
         ((-6.0, 7.0, -2.0, -12.0, 9.0, 590.0), 2),
         ((8.0, 2.0, -7.0, 15.0, 14.0, 618.0), 3))
PBR_GLOB = "/work/data/pbr_*"
#: the verdict as it was when the reference was recorded: the corner methods' budget had no
#: part for an edge break (ninth session), so the images' edges are declared sharp
LIMITS = QualityLimits(edge_break_mm=0.0)
#: method -> limits; ``dm+b`` measures the break, so it runs with the defaults
METHODS = {"dm+": LIMITS, "dm": LIMITS, "dm+b": QualityLimits()}


def image_list(cache: Path):
    """(name, camera, image loader) of every image of the fixed list."""
    cam = default_camera("table1")
    out = []
    for preset in PRESETS:
        for dof, seed in POSES:
            name = f"{preset}_s{seed}"

            def load(preset=preset, dof=dof, seed=seed, name=name):
                path = cache / f"{name}.png"
                if not path.exists():
                    from cutterpose.render.analytic import render_holder

                    cache.mkdir(parents=True, exist_ok=True)
                    img = render_holder(Pose.from_euler(*dof), cam, default_holder(), preset,
                                        seed=seed).image
                    cv2.imwrite(str(path), img)
                return load_image(path)

            out.append((name, cam, load))
    for folder in sorted(Path("/").glob(PBR_GLOB.lstrip("/"))):
        truth = folder / "truth.json"
        if not truth.exists() or any(s in folder.name for s in ("900", "901", "heldback")):
            continue
        doc = json.loads(truth.read_text())
        pcam = camera_from_dict(doc["camera"])
        for e in doc["images"]:
            if (folder / e["file"]).exists():
                out.append((f"{folder.name}/{e['file']}", pcam,
                            lambda p=folder / e["file"]: load_image(p)))
    return out


def _nan_list(a):
    return None if a is None else np.where(np.isfinite(a), a, np.nan).tolist()


def run(cache: Path, only: str | None = None, names=None,
        methods: tuple[str, ...] = tuple(METHODS)) -> dict:
    holder = default_holder()
    rec = {}
    for name, cam, load in image_list(cache):
        if (only and only not in name) or (names is not None and name not in names):
            continue
        img = load()
        row = {}
        for method in methods:
            m = measure(img, cam, holder, method, limits=METHODS[method])
            f = m.features
            row[method] = {
                "ok": bool(m.ok), "reason": m.quality.reason,
                "dof": None if m.pose is None else m.pose.dof.tolist(),
                "timings_ms": {k: round(float(v), 2) for k, v in m.timings_ms.items()}}
            if m.quality.budget is not None:
                row[method]["std"] = _nan_list(np.asarray(m.quality.budget.std_dof, float))
            if method == "dm+":
                row["visible"] = None if f is None else np.asarray(f.visible).tolist()
                row["corners_px"] = None if f is None else _nan_list(f.corners_px)
        rec[name] = row
        d = row["dm+"]
        print(f"{name:28s} seen {sum(row['visible'] or [])}/20 ok {d['ok']!s:5s} "
              f"{d['reason'][:60]}", flush=True)
    return rec


def _ang(a, b):
    d = np.asarray(a, float) - np.asarray(b, float)
    d[:3] = (d[:3] + 180.0) % 360.0 - 180.0
    return d


def compare(ref: dict, new: dict, tol_px: float, tol_mm: float, tol_deg: float) -> list[str]:
    """Differences beyond the tolerances, one line each (empty: all within)."""
    bad = []
    print(f"{'image':28s} {'corner px':>10s}"
          + "".join(f" {k + ' deg':>9s} {k + ' mm':>9s}" for k in METHODS))
    for name, r in ref.items():
        n = new.get(name)
        if n is None:
            continue
        line = f"{name:28s}"
        if r["visible"] != n["visible"]:
            bad.append(f"{name}: seen corners changed {r['visible']} -> {n['visible']}")
        if r["corners_px"] is not None and n["corners_px"] is not None:
            a, b = np.array(r["corners_px"], float), np.array(n["corners_px"], float)
            both = np.isfinite(a).all(axis=1) & np.isfinite(b).all(axis=1)
            dc = float(np.abs(a[both] - b[both]).max()) if both.any() else 0.0
            line += f" {dc:10.1e}"
            if dc > tol_px:
                bad.append(f"{name}: a corner moved {dc:.4f} px (> {tol_px})")
        else:
            line += f" {'-':>10s}"
        for method in [k for k in METHODS if k in r and k in n]:
            rr, nn = r[method], n[method]
            if rr["ok"] != nn["ok"] or rr["reason"] != nn["reason"]:
                bad.append(f"{name} {method}: verdict changed {rr['ok']} {rr['reason']!r} -> "
                           f"{nn['ok']} {nn['reason']!r}")
            if (rr["dof"] is None) != (nn["dof"] is None):
                bad.append(f"{name} {method}: pose appeared/disappeared")
                line += f" {'-':>9s} {'-':>9s}"
                continue
            if rr["dof"] is None:
                line += f" {'-':>9s} {'-':>9s}"
                continue
            d = np.abs(_ang(rr["dof"], nn["dof"]))
            line += f" {d[:3].max():9.1e} {d[3:].max():9.1e}"
            if d[:3].max() > tol_deg or d[3:].max() > tol_mm:
                bad.append(f"{name} {method}: pose moved {d[:3].max():.5f} deg / "
                           f"{d[3:].max():.5f} mm")
        print(line)
    return bad


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    g = ap.add_mutually_exclusive_group(required=True)
    g.add_argument("--record", type=Path, help="write the recording here")
    g.add_argument("--check", type=Path, help="compare with this recording")
    ap.add_argument("--cache", type=Path, default=Path("/tmp/cutterpose_speed_images"))
    ap.add_argument("--only", help="only images whose name contains this")
    ap.add_argument("--tol-px", type=float, default=0.02)
    ap.add_argument("--tol-mm", type=float, default=0.005)
    ap.add_argument("--tol-deg", type=float, default=0.001)
    a = ap.parse_args()
    ref = json.loads(a.check.read_text()) if a.check else None
    methods = tuple(METHODS) if ref is None else tuple(
        k for k in METHODS if any(k in row for row in ref.values()))
    rec = run(a.cache, a.only, None if ref is None else set(ref), methods)
    if a.record:
        a.record.write_text(json.dumps(rec, indent=1))
        print(f"recorded {len(rec)} images -> {a.record}")
        return
    bad = compare(ref, rec, a.tol_px, a.tol_mm, a.tol_deg)
    for b in bad:
        print("DIFF", b)
    print(f"{len(rec)} images compared, {len(bad)} differences beyond the tolerances")
    sys.exit(1 if bad else 0)


if __name__ == "__main__":
    main()
