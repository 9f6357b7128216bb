"""Field-chain corners and dm+ poses on pbr image sets (issue 10): set -> table.

Per image: ``detect_features`` (the field chain), the corners seen, their error against the
truth's projected design corners over the seen corners that the renderer does not mark hidden
(``hidden_corners``), the count of "wrong" seen corners (> 3 px off), then ``measure_features``
with ``dm+`` and the protocol's error figures (bias and std per DOF, p95 rotation and
translation) over the images with a pose, accepted or not (the verdict is another part's).

    PYTHONPATH=src python benchmarks/pbr_corners.py /work/data/pbr_sharp_s100 \
        /work/data/pbr_new_s200 [--limit N] [--verbose] [--csv out.csv]

On rounded edges (``new``, ``worn``) the image edge lies legitimately a few tenths of a px to
a few px off the design corner (the edge model's job); on ``sharp`` it must sit on it.
"""

import argparse
import csv
import time
from pathlib import Path

import cv2
import numpy as np

from cutterpose.errors import CutterposeError
from cutterpose.experiments.images import load_image_set
from cutterpose.geometry.pose import pose_errors
from cutterpose.image import FeatureParams, detect_features
from cutterpose.image.params import signed_area
from cutterpose.pipeline import measure_features

WRONG_PX = 3.0  #: a seen corner farther than this from the design corner is counted wrong


def line_offsets(f, e: dict, camera, holder):
    """Outward offset (mm, in the top-face plane) of each seen line from its design edge, at
    both ends, and whether it lies outside the band a broken edge of the truth's radius can
    put the image edge in (``[-0.5 r_max - 0.3, r_max + 0.3]`` mm: the rise is somewhere
    between the wall at depth ``r`` and the face at ``r`` outside; 0.3 mm ~ 1.2 px of slack):
    a line on something else (a wrong rise, a lump, the cutter)."""
    truth = camera.undistort_px(np.asarray(e["corners_px"], float))
    n = len(truth)
    nxt = np.roll(truth, -1, axis=0)
    d = (nxt - truth) / np.linalg.norm(nxt - truth, axis=1, keepdims=True)
    sign = np.sign(signed_area(truth))
    n_out = -sign * np.column_stack([-d[:, 1], d[:, 0]])
    model = np.asarray(holder.corners_mm, float)
    mm = np.linalg.norm(np.roll(model, -1, axis=0) - model, axis=1)
    px_per_mm = np.linalg.norm(nxt - truth, axis=1) / mm
    r_max = np.zeros(n)
    edges = e.get("edges")
    if isinstance(edges, list) and len(edges) == n:
        r_max = np.array([float(x.get("radius_max_mm", 0.0)) for x in edges])
    off = np.full((n, 2), np.nan)
    bad = np.zeros(n, bool)
    L = np.asarray(f.lines_ideal, float)
    for k in range(n):
        if not np.all(np.isfinite(L[k])):
            continue
        for j, p in enumerate((truth[k], nxt[k])):
            q = p - (L[k, :2] @ p + L[k, 2]) * L[k, :2]
            off[k, j] = (q - p) @ n_out[k] / px_per_mm[k]
        lo, hi = -0.5 * r_max[k] - 0.3, r_max[k] + 0.3
        bad[k] = bool(np.any((off[k] < lo) | (off[k] > hi)))
    return off, bad


def run_image(folder: Path, e: dict, camera, holder, params) -> dict:
    img = cv2.imread(str(folder / e["file"]), cv2.IMREAD_GRAYSCALE)
    truth = np.asarray(e["corners_px"], float)
    hidden = np.zeros(len(truth), bool)
    hidden[[int(k) for k in e.get("hidden_corners", {})]] = True
    row = {"file": e["file"], "n_seen": 0, "n_hidden": int(hidden.sum()), "err": np.zeros(0),
           "ok": False, "pose": False, "reason": ""}
    t0 = time.perf_counter()
    try:
        f = detect_features(img, camera, holder, params)
    except CutterposeError as ex:
        row.update(reason=f"features: {ex}", t_feat=1e3 * (time.perf_counter() - t0))
        return row
    row["t_feat"] = 1e3 * (time.perf_counter() - t0)
    vis = np.asarray(f.visible, bool)
    row["n_seen"] = int(vis.sum())
    use = vis & ~hidden
    row["err"] = np.linalg.norm(f.corners_px[use] - truth[use], axis=1)
    row["n_hidden_seen"] = int((vis & hidden).sum())
    row["line_off"], row["line_bad"] = line_offsets(f, e, camera, holder)
    t1 = time.perf_counter()
    try:
        m = measure_features(f, camera, holder, "dm+")
    except CutterposeError as ex:
        row.update(reason=f"measure: {ex}")
        return row
    row["t_pose"] = 1e3 * (time.perf_counter() - t1)
    row["ok"], row["reason"] = bool(m.ok), m.quality.reason
    if m.pose is not None:
        row["pose"] = True
        row["R"], row["t"] = np.asarray(e["R_cam_holder"]), np.asarray(e["t_cam_holder_mm"])
        row["Re"], row["te"] = m.pose.R, m.pose.t_mm
    return row


