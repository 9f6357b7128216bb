"""Detected vs true corners on one rendered pose per preset (docs/notes/images.md, "Measured").

Renders pose (3, -4, 5 deg, 10, -8, 610 mm) with the Table 1 camera and seed 1 for each preset,
runs :func:`cutterpose.image.features.detect_features` with the given parameters and prints the RMS,
the largest coordinate error and the mean offset of the corners (best cyclic assignment), the
threshold and the segmentation path used, and the time per stage.

Usage::

    python benchmarks/corners_presets.py [--params '{"chain": "paper"}'] easy dim worn hard

(default: the field chain; ``{"chain": "paper"}`` the threshold chain of section 2.1,
``{"chain": "paper", "refine": false}`` the paper's own lines.)
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from cutterpose.errors import CutterposeError
from cutterpose.geometry.camera import default_camera
from cutterpose.geometry.holder import default_holder
from cutterpose.geometry.pose import Pose
from cutterpose.image import FeatureParams, detect_features
from cutterpose.render.analytic import render_holder


def best_assignment(c: np.ndarray, true: np.ndarray):
    """(RMS, per-corner error) under the best cyclic shift and direction."""
    best = None
    for seq in (c, c[::-1]):
        for s in range(len(c)):
            d = np.roll(seq, s, axis=0) - true
            e = float(np.sqrt(np.mean(np.sum(d ** 2, axis=1))))
            if best is None or e < best[0]:
                best = (e, d)
    return best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("presets", nargs="+")
    ap.add_argument("--params", default="{}", help="FeatureParams fields as JSON")
    a = ap.parse_args()
    cam, hol = default_camera("table1"), default_holder()
    pose = Pose.from_euler(3, -4, 5, 10, -8, 610)
    params = FeatureParams(**json.loads(a.params))
    for name in a.presets:
        r = render_holder(pose, cam, hol, name, seed=1)
        t = time.perf_counter()
        try:
            f = detect_features(r.image, cam, hol, params)
        except CutterposeError as e:
            print(f"{name:9s} refused: {e}")
            continue
        ms = (time.perf_counter() - t) * 1e3
        if f.order == "holder":  # field chain: model order, NaN for corners not seen
            d = (f.corners_px - r.corners_px)[f.visible]
            e = float(np.sqrt(np.mean(np.sum(d ** 2, axis=1))))
        else:
            e, d = best_assignment(f.corners_px, r.corners_px)
        print(f"{name:9s} rms {e:.3f} px, max {np.abs(d).max():.2f} px, mean "
              f"{np.round(d.mean(axis=0), 3)}, seen {int(f.visible.sum())}/20, threshold "
              f"{f.threshold}, {f.segmentation}, {ms:.0f} ms",
              {k: round(v, 1) for k, v in f.timings_ms.items()})


if __name__ == "__main__":
    main()
