"""Depth bias through a broken pocket edge, with and without the radius estimation, and the
verdict's behaviour (docs/notes/edge_model.md).

    PYTHONPATH=src python benchmarks/edge_model_bias.py --preset new --count 12 --seed 21
    PYTHONPATH=src python benchmarks/edge_model_bias.py --set /work/data/new_s1 [--count 20]

Renders ``count`` images of the analytic renderer's ``preset`` (``new``: fillet 0.5-1.5 mm,
``rounded``: 1.5-4.5 mm, per edge) at random poses of the working range, or reads an image set
(``truth.json``, e.g. one of the pbr sets), measures each with ``dm``, ``dm+`` and ``dm+r`` and
prints one line per image and method and a summary: accepted, mean and std of the Z error,
p95 translation and rotation errors over all and over the accepted images.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from cutterpose.errors import FeatureError
from cutterpose.geometry.camera import camera_from_dict, default_camera
from cutterpose.geometry.holder import default_holder
from cutterpose.geometry.pose import Pose, pose_errors
from cutterpose.image import detect_features, load_image
from cutterpose.pipeline import measure_features
from cutterpose.render.analytic import random_pose, render_holder

METHODS = ("dm", "dm+", "dm+r")


def images(args):
    holder = default_holder()
    if args.set:
        doc = json.loads((Path(args.set) / "truth.json").read_text())
        cam = camera_from_dict(doc["camera"])
        for e in doc["images"][: args.count]:
            truth = Pose(np.array(e["R_cam_holder"]), np.array(e["t_cam_holder_mm"]))
            r = e.get("edge_radius_mm") or e.get("params", {}).get("edge_radius_mm")
            yield e["file"], load_image(Path(args.set) / e["file"]), cam, holder, truth, r
        return
    cam = default_camera("table1")
    rng = np.random.default_rng(args.seed)
    for i in range(args.count):
        truth = random_pose(rng)
        r = render_holder(truth, cam, holder, args.preset, seed=args.seed * 1000 + i)
        yield f"{args.preset}_{i}", r.image, cam, holder, truth, r.edge_radius_mm


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--preset", default="new")
    ap.add_argument("--set", default="")
    ap.add_argument("--count", type=int, default=12)
    ap.add_argument("--seed", type=int, default=21)
    args = ap.parse_args()
    rows = {m: [] for m in METHODS}
    for name, img, cam, holder, truth, radii in images(args):
        rm = float(np.mean(radii)) if radii is not None and np.size(radii) else float("nan")
        try:
            f = detect_features(img, cam, holder)
        except FeatureError as e:
            print(f"{name}: no features: {e}", flush=True)
            for m in METHODS:
                rows[m].append((np.nan, np.nan, np.nan, 0, np.nan))
            continue
        for m in METHODS:
            M = measure_features(f, cam, holder, m)
            if M.pose is None:
                rows[m].append((np.nan, np.nan, np.nan, 0, np.nan))
                print(f"{name} {m}: no pose: {M.quality.reason}", flush=True)
                continue
            e = pose_errors(truth.R, truth.t_mm, M.pose.R, M.pose.t_mm)
            dz = float(M.pose.dof[5] - truth.dof[5])
            b = M.quality.budget
            rows[m].append((dz, float(e.trans_mm[0]), float(e.rot_deg[0]), int(M.ok),
                            M.edge_radius_mm))
            print(f"{name} r_true {rm:.2f} {m:5s} ok={int(M.ok)} dZ {dz:+.3f} trans "
                  f"{e.trans_mm[0]:.3f} rot {e.rot_deg[0]:.3f} r {M.edge_radius_mm:.2f} "
                  f"pos3s {b.position_3sigma_mm:.2f} ang3s {b.angle_3sigma_deg:.3f} "
                  f"{M.quality.reason[:70]}", flush=True)
    print("\nmethod  n  accepted  Z bias  Z std  p95 trans  p95 rot | accepted: p95 trans  "
          "max trans  max rot")
    for m in METHODS:
        a = np.array(rows[m], float)
        ok = a[:, 3] == 1
        fin = np.isfinite(a[:, 0])
        acc = a[ok & fin]

        def q(x, p):
            return np.quantile(x, p) if len(x) else np.nan

        print(f"{m:5s} {len(a):3d} {ok.sum():5d}   {np.nanmean(a[:, 0]):+.3f}  "
              f"{np.nanstd(a[:, 0]):.3f}  {q(a[fin, 1], 0.95):8.3f}  {q(a[fin, 2], 0.95):7.3f} | "
              f"{q(acc[:, 1], 0.95):8.3f}  {np.max(acc[:, 1]) if len(acc) else np.nan:8.3f}  "
              f"{np.max(acc[:, 2]) if len(acc) else np.nan:7.3f}")


if __name__ == "__main__":
    main()
