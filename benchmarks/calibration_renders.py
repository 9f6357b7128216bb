"""Every target kind rendered with ``render-plate`` and calibrated with ``calibrate`` (issue 29).

    python benchmarks/calibration_renders.py --out results/calibration_renders [--count 12]

No real photographs of light circles, asymmetric grids, chessboards or ChArUco boards are at
hand, so each kind is rendered through the Table 1 camera (4112 x 3008, division model) with
the holder renderer's sensor model (``easy`` preset) by the CLI, then calibrated by the CLI
with the division model (the rendering camera's model) and OpenCV's (k1, k2, k3, p1, p2). The
table compares the result with the rendering camera (truth.json): focal length, principal
point, RMS, images used.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

KINDS = ["circles:9x7:30", "circles:9x7:30:light", "circles:10x10:25:origin-dot",
         "acircles:4x11:20", "acircles:4x11:20:light", "chessboard:9x6:30",
         "charuco:7x9:30:22:DICT_5X5_100", "caltab:7x7:30"]


def cli(*args) -> str:
    r = subprocess.run([sys.executable, "-m", "cutterpose.cli", *args], capture_output=True,
                       text=True)
    if r.returncode != 0:
        raise SystemExit(f"cutterpose {' '.join(args)} failed:\n{r.stdout}\n{r.stderr}")
    return r.stdout


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--count", type=int, default=12)
    ap.add_argument("--kinds", nargs="*", default=KINDS)
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for spec in args.kinds:
        folder = out / spec.replace(":", "_")
        t0 = time.time()
        cli("render-plate", "--target", spec, "--count", str(args.count), "--seed", "1",
            "--out", str(folder))
        t_render = time.time() - t0
        truth = json.loads((folder / "truth.json").read_text())["camera"]
        f_true = truth["focal_length_m"] / truth["pixel_size_m"][0]
        pp_true = np.array(truth["principal_point_px"])
        for model, extra in (("division", []), ("opencv", [])):
            cam_file = folder / f"camera_{model}.json"
            t1 = time.time()
            cli("calibrate", str(folder), "--target", spec, "--model", model, "--no-pictures",
                "--out", str(cam_file), *extra)
            rep = json.loads(cam_file.with_name(cam_file.stem + ".report.json").read_text())
            cam = rep["camera"]
            if model == "division":
                f = cam["focal_length_m"] / cam["pixel_size_m"][0]
                pp = np.array(cam["principal_point_px"])
            else:
                K = np.array(cam["camera_matrix"])
                f, pp = K[0, 0], K[:2, 2]
            row = {"target": spec, "model": model, "used": len(rep["per_image_rms_px"]),
                   "skipped": rep["skipped"], "f_err_pct": 100 * (f / f_true - 1),
                   "pp_err_px": float(np.hypot(*(pp - pp_true))), "rms_px": rep["rms_px"],
                   "render_s": t_render, "calibrate_s": time.time() - t1}
            rows.append(row)
            print(f"| `{spec}` | {model} | {row['used']} of {args.count} | "
                  f"{row['f_err_pct']:+.4f} % | {row['pp_err_px']:.2f} | {row['rms_px']:.4f} |",
                  flush=True)
    (out / "table.json").write_text(json.dumps(rows, indent=1) + "\n")


if __name__ == "__main__":
    main()
