"""Speed of ``measure`` with ``dm+b`` (the default) and ``dm+r`` against ``dm+`` on the same
images, one core
(issue 13: <= 50 ms from memory; docs/notes/edge_model.md, section "Cost").

    PYTHONPATH=src python benchmarks/dmr_speed.py [--repeats 5] [--pbr /work/data/pbr_new_s200]
        [--count 10]
    PYTHONPATH=src python benchmarks/dmr_speed.py --grid   # dm+r fitted on the offset grid
    PYTHONPATH=src python benchmarks/dmr_speed.py --write-grid   # rebuild the offset grid
    PYTHONPATH=src python benchmarks/dmr_speed.py --edge-look look.json  # + dm+b calibrated

Images: ``make bench``'s image (analytic ``easy`` preset at 3,-4,2,5,-8,610), the analytic
``new`` preset (0.5-1.5 mm fillets) at the same pose, and the first ``count`` images of a pbr
set (read into memory first). Per image the fastest of ``repeats`` interleaved runs of each
method (the minimum filters out the other jobs of a shared machine), then the median over the
images of the wall time and of the ``solve`` and ``quality`` stages (``timings_ms``).

``--write-grid`` rebuilds ``src/cutterpose/data/edge_offset_grid.npz`` (the edge model's
offsets tabulated over the view, :func:`cutterpose.image.edge_model.build_offset_grid`;
~1 min): needed after any change of the edge model or of ``EdgeLook``'s defaults.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_v] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

cv2.setNumThreads(1)

from cutterpose.geometry.camera import camera_from_dict, default_camera  # noqa: E402
from cutterpose.geometry.holder import default_holder  # noqa: E402
from cutterpose.geometry.pose import Pose  # noqa: E402
from cutterpose.image import edge_model  # noqa: E402
from cutterpose.pipeline import measure  # noqa: E402
from cutterpose.render.analytic import render_holder  # noqa: E402

METHODS = ("dm+", "dm+r", "dm+b")
TARGET_MS = 50.0


def write_grid() -> Path:
    """Tabulate the nominal look's offsets for both edge shapes and write the package file."""
    from cutterpose.image.edge_model import EdgeLook, build_offset_grid

    keys, grids = [], []
    for shape in ("round", "chamfer"):
        t0 = time.perf_counter()
        look = EdgeLook(shape=shape)
        grids.append(build_offset_grid(look))
        keys.append(edge_model.look_key(look))
        print(f"{shape}: {time.perf_counter() - t0:.1f} s, {np.isnan(grids[-1]).sum()} NaN")
    out = Path(edge_model.__file__).parents[1] / "data" / edge_model.OFFSET_GRID_FILE
    np.savez_compressed(out, theta_deg=edge_model.GRID_THETA_DEG, m=edge_model.GRID_M,
                        rho_px=edge_model.GRID_RHO_PX, keys=np.array(keys),
                        **{f"grid_{i}": g for i, g in enumerate(grids)})
    print(f"wrote {out}")
    return out


def _images(pbr: str, count: int):
    cam = default_camera("table1")
    pose = Pose.from_euler(3, -4, 2, 5, -8, 610)
    yield "bench (easy)", render_holder(pose, cam, default_holder(), seed=1).image, cam
    yield "new preset", render_holder(pose, cam, default_holder(), "new", seed=1).image, cam
    if pbr and count:
        doc = json.loads((Path(pbr) / "truth.json").read_text())
        scam = camera_from_dict(doc["camera"])
        for e in doc["images"][:count]:
            img = cv2.imread(str(Path(pbr) / e["file"]), cv2.IMREAD_GRAYSCALE)
            yield f"pbr {e['file']}", img, scam


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--pbr", default="/work/data/pbr_new_s200")
    ap.add_argument("--count", type=int, default=10, help="pbr images")
    ap.add_argument("--write-grid", action="store_true")
    ap.add_argument("--grid", action="store_true",
                    help="dm+r on the shipped offset grid (edge_radius.TABULATED_TABLES)")
    ap.add_argument("--edge-look", help="also dm+b with this calibrated edge look "
                    "(`cutterpose calibrate-edge-look`), as 'dm+b/look'")
    a = ap.parse_args()
    methods = METHODS
    look = None
    if a.edge_look:
        from cutterpose.calibration.edge_look import load_edge_look

        look = load_edge_look(a.edge_look)
        methods = METHODS + ("dm+b/look",)
    if a.grid:
        from cutterpose.solvers import edge_radius

        edge_radius.TABULATED_TABLES = True
    if a.write_grid:
        write_grid()
        return
    holder = default_holder()
    rows = {m: [] for m in methods}
    for label, img, cam in _images(a.pbr, a.count):
        measure(img, cam, holder)                      # warm-up (imports, caches)
        best = {m: (np.inf, {}, False) for m in methods}
        for _ in range(a.repeats):
            for m in methods:
                t0 = time.perf_counter()
                res = (measure(img, cam, holder, method="dm+b", edge_look=look)
                       if m == "dm+b/look" else measure(img, cam, holder, method=m))
                dt = 1e3 * (time.perf_counter() - t0)
                if dt < best[m][0]:
                    best[m] = (dt, dict(res.timings_ms), bool(res.ok))
        for m in methods:
            rows[m].append(best[m])
        print(f"{label:22s} " + "  ".join(
            f"{m}: {best[m][0]:6.1f} ms (solve {best[m][1].get('solve', np.nan):5.1f}, "
            f"quality {best[m][1].get('quality', np.nan):5.1f}, ok {best[m][2]})"
            for m in methods), flush=True)
    print(f"\nmedian over {len(rows['dm+'])} images, fastest of {a.repeats} per image, one "
          f"thread:")
    for m in methods:
        wall = np.median([r[0] for r in rows[m]])
        st = {k: np.median([r[1].get(k, np.nan) for r in rows[m]]) for k in ("solve", "quality")}
        print(f"  {m:5s} measure {wall:6.1f} ms (target {TARGET_MS:.0f}: "
              f"{'ok' if wall <= TARGET_MS else 'SLOWER'}); solve {st['solve']:.1f} ms, "
              f"quality {st['quality']:.1f} ms")
    for m in methods[1:]:
        extra = np.median([r[0] - q[0] for r, q in zip(rows[m], rows["dm+"])])
        print(f"  {m} costs {extra:.1f} ms more than dm+ (median of the per-image differences)")


if __name__ == "__main__":
    main()
