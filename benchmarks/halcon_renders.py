"""HALCON plates on renders: detect and calibrate, compared with the rendering camera.

Nobody here has photographs of a HALCON plate, so this renders them: the shipped plate
descriptions (``cutterpose/data/hexplate_15x17_2.5mm.cpd``, a hexagonal plate with five finder
patterns, and ``caltab_7x7_30mm.descr``, the rectangular caltab) are drawn with the project's
plate renderer (:func:`cutterpose.calibration.plate.render_plate`: exact perspective and lens
distortion, defocus, shot and read noise, 8-bit quantisation of a render preset) through a
known HALCON ``area_scan_polynomial`` camera, detected, and calibrated with the polynomial and
the division model. Printed: per plate and model the focal length and principal point against
the rendering camera, the RMS reprojection error, the number of views used and of marks per
view (the hexagonal plate's views include partial ones: the plate runs off the image).

Usage::

    python benchmarks/halcon_renders.py [--views 12] [--preset easy] [--out DIR]
"""

from __future__ import annotations

import argparse
import time
from importlib import resources
from pathlib import Path

import cv2
import numpy as np

from cutterpose.calibration.halcon_plate import HalconPlate
from cutterpose.calibration.intrinsics import calibrate
from cutterpose.calibration.plate import render_plate, sample_plate_poses
from cutterpose.calibration.view_refine import calibrate_views
from cutterpose.geometry.camera import PolynomialCamera
from cutterpose.geometry.pose import Pose
from cutterpose.render.analytic import preset

#: the rendering camera: 1280 x 960, 4.8 um pixels, 8 mm lens with barrel distortion and a
#: small decentering (HALCON units: K1 1/m^2, K2 1/m^4, K3 1/m^6, P1, P2 1/m)
CAMERA = PolynomialCamera(0.008, -1200.0, 4e6, 0.0, 0.4, -0.25, (4.8e-6, 4.8e-6),
                          (652.0, 471.0), (1280, 960), name="rendering camera")
PIXEL_HEIGHT_M = 4.8e-6


def _partial_poses(plate, count: int, seed: int) -> list[Pose]:
    """Poses that show the plate larger than the image (partial views): the plate's centre is
    aimed at a random image point at a distance where it overfills the image."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    out = []
    w, h = CAMERA.image_size_px
    for _ in range(count):
        axis = rng.normal(size=3) * [1, 1, 0]
        R = Rotation.from_rotvec(axis / np.linalg.norm(axis) * np.radians(rng.uniform(15, 35)))
        R = (R * Rotation.from_rotvec([0, 0, rng.uniform(-np.pi, np.pi)])).as_matrix()
        ray = CAMERA.pixel_to_ray(np.array([rng.uniform(0.3, 0.7) * w,
                                            rng.uniform(0.3, 0.7) * h]))
        out.append(Pose(R, ray / ray[2] * rng.uniform(95, 125), "cam", "plate"))
    return out


def run(name: str, plate, poses, settings, out: Path | None):
    rng = np.random.default_rng(1)
    ids, pts, used, skipped = [], [], [], {}
    t0 = time.time()
    for k, pose in enumerate(poses):
        img = render_plate(CAMERA, pose, plate, settings=settings, rng=rng)
        if out is not None:
            cv2.imwrite(str(out / f"{name}_{k:02d}.png"), img)
        det = plate.detect(img)
        if det:
            ids.append(det.ids)
            pts.append(det.points_px)
            used.append(k)
        else:
            skipped[k] = det.reason
    t_det = time.time() - t0
    rows = []
    for model in ("polynomial", "division"):
        t1 = time.time()
        if not plate.hexagonal and model == "division":  # complete views: intrinsics'
            res = calibrate(np.stack(pts), plate.geometry.plate, CAMERA.image_size_px,
                            model="division", pixel_height_m=PIXEL_HEIGHT_M)
        else:
            res = calibrate_views(plate, ids, pts, CAMERA.image_size_px, model=model,
                                  pixel_height_m=PIXEL_HEIGHT_M)
        cam = res.camera
        df = 100 * (cam.K[0, 0] / CAMERA.K[0, 0] - 1), 100 * (cam.K[1, 1] / CAMERA.K[1, 1] - 1)
        dp = np.subtract(cam.principal_point_px, CAMERA.principal_point_px)
        rows.append((name, model, len(used), len(skipped),
                     f"{min(map(len, ids))}-{max(map(len, ids))}", df, dp, res.rms_px,
                     res.std, time.time() - t1))
    return rows, skipped, t_det


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--views", type=int, default=12)
    ap.add_argument("--preset", default="easy")
    ap.add_argument("--out", default=None, help="folder for the rendered images")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--write-poses", default=None, help="write the hexagonal plate's poses "
                    "(T_cam_plate, protocol CSV) and the rendering camera (.dat) to this folder "
                    "for `cutterpose render-plate --plate-poses` and stop")
    a = ap.parse_args()
    data = resources.files("cutterpose.data")
    settings = preset(a.preset)
    out = Path(a.out) if a.out else None
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
    hexp = HalconPlate.from_file(data / "hexplate_15x17_2.5mm.cpd")
    caltab = HalconPlate.from_file(data / "caltab_7x7_30mm.descr")
    n_full = a.views - a.views // 3
    hex_poses = (sample_plate_poses(CAMERA, n_full, hexp, distance_mm=(230, 330), seed=a.seed)
                 + _partial_poses(hexp, a.views // 3, a.seed))
    # the CirclePlate's sampler keeps the triangular mark in view too
    if a.write_poses:
        from cutterpose.geometry.camera_files import save_camera
        from cutterpose.robot.poses import write_poses

        folder = Path(a.write_poses)
        folder.mkdir(parents=True, exist_ok=True)
        write_poses(folder / "hexplate_poses.csv", hex_poses)
        save_camera(CAMERA, folder / "rendering_camera.dat")
        print(f"wrote {folder / 'hexplate_poses.csv'} and {folder / 'rendering_camera.dat'}")
        return
    cal_poses = sample_plate_poses(CAMERA, a.views, caltab.geometry.plate,
                                   distance_mm=(750, 1000),
                                   seed=a.seed)
    print(f"rendering camera: {CAMERA.to_dict()}")
    print(f"preset {a.preset}, {a.views} views per plate\n")
    print("| plate | model | views used | skipped | marks/view | fx err % | fy err % | "
          "cx err px | cy err px | RMS px | sd f | sd cx, cy px |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for name, plate, poses in (("hexplate_15x17_2.5mm.cpd", hexp, hex_poses),
                               ("caltab_7x7_30mm.descr", caltab, cal_poses)):
        rows, skipped, t_det = run(Path(name).stem, plate, poses, settings, out)
        for (_, model, nu, ns, mv, df, dp, rms, std, _) in rows:
            print(f"| {name} | {model} | {nu} | {ns} | {mv} | {df[0]:+.3f} | {df[1]:+.3f} | "
                  f"{dp[0]:+.2f} | {dp[1]:+.2f} | {rms:.4f} | "
                  f"{std.get('focal_length_m', std.get('fy_px', np.nan)) * 1e6:.3f} um | "
                  f"{std.get('cx_px', np.nan):.2f}, {std.get('cy_px', np.nan):.2f} |")
        for k, why in skipped.items():
            print(f"  {name} view {k} skipped: {why}")
        print(f"  ({name}: render+detect {t_det:.1f} s)")


if __name__ == "__main__":
    main()
