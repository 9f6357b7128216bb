"""Hand-eye calibration on real photographs (issue 29): robot_cal_tools' rct_10x10 set.

    cutterpose calibrate tests/data/real/rct_10x10/images --target circles:10x10:25.4:origin-dot \\
        --model opencv --out results/rct_camera.json
    PYTHONPATH=src python benchmarks/handeye_real.py --data tests/data/real/rct_10x10 \\
        --camera results/rct_camera.json --out results/handeye_real \\
        --figure docs/img/handeye_rct_overlay.jpg

15 webcam images (640 x 480) of a 10 x 10 circle grid with an origin dot, the robot's
base -> tool0 pose per image (ROS YAML). Steps, all on the same detections:

1. the target detected in every image (the target's own detector);
2. the intrinsics from the same images (``cv2.calibrateCamera``, OpenCV's default model
   k1, k2, p1, p2, k3), or ``--camera FILE``;
3. :func:`calibrate_handeye` (the refinement) and, on the same target poses and intrinsics,
   every OpenCV method (``cv2.calibrateHandEye``: Tsai, Park, Horaud, Andreff, Daniilidis;
   ``cv2.calibrateRobotWorldHandEye``: Shah, Li): the table of differences, and the spread
   among the OpenCV methods themselves;
4. the robot-vs-camera motion mismatch of every station (independent of ``X``): what no
   hand-eye method can remove;
5. leave-one-station-out: each method calibrated on 14 stations predicts the 15th station's
   image (RMS px of the target's points): which transform explains unseen data best;
6. the 180-degree check: the same detections with every second station's point order
   reversed, calibrated with the target declared symmetric: the result must not change.

Writes ``handeye_real.json`` and ``handeye_real.md`` (the tables of docs/results/handeye.md).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import cv2
import numpy as np

from cutterpose.calibration.handeye import calibrate_handeye
from cutterpose.calibration.handeye_problem import TargetModel
from cutterpose.calibration.handeye_report import report_markdown
from cutterpose.calibration.handeye_starts import OPENCV_METHODS
from cutterpose.geometry.camera import OpenCVCamera
from cutterpose.geometry.camera_files import load_camera
from cutterpose.geometry.pose import Pose, geodesic_deg
from cutterpose.robot.pose_files import pair_with_images, read_pose_set


def detect(paths, target):
    """names, (n, N, 2) points, skipped {name: reason}."""
    names, pts, skipped = [], [], {}
    n_all = len(target.points_target_mm)
    for p in paths:
        det = target.detect(cv2.imread(str(p), cv2.IMREAD_GRAYSCALE))
        if det:
            full = np.full((n_all, 2), np.nan)  # target order, NaN where not seen
            full[det.ids] = det.points_px
            names.append(p.name)
            pts.append(full)
        else:
            skipped[p.name] = str(det.reason)
    return names, np.stack(pts), skipped


def intrinsics(pts: np.ndarray, points_mm: np.ndarray, size) -> tuple[OpenCVCamera, float]:
    seen = [np.all(np.isfinite(p), axis=1) for p in pts]
    obj = [points_mm[s].astype(np.float32) for s in seen]
    rms, K, dist, _, _ = cv2.calibrateCamera(obj, [p[s].astype(np.float32)
                                                   for p, s in zip(pts, seen)],
                                             tuple(size), None, None)
    K[0, 1] = 0.0
    return OpenCVCamera(K, dist.ravel(), tuple(size), "rct_10x10 (cv2.calibrateCamera)"), rms


def _predict_rms(cam, points_mm, A: Pose, X: Pose, Y: Pose, obs: np.ndarray) -> float:
    T = X.inverse() @ A.inverse() @ Y
    return float(np.sqrt(np.nanmean(np.sum((cam.project(T.apply(points_mm)) - obs) ** 2,
                                           axis=1))))


def overlay(paths_by_name: dict, names: list, pts, cam, target: TargetModel, A, X, Y,
            stations, out: Path) -> None:
    """The best and the worst station side by side: detected centres (green) and the target
    projected from the robot pose through the calibration (red, X^-1 A_i^-1 Y)."""
    order = np.argsort([s.rms_px for s in stations])
    tiles = []
    for k in (order[0], order[-1]):
        img = cv2.cvtColor(cv2.imread(str(paths_by_name[names[k]])), cv2.COLOR_BGR2GRAY)
        img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
        pred = cam.project((X.inverse() @ A[k].inverse() @ Y).apply(target.points_mm))
        for (u, v), (pu, pv) in zip(pts[k], pred):
            if np.isfinite(u):
                cv2.circle(img, (int(round(u)), int(round(v))), 3, (0, 200, 0), 1, cv2.LINE_AA)
            cv2.drawMarker(img, (int(round(pu)), int(round(pv))), (0, 0, 255),
                           cv2.MARKER_CROSS, 6, 1, cv2.LINE_AA)
        s = stations[k]
        cv2.putText(img, f"{s.name}: {s.rms_px:.1f} px, motion {s.motion_deg:.2f} deg"
                    + ("" if s.used else " (outlier)"), (8, 22), cv2.FONT_HERSHEY_SIMPLEX,
                    0.6, (0, 0, 255), 1, cv2.LINE_AA)
        tiles.append(img)
    cv2.imwrite(str(out), np.concatenate(tiles, axis=1), [cv2.IMWRITE_JPEG_QUALITY, 80])


def leave_one_out(A, pts, cam, target: TargetModel, rep):
    """method -> list of the left-out station's prediction RMS [px]."""
    out: dict = {}
    for k in range(len(A)):
        keep = [i for i in range(len(A)) if i != k]
        r = calibrate_handeye([A[i] for i in keep], pts[keep], cam, target,
                              repeatability_mm=rep[0], repeatability_deg=rep[1])
        cands = {"refined": (r.T_flange_cam, r.T_base_plate)}
        cands.update({m: v for m, v in r.starts.items() if not isinstance(v, str)})
        for m, (X, Y) in cands.items():
            out.setdefault(m, []).append(_predict_rms(cam, target.points_mm, A[k], X, Y,
                                                      pts[k]))
    return out


