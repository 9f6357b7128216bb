"""The robot cell's "Done when" figures (issue 11), at full resolution in the simulated cell.

    python benchmarks/robot_cell.py handeye --seeds 10 --stations 20 --out results/robot_cell
    python benchmarks/robot_cell.py summary --out results/robot_cell    # table of the first
    python benchmarks/robot_cell.py endtoend --out results/robot_cell   # needs the first

``handeye``: per seed a random cell (camera mount, plate), 20 stations, the plate rendered and
detected (Table 1 camera, 4112 x 3008), robot noise 0.03 mm / 0.005 deg; the refined
``T_flange_cam`` against the truth and against every OpenCV method on the same data (with
OpenCV >= 4 builds that have the bindings; the numpy Tsai/Park/Shah always), then the same
data with one station's reported pose moved 5 mm. Writes ``handeye.csv``, ``handeye.json``,
one ``handeye_seedN.json`` per seed (the calibration the end-to-end part uses) and the cells'
truth.

``endtoend``: per seed, 2 holder poses in the base frame, each imaged from 5 stations of
that seed's cell (holder in the measurement's working range, preset ``easy``), measured with
``dm+``, located in the base frame with the seed's calibrated hand-eye file and the reported
flange pose; the grasp point's error against the truth and the stated 3-sigma bounds.
Writes ``endtoend.csv`` and ``endtoend.json``.
"""

from __future__ import annotations

import argparse
import csv
import json
import time
from pathlib import Path

import numpy as np

from cutterpose.calibration.handeye import calibrate_handeye, save_handeye
from cutterpose.calibration.intrinsics import detect_plate
from cutterpose.errors import FeatureError
from cutterpose.geometry.camera import default_camera
from cutterpose.geometry.pose import Pose, geodesic_deg
from cutterpose.robot.cell import RobotCell


def _err(X: Pose, truth: Pose) -> tuple[float, float]:
    return float(np.linalg.norm(X.t_mm - truth.t_mm)), float(geodesic_deg(X.R, truth.R))