def table(name: str, rows: list) -> str:
    n = len(rows)
    seen = np.array([r["n_seen"] for r in rows])
    err = np.concatenate([r["err"] for r in rows]) if rows else np.zeros(0)
    wrong = int((err > WRONG_PX).sum())
    n_lines = sum(int(np.isfinite(r["line_off"][:, 0]).sum()) for r in rows if "line_off" in r)
    bad_lines = sum(int(r["line_bad"].sum()) for r in rows if "line_off" in r)
    posed = [r for r in rows if r["pose"]]
    t_feat = [r["t_feat"] for r in rows if "t_feat" in r]
    t_all = [r["t_feat"] + r.get("t_pose", 0.0) for r in rows if "t_feat" in r]
    cells = [name, f"{n}", f"{sum(r['n_seen'] >= 6 for r in rows)}",
             f"{np.mean(seen):.1f} ({seen.min() if n else 0}-{seen.max() if n else 0})",
             f"{np.sqrt(np.mean(err ** 2)):.3f}" if len(err) else "-",
             f"{err.max():.2f}" if len(err) else "-", f"{wrong}",
             f"{n_lines / max(n, 1):.1f} / {bad_lines}"]
    if posed:
        pe = pose_errors(np.array([r["R"] for r in posed]), np.array([r["t"] for r in posed]),
                         np.array([r["Re"] for r in posed]), np.array([r["te"] for r in posed]))
        cells += [f"{len(posed)} / {sum(r['ok'] for r in rows)}",
                  " ".join(f"{x:+.3f}" for x in np.mean(pe.dof, axis=0)),
                  " ".join(f"{x:.3f}" for x in np.std(pe.dof, axis=0)),
                  f"{np.percentile(pe.rot_deg, 95):.3f} / {np.percentile(pe.trans_mm, 95):.3f}",
                  f"{np.max(pe.rot_deg):.3f} / {np.max(pe.trans_mm):.3f}"]
    else:
        cells += ["0 / 0", "-", "-", "-", "-"]
    cells += [f"{np.median(t_feat):.0f} / {np.median(t_all):.0f}" if t_feat else "-"]
    return "| " + " | ".join(cells) + " |"


COLUMNS = ["set", "images", "features ok", "corners seen, mean (min-max)",
           "RMS px (seen, not hidden)", "max px", "seen > 3 px",
           "lines seen per image / off the edge band", "dm+ pose / accepted",
           "bias a b g [deg] X Y Z [mm]", "std", "p95 rot deg / trans mm", "max rot / trans",
           "median ms features / +dm+"]
HEADER = "| " + " | ".join(COLUMNS) + " |\n" + "|---" * len(COLUMNS) + "|"


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folders", nargs="+")
    ap.add_argument("--limit", type=int, default=None)
    ap.add_argument("--verbose", action="store_true", help="one line per image")
    ap.add_argument("--csv", default=None, help="per-image rows to this file")
    ap.add_argument("--params", default=None, help="FeatureParams changes as JSON")
    a = ap.parse_args()
    cv2.setNumThreads(1)
    lines, per_image = [], []
    for folder in map(Path, a.folders):
        if "heldback" in folder.name:
            raise SystemExit("held-back sets are for the final report only")
        camera, holder, entries = load_image_set(folder)
        import json
        changes = json.loads(a.params) if a.params else {}
        params = FeatureParams.for_camera(camera, **changes)
        rows = []
        for e in entries[: a.limit]:
            r = run_image(folder, e, camera, holder, params)
            rows.append(r)
            per_image.append((folder.name, r))
            if a.verbose:
                err = r["err"]
                print(f"{folder.name}/{r['file']}: seen {r['n_seen']:2d} (hidden "
                      f"{r['n_hidden']}), rms {np.sqrt(np.mean(err ** 2)) if len(err) else 0:.3f}"
                      f" max {err.max() if len(err) else 0:.2f} px, "
                      f"{'ok' if r['ok'] else 'refused'}: {r['reason'][:120]}", flush=True)
        lines.append(table(folder.name, rows))
    print(HEADER)
    print("\n".join(lines))
    if a.csv:
        with open(a.csv, "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(["set", "file", "n_seen", "n_hidden", "rms_px", "max_px", "ok", "reason"])
            for name, r in per_image:
                err = r["err"]
                w.writerow([name, r["file"], r["n_seen"], r["n_hidden"],
                            f"{np.sqrt(np.mean(err ** 2)):.4f}" if len(err) else "",
                            f"{err.max():.4f}" if len(err) else "", r["ok"], r["reason"]])


if __name__ == "__main__":
    main()