def flipped_check(A, pts, cam, target: TargetModel, rep, reference):
    N = target.n_points
    turned = pts.copy()
    turned[1::2] = turned[1::2, ::-1]
    sym = TargetModel(target.points_mm, [np.arange(N)[::-1].copy()], target.marks, "plain")
    r = calibrate_handeye(A, turned, cam, sym, repeatability_mm=rep[0],
                          repeatability_deg=rep[1])
    return {"dt_mm": float(np.linalg.norm(r.T_flange_cam.t_mm - reference.t_mm)),
            "dR_deg": float(geodesic_deg(r.T_flange_cam.R, reference.R)),
            "turned_found": [s.order != "as detected" for s in r.stations],
            "turned_true": [bool(i % 2) for i in range(len(A))]}


def _spread(poses: dict) -> tuple[float, float, str, str]:
    """Largest pairwise dt [mm] and dR [deg] among methods, and the pairs."""
    best = (0.0, 0.0, "", "")
    names = list(poses)
    dt = dr = 0.0
    pt = pr = ""
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            t = float(np.linalg.norm(poses[a].t_mm - poses[b].t_mm))
            g = float(geodesic_deg(poses[a].R, poses[b].R))
            if t > dt:
                dt, pt = t, f"{a}-{b}"
            if g > dr:
                dr, pr = g, f"{a}-{b}"
    return (dt, dr, pt, pr) if names else best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default="tests/data/real/rct_10x10")
    ap.add_argument("--target", default="circles:10x10:25.4:origin-dot")
    ap.add_argument("--camera", default=None, help="camera file (default: calibrate from the "
                    "same images)")
    ap.add_argument("--repeatability-mm", type=float, default=0.1)
    ap.add_argument("--repeatability-deg", type=float, default=0.01)
    ap.add_argument("--out", default="results/handeye_real")
    ap.add_argument("--figure", default=None, help="write the overlay of the best and the "
                    "worst station (PNG)")
    a = ap.parse_args()
    from cutterpose.calibration.targets import target_from_spec

    t0 = time.time()
    data, out = Path(a.data), Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    tgt = target_from_spec(a.target)
    model = TargetModel.of(tgt)
    paths = sorted((data / "images").glob("*.png"))
    names, pts, skipped = detect(paths, tgt)
    ps = read_pose_set(data / "poses")
    A = [ps.poses[j] for j in pair_with_images(names, ps.names)]
    if a.camera:
        cam, cal_rms = load_camera(a.camera), None
    else:
        cam, cal_rms = intrinsics(pts, model.points_mm, (640, 480))
    rep = (a.repeatability_mm, a.repeatability_deg)
    r = calibrate_handeye(A, pts, cam, tgt, names=names, repeatability_mm=rep[0],
                          repeatability_deg=rep[1])
    X = r.T_flange_cam
    ocv = {m: r.starts[m][0] for m in OPENCV_METHODS if not isinstance(r.starts[m], str)}
    m_deg = np.array([s.motion_deg for s in r.stations])
    m_mm = np.array([s.motion_mm for s in r.stations])
    if a.figure:
        overlay({p.name: p for p in paths}, names, pts, cam, model, A, X, r.T_base_plate,
                r.stations, Path(a.figure))
    loo = leave_one_out(A, pts, cam, model, rep)
    flip = flipped_check(A, pts, cam, model, rep, X)
    res = {
        "data": str(data), "target": a.target, "skipped": skipped, "n_stations": len(names),
        "camera": cam.to_dict(), "calibrate_rms_px": cal_rms,
        "refined": {"t_mm": X.t_mm.tolist(), "R": X.R.tolist(), "verdict": r.verdict,
                    "rms_px": r.rms_px, "sigma_px": r.sigma_px,
                    "sd": np.sqrt(np.diag(r.handeye.covariance)).tolist()},
        "plate_spread": r.plate_spread,
        "methods": {m: {"t_mm": v.t_mm.tolist(),
                        "dt_mm": float(np.linalg.norm(v.t_mm - X.t_mm)),
                        "dR_deg": float(geodesic_deg(v.R, X.R))} for m, v in ocv.items()},
        "failed": {m: v for m, v in r.starts.items() if isinstance(v, str)},
        "spread_all_opencv": _spread(ocv),
        "spread_without_daniilidis_li": _spread({m: v for m, v in ocv.items()
                                                 if m not in ("daniilidis", "li")}),
        "spread_tsai_park_horaud_shah": _spread({m: v for m, v in ocv.items()
                                                 if m in ("tsai", "park", "horaud", "shah")}),
        "motion_mismatch": {"median_deg": float(np.median(m_deg)),
                            "median_mm": float(np.median(m_mm)),
                            "per_station_deg": m_deg.tolist()},
        "leave_one_out_px": {m: {"median": float(np.median(v)), "mean": float(np.mean(v))}
                             for m, v in loo.items()},
        "flipped_check": flip, "seconds": time.time() - t0,
    }
    (out / "handeye_real.json").write_text(json.dumps(res, indent=1) + "\n")
    (out / "handeye_real_report.md").write_text(report_markdown(r, "rct_10x10"))
    print(json.dumps({k: res[k] for k in ("refined", "plate_spread", "spread_all_opencv",
                                          "spread_without_daniilidis_li",
                                          "spread_tsai_park_horaud_shah", "motion_mismatch",
                                          "leave_one_out_px", "flipped_check", "seconds")},
                     indent=1))


if __name__ == "__main__":
    main()