def run_handeye(seeds: int, stations: int, out: Path) -> None:
    import cv2

    out.mkdir(parents=True, exist_ok=True)
    cam = default_camera("table1")
    rows, summary = [], []
    for seed in range(seeds):
        t0 = time.time()
        cell = RobotCell.random(cam, seed)
        true = cell.plate_stations(stations, seed)
        reported = cell.report(true, np.random.default_rng([seed, 1]))
        rng = np.random.default_rng([seed, 2])
        pts, keep, lost = [], [], []
        for i, a in enumerate(true):
            try:
                pts.append(detect_plate(cell.plate_image(a, rng), cell.plate).points_px)
                keep.append(i)
            except FeatureError as e:  # as in a real cell: the station is dropped, and counted
                lost.append(f"station{i}: {e}")
        pts = np.stack(pts)
        reported = [reported[i] for i in keep]
        # the detected centres and poses, so that other estimators can be run on the same data
        # without rendering again (benchmarks/handeye_floor.py)
        np.savez(out / f"data_seed{seed}.npz", points_px=pts, keep=np.array(keep),
                 T_base_flange_reported=np.stack([a.matrix for a in reported]),
                 T_base_flange_true=np.stack([true[i].matrix for i in keep]))
        res = calibrate_handeye(reported, pts, cam, cell.plate,
                                names=[f"station{i}" for i in keep])
        save_handeye(res, out / f"handeye_seed{seed}.json")
        (out / f"cell_seed{seed}.json").write_text(json.dumps(cell.truth_dict()))
        e_mm, e_deg = _err(res.T_flange_cam, cell.T_flange_cam)
        rec = {"seed": seed, "refined_mm": e_mm, "refined_deg": e_deg,
               "refined_at_holder_mm": err_at_holder(res.T_flange_cam, cell.T_flange_cam),
               "start": res.start_method, "verdict": res.verdict,
               "sd_mm": float(np.sqrt(np.trace(res.handeye.covariance[:3, :3]))),
               "sd_deg": float(np.degrees(np.sqrt(np.trace(res.handeye.covariance[3:, 3:])))),
               "distrusted": [s.name for s in res.stations if not s.used],
               "not_detected": lost, "methods": {}}
        for name, v in res.starts.items():
            if isinstance(v, str):
                rec["methods"][name] = v
                continue
            m_mm, m_deg = _err(v[0], cell.T_flange_cam)
            rec["methods"][name] = [m_mm, m_deg, err_at_holder(v[0], cell.T_flange_cam)]
            rows.append([seed, name, m_mm, m_deg])
        rows.append([seed, "refined", e_mm, e_deg])
        # one station's reported pose 5 mm off, in a random direction
        k = seed % len(reported)
        d = np.random.default_rng([seed, 3]).normal(size=3)
        bad = list(reported)
        bad[k] = Pose(bad[k].R, bad[k].t_mm + 5.0 * d / np.linalg.norm(d), "base", "flange")
        rb = calibrate_handeye(bad, pts, cam, cell.plate)
        c_mm, c_deg = _err(rb.T_flange_cam, cell.T_flange_cam)
        rec["corrupted"] = {"station": k, "flagged": not rb.stations[k].used,
                            "others_flagged": [s.name for i, s in enumerate(rb.stations)
                                               if not s.used and i != k],
                            "error_mm": c_mm, "error_deg": c_deg}
        rows.append([seed, "refined, 1 station 5 mm off", c_mm, c_deg])
        rec["seconds"] = time.time() - t0
        summary.append(rec)
        print(json.dumps(rec), flush=True)
    with open(out / "handeye.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["seed", "method", "error_mm", "error_deg"])
        w.writerows(rows)
    ref_mm = np.array([r["refined_mm"] for r in summary])
    ref_deg = np.array([r["refined_deg"] for r in summary])
    methods = sorted({n for r in summary for n, v in r["methods"].items()
                      if not isinstance(v, str)})

    def best(r, key):
        vals = [v[key] for v in r["methods"].values() if not isinstance(v, str)]
        return min(vals)

    at_least_as_close = sum(r["refined_mm"] <= best(r, 0) and r["refined_deg"] <= best(r, 1)
                            for r in summary)
    agg = {
        "opencv": cv2.__version__, "seeds": seeds, "stations": stations,
        "median_refined_mm": float(np.median(ref_mm)),
        "median_refined_deg": float(np.median(ref_deg)),
        "max_refined_mm": float(ref_mm.max()), "max_refined_deg": float(ref_deg.max()),
        "median_by_method": {m: [float(np.median([r["methods"][m][0] for r in summary])),
                                 float(np.median([r["methods"][m][1] for r in summary]))]
                             for m in methods},
        "refined_at_least_as_close_as_best_method_mm_and_deg": at_least_as_close,
        "refined_closer_mm": int(sum(r["refined_mm"] <= best(r, 0) for r in summary)),
        "refined_closer_deg": int(sum(r["refined_deg"] <= best(r, 1) for r in summary)),
        "corrupted_flagged": int(sum(r["corrupted"]["flagged"] for r in summary)),
        "corrupted_max_mm": float(max(r["corrupted"]["error_mm"] for r in summary)),
        "corrupted_max_deg": float(max(r["corrupted"]["error_deg"] for r in summary)),
        "false_flags_clean": int(sum(len(r["distrusted"]) for r in summary)),
        "stations_not_detected": int(sum(len(r["not_detected"]) for r in summary)),
        "per_seed": summary,
    }
    (out / "handeye.json").write_text(json.dumps(agg, indent=1))
    print(json.dumps({k: v for k, v in agg.items() if k != "per_seed"}, indent=1))


#: where the hand-eye error matters: the holder, 600 mm along the optical axis
P_HOLDER_CAM_MM = np.array([0.0, 0.0, 600.0])


def err_at_holder(X: Pose, truth: Pose) -> float:
    """Distance (mm) between where ``X`` and the true transform put a point 600 mm in front of
    the camera: translation and rotation errors in one figure, as the grasp sees them."""
    return float(np.linalg.norm(X.apply(P_HOLDER_CAM_MM) - truth.apply(P_HOLDER_CAM_MM)))


def run_summary(out: Path) -> None:
    """Per seed and method: errors in mm, deg and at the holder; wins of the refinement."""
    seeds = sorted(int(p.stem[len("handeye_seed"):]) for p in out.glob("handeye_seed*.json"))
    table = {}
    for seed in seeds:
        d = json.loads((out / f"handeye_seed{seed}.json").read_text())
        truth = Pose.from_matrix(json.loads((out / f"cell_seed{seed}.json").read_text())
                                 ["T_flange_cam"], "flange", "cam")
        cand = {"refined": d["T_flange_cam"]}
        cand |= {k: v["T_flange_cam"] for k, v in d["opencv_methods"].items()
                 if not isinstance(v, str)}
        data = out / f"data_seed{seed}.npz"
        if data.is_file():  # the explicit bundle adjustment on the same detected centres
            z = np.load(data)
            cell = json.loads((out / f"cell_seed{seed}.json").read_text())
            from cutterpose.calibration.plate import CirclePlate

            ba = calibrate_handeye([Pose.from_matrix(m, "base", "flange")
                                    for m in z["T_base_flange_reported"]], z["points_px"],
                                   default_camera("table1"),
                                   CirclePlate.from_dict(cell["plate"]),
                                   refinement="bundle")
            cand["bundle"] = ba.T_flange_cam.matrix
        table[seed] = {}
        for k, T in cand.items():
            X = Pose.from_matrix(T, "flange", "cam")
            table[seed][k] = (*_err(X, truth), err_at_holder(X, truth))
    methods = sorted({m for t in table.values() for m in t} - {"refined", "bundle"})
    methods = (["bundle"] if "bundle" in table[seeds[0]] else []) + methods
    opencv = [m for m in methods if not m.endswith("-numpy") and m != "bundle"]
    lines = ["| method | median mm | median deg | median at holder mm | max at holder mm |",
             "|---|---|---|---|---|"]
    for m in ["refined"] + methods:
        v = np.array([table[s][m] for s in seeds if m in table[s]])
        lines.append(f"| {m} | {np.median(v[:, 0]):.4f} | {np.median(v[:, 1]):.4f} | "
                     f"{np.median(v[:, 2]):.4f} | {v[:, 2].max():.4f} |")
    for group, names in (("OpenCV", opencv), ("every start", methods)):
        if not names:
            continue
        wins = [sum(table[s]["refined"][i] <= min(table[s][m][i] for m in names
                                                   if m in table[s]) for s in seeds)
                for i in range(3)]
        lines.append(f"\nrefined at least as close as the best {group} method: "
                     f"{wins[0]}/{len(seeds)} seeds in mm, {wins[1]}/{len(seeds)} in deg, "
                     f"{wins[2]}/{len(seeds)} at the holder")
    if opencv:
        from scipy.stats import wilcoxon

        ref = np.array([table[s]["refined"][2] for s in seeds])
        tests = []
        for m in opencv:
            o = np.array([table[s][m][2] for s in seeds if m in table[s]])
            if len(o) == len(ref):
                tests.append(f"{m} {int(np.sum(ref < o))}/{len(seeds)} (p = "
                             f"{wilcoxon(ref, o, alternative='less').pvalue:.2g})")
        lines.append("\nrefined closer at the holder than each OpenCV method, paired over seeds "
                     "(one-sided Wilcoxon signed-rank): " + ", ".join(tests))
    # per seed: every method's error at the holder (mm) and in angle (deg)
    cols = ["refined"] + methods
    for i, unit in ((2, "at holder, mm"), (1, "deg")):
        lines += ["", f"Per seed, error {unit}:", "",
                  "| seed | " + " | ".join(cols) + " | best OpenCV |",
                  "|---" * (len(cols) + 2) + "|"]
        for s in seeds:
            best = min((table[s][m][i] for m in opencv if m in table[s]), default=np.nan)
            lines.append(f"| {s} | " + " | ".join(
                f"{table[s][m][i]:.4f}" if m in table[s] else "-" for m in cols)
                + f" | {best:.4f} |")
    text = "\n".join(lines)
    (out / "handeye_summary.md").write_text(text + "\n")
    print(text)


def run_endtoend(out: Path, holders: int, stations: int, preset: str) -> None:
    from scipy.spatial.transform import Rotation

    from cutterpose.calibration.handeye import load_handeye
    from cutterpose.geometry.holder import default_holder
    from cutterpose.pipeline import QualityLimits, measure
    from cutterpose.render.analytic import preset as render_preset
    from cutterpose.render.analytic import render_holder
    from cutterpose.robot import RobotAccuracy, locate

    cam = default_camera("table1")
    holder = default_holder()
    seeds = sorted(int(p.stem[len("handeye_seed"):]) for p in out.glob("handeye_seed*.json"))
    rows = []
    for seed in seeds:
        truth = json.loads((out / f"cell_seed{seed}.json").read_text())
        cell = RobotCell(cam, Pose.from_matrix(truth["T_flange_cam"], "flange", "cam"),
                         Pose.from_matrix(truth["T_base_plate"], "base", "plate"))
        he = load_handeye(out / f"handeye_seed{seed}.json")
        acc = RobotAccuracy(cell.repeatability_mm, cell.repeatability_deg)
        rng = np.random.default_rng([seed, 20])
        for h in range(holders):
            # holder on the cutterhead: its Z along base +x (facing the robot), turned a little
            R = (Rotation.from_euler("xyz", rng.uniform(-5, 5, 3), degrees=True).as_matrix()
                 @ np.column_stack([[0, 1.0, 0], [0, 0, 1.0], [1.0, 0, 0]]))
            T_bh = Pose(R, [1500 + rng.uniform(-50, 50), rng.uniform(-200, 200),
                            800 + rng.uniform(-50, 50)], "base", "holder")
            true_grasp = T_bh @ holder_grasp(holder)
            for k, a in enumerate(cell.holder_stations(T_bh, stations, seed * 100 + h)):
                rep = cell.report([a], rng)[0]
                img_seed = int(rng.integers(1 << 31))
                r = render_holder(cell.camera_view(a, T_bh), cam, holder, preset, seed=img_seed)
                t0 = time.time()
                # the renderer's pocket edge as the holder's drawing would give it
                m = measure(r.image, cam, holder, "dm+", limits=QualityLimits(
                    edge_break_mm=render_preset(preset).edge_radius_mm
                    * (1 + render_preset(preset).edge_radius_spread)))
                res = locate(m, he, rep, acc, camera=cam, holder=holder)
                row = {"seed": seed, "holder": h, "station": k, "ok": m.ok,
                       "verdict": res.grasp.verdict, "reason": res.grasp.reason,
                       "seconds": time.time() - t0}
                if res.T_base_grasp is not None:
                    e_mm, e_deg = _err(res.T_base_grasp.pose, true_grasp)
                    row.update(error_mm=e_mm, error_deg=e_deg,
                               bound_mm=res.grasp.position_3sigma_mm,
                               bound_deg=res.grasp.angle_3sigma_deg)
                rows.append(row)
                print(json.dumps(row), flush=True)
    with open(out / "endtoend.csv", "w", newline="") as f:
        keys = ["seed", "holder", "station", "ok", "verdict", "error_mm", "error_deg",
                "bound_mm", "bound_deg", "reason", "seconds"]
        w = csv.DictWriter(f, keys, extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)
    have = [r for r in rows if "error_mm" in r]
    e_mm = np.array([r["error_mm"] for r in have])
    e_deg = np.array([r["error_deg"] for r in have])
    b_mm = np.array([r["bound_mm"] for r in have])
    b_deg = np.array([r["bound_deg"] for r in have])
    agg = {"measurements": len(rows), "with_pose": len(have),
           "refused": int(sum(not r["ok"] for r in rows)),
           "grasp_verdicts": int(sum(r["verdict"] == "grasp" for r in rows)),
           "max_error_mm": float(e_mm.max()), "median_error_mm": float(np.median(e_mm)),
           "max_error_deg": float(e_deg.max()), "median_error_deg": float(np.median(e_deg)),
           "within_1mm": int(np.sum(e_mm <= 1.0)),
           "coverage_position": float(np.mean(e_mm <= b_mm)),
           "coverage_angle": float(np.mean(e_deg <= b_deg)),
           "coverage_both": float(np.mean((e_mm <= b_mm) & (e_deg <= b_deg))),
           "median_bound_mm": float(np.median(b_mm)), "median_bound_deg": float(np.median(b_deg)),
           "grasp_with_error_over_1mm": int(sum(r["verdict"] == "grasp" and r["error_mm"] > 1.0
                                                for r in have))}
    (out / "endtoend.json").write_text(json.dumps(agg, indent=1))
    print(json.dumps(agg, indent=1))


def holder_grasp(holder) -> Pose:
    from cutterpose.robot.grasp import grasp_frame

    return grasp_frame(holder)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    a = sub.add_parser("handeye")
    a.add_argument("--seeds", type=int, default=10)
    a.add_argument("--stations", type=int, default=20)
    a.add_argument("--out", default="results/robot_cell")
    c = sub.add_parser("summary", help="the hand-eye table from a finished handeye run")
    c.add_argument("--out", default="results/robot_cell")
    b = sub.add_parser("endtoend")
    b.add_argument("--out", default="results/robot_cell")
    b.add_argument("--holders", type=int, default=2, help="holder poses per seed")
    b.add_argument("--stations", type=int, default=5, help="stations per holder pose")
    b.add_argument("--preset", default="easy")
    args = ap.parse_args()
    if args.cmd == "handeye":
        run_handeye(args.seeds, args.stations, Path(args.out))
    elif args.cmd == "summary":
        run_summary(Path(args.out))
    else:
        run_endtoend(Path(args.out), args.holders, args.stations, args.preset)


if __name__ == "__main__":
    main()
