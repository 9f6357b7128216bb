"""Speed benchmark: median time per solve of every method, as a ratio to OpenCV's SQPnP measured
in the same run, and the time of `measure` on a full 4112 x 3008 image (from memory and from
its PNG file), per stage, as ratios to a naive OpenCV chain and to SQPnP timed in the same run
(issue 13: <= 50 ms from memory, <= 130 ms with the PNG decode, one core), and tracking: a
rendered 20-frame approach (analytic ``field`` preset, 900 -> 600 mm) tracked frame by frame,
the tracked frames' CPU time as a ratio to the full measurement of the same frames (issue 13:
<= 15 ms a tracked frame).

Runs on one core (BLAS and OpenCV threads pinned to 1), so the figures compare with the issues'
single-core targets. Usage: ``make bench`` or ``python benchmarks/bench.py [--trials N]
[--skip-solvers] [--images SET_DIR ...]``. On a shared machine absolute times drift: the ratios
and the CPU times are the figures to compare.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_v] = "1"

import argparse  # noqa: E402
import resource  # noqa: E402
import time  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

cv2.setNumThreads(1)

from cutterpose.experiments.synthetic import generate_trials  # noqa: E402
from cutterpose.geometry.holder import default_holder  # noqa: E402
from cutterpose.methods import get_method  # noqa: E402

# method -> target median in microseconds (from the issues)
TARGETS_US = {"dlt": 200, "epnp": 200, "rpnp": 200, "aspnp": 20_000, "opnp": 20_000,
              "dm": 50_000, "dm+": 50_000}
METHODS = ["opencv-sqpnp", "opencv-ippe-lm", "dlt", "epnp", "rpnp", "aspnp", "opnp",
           "opnp+lm", "initial", "dm", "dm+"]


def _paired_us(fn, ref, inputs, repeat):
    """Median over inputs of the fastest of ``repeat`` calls per input, in microseconds, for
    ``fn`` and for the reference ``ref``, their calls interleaved.

    The minimum per input filters out the other jobs of a shared machine; interleaving puts the
    method and the reference under the same machine conditions, so their ratio is steady even
    when absolute times drift (they moved by 40 % within an hour here).
    """
    best_f, best_r = [], []
    for x in inputs:
        tf = tr = np.inf
        for _ in range(repeat):
            t0 = time.perf_counter()
            fn(x)
            t1 = time.perf_counter()
            if ref is not None:
                ref(x)
            t2 = time.perf_counter()
            tf, tr = min(tf, t1 - t0), min(tr, t2 - t1)
        best_f.append(tf)
        best_r.append(tr)
    return 1e6 * float(np.median(best_f)), 1e6 * float(np.median(best_r))


# fast methods get more repeats (cheap); slow ones fewer, to keep the bench short
FAST = ("opencv-sqpnp", "opencv-ippe-lm", "dlt", "epnp", "rpnp")


def bench_solvers(n_trials: int) -> None:
    tr = generate_trials(n_trials, 1.0, seed=11)
    cam, holder = tr.camera, default_holder()
    P = holder.points_holder_mm.reshape(-1, 1, 3)

    def ref(x):
        return cv2.solvePnP(P, x.reshape(-1, 1, 2), cam.K, None, flags=cv2.SOLVEPNP_SQPNP)

    print("reference: cv2.solvePnP(SOLVEPNP_SQPNP) called directly, 20 points at 1 px, timed\n"
          "interleaved with each fast method (fastest of 15 calls per input); slow methods\n"
          f"(fastest of 2) use the fast rows' median reference; median over {n_trials} inputs;\n"
          "one thread\n")
    print(f"{'method':16s} {'median us':>11s} {'SQPnP us':>9s} {'x SQPnP':>8s} {'target us':>10s}"
          "  verdict")
    refs = []
    for _ in range(2):  # warm the CPU up before the first row
        _paired_us(ref, ref, tr.points_px[:50], 5)
    for name in METHODS:
        try:
            m = get_method(name)
        except Exception as e:  # noqa: BLE001
            print(f"{name:16s} {'-':>11s}  not available ({e})")
            continue
        pts = tr.points_px
        if not m.needs_correspondences:
            # contour order with an arbitrary start, as the image pipeline delivers it
            pts = np.roll(pts, 7, axis=1)

        def fn(x, m=m):
            return m.solve(x, cam, holder)

        fn(pts[0])  # warm-up: imports, caches, stored templates
        if name in FAST:
            us, ref_us = _paired_us(fn, ref, pts, 15)
            refs.append(ref_us)
        else:
            # a slow method evicts the reference's caches: interleaving would inflate it, so
            # the slow rows use the median reference of the fast rows
            us, _ = _paired_us(fn, None, pts, 2)
            ref_us = float(np.median(refs))
        tgt = TARGETS_US.get(name)
        verdict = "" if tgt is None else ("ok" if us < tgt else "SLOWER THAN TARGET")
        print(f"{name:16s} {us:11.1f} {ref_us:9.1f} {us / ref_us:8.1f} {tgt if tgt else '':>10} "
              f"{verdict:>4s}")


def naive_chain(img, cam, holder):
    """The floor of an image-to-pose chain with OpenCV alone (issue 13's reference): Otsu
    threshold of the whole frame, the largest hole of the bright region, a 20-vertex polygon,
    undistorted, IPPE. No sub-pixel work, no checks: a speed reference, not a method."""
    _, binary = cv2.threshold(img, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    contours, hier = cv2.findContours(binary, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_SIMPLE)
    holes = [c for c, h in zip(contours, hier[0]) if h[3] >= 0] if hier is not None else []
    if not holes:
        return None
    c = max(holes, key=cv2.contourArea)
    poly = cv2.approxPolyDP(c, 0.01 * cv2.arcLength(c, True), True)[:, 0, :].astype(float)
    if len(poly) != holder.n_corners:
        return None
    ideal = cam.undistort_px(poly)
    P = holder.points_holder_mm
    # correspondences by the closest cyclic shift to the nominal projection (no symmetry care)
    nominal = cam.project(P + [0.0, 0.0, 600.0])
    k = int(np.argmin([np.sum((np.roll(ideal, -s, 0) - nominal) ** 2) for s in range(len(P))]))
    ok, rvec, tvec = cv2.solvePnP(P, np.roll(ideal, -k, 0), cam.K, None,
                                  flags=cv2.SOLVEPNP_IPPE)
    return tvec if ok else None


def _images(folder, count):
    """Up to ``count`` images of an image set (truth.json order) as 8-bit grey arrays, with
    their paths."""
    import json
    from pathlib import Path

    from cutterpose.geometry.camera import camera_from_dict
    from cutterpose.image import load_image

    doc = json.loads((Path(folder) / "truth.json").read_text())
    cam = camera_from_dict(doc["camera"])
    paths = [Path(folder) / e["file"] for e in doc["images"][:count]]
    return cam, [load_image(p) for p in paths], paths


def _sqpnp_ref(cam, holder):
    """The solver reference of the speed ratios: SQPnP on 20 corners at 1 px (one input)."""
    tr = generate_trials(1, 1.0, seed=11)
    P = holder.points_holder_mm.reshape(-1, 1, 3)
    x = tr.points_px[0].reshape(-1, 1, 2)
    K = tr.camera.K

    def ref():
        return cv2.solvePnP(P, x, K, None, flags=cv2.SOLVEPNP_SQPNP)

    return ref


def _time_image(img, path, cam, holder, repeats, sqpnp, method="dm+b", edge_look=None,
                limits=None):
    """Fastest of ``repeats`` interleaved runs of: ``measure`` from memory (wall and CPU
    time), ``measure`` of the PNG file (decode included), the naive chain and SQPnP; with the
    stage times of the fastest run and the verdict. Interleaving puts all under the same
    machine conditions; the minimum filters out the other jobs of a shared machine."""
    from cutterpose.pipeline import measure

    best = {"wall": np.inf, "cpu": np.inf, "png": np.inf, "naive": np.inf, "sqpnp": np.inf}
    stages, ok = {}, False
    for _ in range(repeats):
        c0, t0 = time.process_time(), time.perf_counter()
        try:
            m = measure(img, cam, holder, method=method, edge_look=edge_look, limits=limits)
        except Exception:  # noqa: BLE001 - a refused image still took its time
            m = None
        t1, c1 = time.perf_counter(), time.process_time()
        if t1 - t0 < best["wall"]:
            stages = dict(getattr(m, "timings_ms", None) or {})
            ok = bool(m is not None and m.ok)
        best["wall"] = min(best["wall"], t1 - t0)
        best["cpu"] = min(best["cpu"], c1 - c0)
        if path is not None:
            t2 = time.perf_counter()
            try:
                measure(path, cam, holder, method=method, edge_look=edge_look, limits=limits)
            except Exception:  # noqa: BLE001
                pass
            best["png"] = min(best["png"], time.perf_counter() - t2)
        c3, t3 = time.process_time(), time.perf_counter()
        naive_chain(img, cam, holder)
        t4, c4 = time.perf_counter(), time.process_time()
        sqpnp()
        t5 = time.perf_counter()
        best["naive"] = min(best["naive"], t4 - t3)
        best["naive_cpu"] = min(best.get("naive_cpu", np.inf), c4 - c3)
        best["sqpnp"] = min(best["sqpnp"], t5 - t4)
    return {k: 1e3 * v for k, v in best.items()}, stages, ok


TARGET_MS, TARGET_PNG_MS = 50.0, 130.0   # issue 13: one core, from memory / with the decode


def _report(label, rows):
    med = {k: float(np.median([r[k] for r in rows])) for k in rows[0]}
    verdict = "ok" if med["wall"] <= TARGET_MS else "SLOWER THAN TARGET"
    png = (f"; from the PNG file {med['png']:.1f} ms (target {TARGET_PNG_MS:.0f}: "
           f"{'ok' if med['png'] <= TARGET_PNG_MS else 'SLOWER THAN TARGET'})"
           if np.isfinite(med["png"]) else "")
    print(f"measure on {label}: median {med['wall']:.1f} ms wall, {med['cpu']:.1f} ms CPU "
          f"(target {TARGET_MS:.0f} ms: {verdict}){png}\n"
          f"  = x {med['wall'] / med['naive']:.1f} the naive OpenCV chain ({med['naive']:.2f} ms;"
          f" CPU: x {med['cpu'] / med['naive_cpu']:.1f} its {med['naive_cpu']:.2f} ms), "
          f"x {med['wall'] / med['sqpnp']:.0f} SQPnP ({1e3 * med['sqpnp']:.1f} us)")
    return med


def _field_images(count: int, cam, holder, seed: int = 13):
    """``count`` rendered images of the ``field`` preset (bright cutter, flush surround, slurry
    lumps over edges and a corner) at random poses of the real rig's range, in memory."""
    from cutterpose.render.analytic import random_pose, render_holder

    rng = np.random.default_rng(seed)
    return [render_holder(random_pose(rng), cam, holder, "field", seed=seed + k).image
            for k in range(count)]


def _time_set(label, cam, holder, imgs, paths, repeats, sqpnp, method="dm+b", edge_look=None,
              limits=None):
    from cutterpose.pipeline import measure

    rows, accepted = [], 0
    measure(imgs[0], cam, holder, method=method, edge_look=edge_look)
    for im, p in zip(imgs, paths):
        r, _, ok = _time_image(im, p, cam, holder, max(3, repeats // 2), sqpnp, method,
                               edge_look, limits)
        rows.append(r)
        accepted += ok
    med = _report(f"{len(imgs)} {label}", rows)
    print(f"  p90 {np.percentile([r['wall'] for r in rows], 90):.1f} ms wall; "
          f"{accepted} of {len(imgs)} accepted (median {med['cpu']:.1f} ms CPU)")


def bench_measure(repeats: int = 7, image_sets: tuple = (), per_set: int = 20,
                  field_images: int = 0, methods=("dm+b", "dm+"), edge_look=None) -> None:
    """``measure`` timed per method: ``dm+b`` (the default: the design edge through a broken
    edge) and ``dm+`` (the corners; the issue-13 target of 50 ms is met by this one only).
    ``edge_look``: a look calibrated in the cell (file), given to ``dm+b`` on the image sets
    only (the sets it was calibrated for; the bench image and the rendered field images keep
    the generic looks)."""
    try:
        from cutterpose.pipeline import measure
        from cutterpose.render.analytic import render_holder
    except ImportError as e:
        print(f"\nmeasure: not available ({e})")
        return
    import tempfile
    from pathlib import Path

    from cutterpose.geometry.camera import default_camera
    from cutterpose.geometry.pose import Pose
    from cutterpose.pipeline import QualityLimits

    cam = default_camera("table1")
    holder = default_holder()
    sqpnp = _sqpnp_ref(cam, holder)
    img = render_holder(Pose.from_euler(3, -4, 2, 5, -8, 610), cam, holder, seed=1).image
    field = _field_images(field_images, cam, holder) if field_images else []
    # the analytic renderer's pocket edge is sharp: declared, so that the corner methods'
    # verdict (accepted counts) is that of a holder whose drawing says so (the --images sets
    # keep the default, a break not known)
    sharp = QualityLimits(edge_break_mm=0.0)
    sets = [(folder, *_images(folder, per_set)) for folder in image_sets]
    for method in methods:
        measure(img, cam, holder, method=method)  # warm-up: imports, cached templates
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "bench.png"
            cv2.imwrite(str(path), img)
            row, stages, _ = _time_image(img, path, cam, holder, repeats, sqpnp, method,
                                         limits=sharp)
        print(f"\n[{method}] fastest of {repeats} interleaved runs per image (measure, measure "
              "of the PNG, naive chain, SQPnP), one thread; medians over images")
        _report(f"a {img.shape[1]} x {img.shape[0]} image ({method})", [row])
        print("  stages of the fastest run (ms): " + ", ".join(
            f"{k} {v:.1f}" for k, v in stages.items()))
        if field:
            _time_set(f"rendered field-preset images (seeds 13..) ({method})", cam, holder,
                      field, [None] * len(field), repeats, sqpnp, method, limits=sharp)
        for folder, scam, imgs, paths in sets:
            look = edge_look if method == "dm+b" else None
            _time_set(f"images of {folder} ({method}{', calibrated look' if look else ''})",
                      scam, holder, imgs, paths, repeats, sqpnp, method, look)


def bench_track(n_frames: int = 20, methods=("dm+b", "dm+")) -> None:
    """Tracking an approach rendered in memory (analytic ``field`` preset, the real camera,
    900 -> 600 mm in ``n_frames``; its sharp edge declared for ``dm+``): per method, the
    tracked frames' CPU time (median, and of the frames without a re-anchor) and the full
    measurement's on the same frames, in one thread."""
    from dataclasses import replace

    from cutterpose.geometry.camera import default_camera
    from cutterpose.pipeline import measure
    from cutterpose.render.analytic import auto_exposed, preset, render_holder
    from cutterpose.render.sequence import approach_poses
    from cutterpose.tracking import Tracker, approach_limits, approach_params

    cam, holder = default_camera("table1"), default_holder()
    poses, _ = approach_poses(n_frames)
    base = preset("field")
    frames = [render_holder(p, cam, holder, base.with_(light_dn=auto_exposed(base.light_dn, p)),
                            seed=0, noise_seed=k).image for k, p in enumerate(poses)]
    print(f"\n[track] a {n_frames}-frame approach (analytic field preset, 900 -> 600 mm), one "
          "thread, CPU time")
    for method in methods:
        limits = replace(approach_limits(), edge_break_mm=0.0 if method == "dm+" else None)
        params = approach_params(cam)
        tracker = Tracker(cam, holder, method, limits=limits)
        tracked, plain, full = [], [], []
        for f in frames:
            c = time.process_time()
            r = tracker.update(f)
            ms = (time.process_time() - c) * 1e3
            if r.mode == "track":
                tracked.append(ms)
                if not r.anchor:
                    plain.append(ms)
            c = time.process_time()
            measure(f, cam, holder, method, params, limits)
            full.append((time.process_time() - c) * 1e3)
        tracker.close()
        if not tracked:
            print(f"  {method}: no frame tracked")
            continue
        med, fm = float(np.median(tracked)), float(np.median(full))
        print(f"  {method}: {len(tracked)} of {n_frames} frames tracked, {med:.1f} ms median "
              f"({np.median(plain) if plain else np.nan:.1f} ms without a re-anchor, "
              f"{len(tracked) - len(plain)} re-anchored); full measurement {fm:.1f} ms; "
              f"ratio {med / fm:.3f} (target 15 ms)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--trials", type=int, default=200)
    ap.add_argument("--skip-measure", action="store_true")
    ap.add_argument("--skip-solvers", action="store_true")
    ap.add_argument("--skip-track", action="store_true")
    ap.add_argument("--track-frames", type=int, default=20)
    ap.add_argument("--images", action="append", default=[],
                    help="an image set (folder with truth.json) to time measure on; repeatable")
    ap.add_argument("--per-set", type=int, default=20, help="images per set")
    ap.add_argument("--methods", default="dm+b,dm+",
                    help="pose methods whose measure is timed (comma-separated)")
    ap.add_argument("--field-images", type=int, default=None,
                    help="render this many field-preset images to time measure on (default "
                         "20 without --images, else 0)")
    ap.add_argument("--edge-look", default=None,
                    help="edge look file (`cutterpose calibrate-edge-look`) for dm+b on the "
                         "--images sets")
    a = ap.parse_args()
    if a.field_images is None:
        a.field_images = 0 if a.images else 20
    if not a.skip_solvers:
        bench_solvers(a.trials)
    if not a.skip_measure:
        look = None
        if a.edge_look:
            from cutterpose.calibration.edge_look import load_edge_look
            look = load_edge_look(a.edge_look)
        bench_measure(image_sets=tuple(a.images), per_set=a.per_set,
                      field_images=a.field_images, methods=tuple(a.methods.split(",")),
                      edge_look=look)
    if not a.skip_track:
        bench_track(a.track_frames)
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"\npeak resident memory of this run: {peak_mb:.0f} MB")


if __name__ == "__main__":
    main()
