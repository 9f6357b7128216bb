"""Every target kind's detector on every kind of real image: no traceback, a reason, a time.

    python benchmarks/calibration_sweep.py [--per-folder 3] [ROOT ...]

Default roots: Debian's visp-images-data (``/usr/share/visp-images-data/ViSP-images``: scenes,
objects, AprilTags, video frames, calibration dots) and tests/data/real. At most
``--per-folder`` images of each folder, each searched for each target of ``SPECS``; prints the
detections, the slowest searches and any exception (there should be none).
"""

from __future__ import annotations

import argparse
import collections
import time
import traceback
from pathlib import Path

import cv2

from cutterpose.calibration.targets import target_from_spec

SPECS = ["circles:6x6:30", "circles:10x10:25.4:origin-dot", "acircles:4x11:20:light",
         "chessboard:9x6:25", "charuco:5x7:30:22:DICT_5X5_100"]
ROOTS = ["/usr/share/visp-images-data/ViSP-images",
         str(Path(__file__).resolve().parents[1] / "tests" / "data" / "real")]


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("roots", nargs="*", default=ROOTS)
    ap.add_argument("--per-folder", type=int, default=3)
    args = ap.parse_args()
    by_dir = collections.defaultdict(list)
    for root in args.roots:
        for p in sorted(Path(root).rglob("*")):
            if p.suffix.lower() in (".pgm", ".png", ".jpg", ".jpeg", ".ppm"):
                by_dir[p.parent].append(p)
    files = [f for v in by_dir.values() for f in v[::max(1, len(v) // args.per_folder)]
             [:args.per_folder]]
    targets = [target_from_spec(s) for s in SPECS]
    found, times, errors, no_reason, n = collections.defaultdict(list), [], 0, 0, 0
    t_all = time.time()
    for f in files:
        img = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
        if img is None:
            continue
        n += 1
        for t in targets:
            t0 = time.time()
            try:
                d = t.detect(img)
                if d:
                    found[t.spec()].append(f.name)
                elif not d.reason:
                    no_reason += 1
            except Exception:  # the point of the sweep: report, do not stop
                errors += 1
                print(f"EXCEPTION {f} {t.spec()}")
                traceback.print_exc(limit=4)
            times.append((time.time() - t0, f.name, img.shape, t.spec()))
        print(f"{f.relative_to(f.parents[1])} {img.shape[1]}x{img.shape[0]}: "
              f"{sum(dt for dt, *_ in times[-len(targets):]):.1f} s", flush=True)
    print(f"{n} images x {len(targets)} targets in {time.time() - t_all:.0f} s: {errors} "
          f"exceptions, {no_reason} failures without a reason")
    for s in SPECS:
        print(f"  {s}: found in {len(found[s])} images {sorted(set(found[s]))[:8]}")
    times.sort(reverse=True)
    print("slowest:", "; ".join(f"{dt:.1f} s {name} {shape[1]}x{shape[0]} {spec}"
                                for dt, name, shape, spec in times[:5]))


if __name__ == "__main__":
    main()
