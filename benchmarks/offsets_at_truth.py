"""Where the tracker's edges lie from the design edge at the *true* pose, frame by frame, and
where the edge model says they should (docs/RESULTS.md section 14).

For every frame of a rendered approach (``truth.json`` with the true poses and, per edge, the
rendered break radius along it): the tracker runs as usual (``Tracker``, ``dm+b``); on each
tracked frame the offsets of its lines from the design edges are measured at the true pose
(:func:`cutterpose.tracking.line_offsets_mm`, per edge end), and the edge model's offsets of the
innermost rise (:mod:`cutterpose.image.edge_model`, nominal look, the rendered profile shape and
each edge's rendered radius at its ends) are evaluated at the same pose. Printed per frame: the
distance and the median over the edges of both; then the change from the first three tracked
frames to the last three, per edge and as the median (what the view model of the tracker has
to follow between anchors), and the fit of a part fixed in pixels (``a_k + b Z / f``, one ``b``
for all edges, and one per edge) to the measured offsets.

Usage: PYTHONPATH=src python benchmarks/offsets_at_truth.py SEQUENCE [--frames N]
"""

from __future__ import annotations

import argparse
import json
import warnings
from pathlib import Path

import numpy as np

from cutterpose.frames import load_frame
from cutterpose.geometry.camera import camera_from_dict
from cutterpose.geometry.holder import holder_from_dict
from cutterpose.geometry.pose import Pose
from cutterpose.image import edge_model as em
from cutterpose.tracking import Tracker, line_offsets_mm


def model_offsets_mm(pose: Pose, camera, holder, radii_ends_mm: np.ndarray, shape: str):
    """(N, 2) edge-model offsets per edge (start, end) for each edge end's own radius."""
    look = em.EdgeLook(shape=shape)
    view = em.edge_views(pose.R, pose.t_mm, camera.K, holder, look)
    # (corner i, side 0) ends edge i - 1, (i, 1) starts edge i
    r_corner = np.column_stack([np.roll(radii_ends_mm[:, 1], 1), radii_ends_mm[:, 0]])
    w = em.tabulated_w_px(r_corner[..., None], view, look)
    if w is None:
        w = np.stack([em.edge_offsets_mm(np.array([r]), view, look, with_rival=False)["w_px"]
                      [..., 0] for r in np.unique(r_corner)])   # (exact model, slower)
        idx = np.searchsorted(np.unique(r_corner), r_corner)
        w = np.take_along_axis(np.moveaxis(w, 0, -1), idx[..., None], -1)
    delta = w[..., 0] / view.a_s
    return np.column_stack([delta[:, 1], np.roll(delta[:, 0], -1)])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sequence")
    ap.add_argument("--frames", type=int, default=0, help="the first N frames (0: all)")
    a = ap.parse_args()
    seq = Path(a.sequence)
    truth = json.loads((seq / "truth.json").read_text())
    cam = camera_from_dict(truth["camera"])
    hol = holder_from_dict(truth["holder"])
    first = truth["images"][0]
    edges = first.get("edges")
    if not edges:
        raise SystemExit(f"{seq}: truth.json has no rendered edge radii (a pbr sequence has)")
    radii = np.array([[e["radius_samples_mm"][0], e["radius_samples_mm"][-1]] for e in edges])
    shape = "chamfer" if first.get("edge_profile") == "chamfer" else "round"
    f_px = float(cam.focal_px)
    tr = Tracker(cam, hol, "dm+b")
    images = truth["images"][:a.frames or None]
    Z, meas, model = [], [], []
    print(f"{seq.name}: offsets from the design edge at the true pose (mm, median over edges)")
    for e in images:
        r = tr.update(load_frame(seq / e["file"]))
        if r.mode != "track":
            continue
        T = Pose(np.array(e["R_cam_holder"]), np.array(e["t_cam_holder_mm"]))
        m = line_offsets_mm(T, r.lines_found, r.edges_found, hol, cam.K).mean(axis=1)
        d = model_offsets_mm(T, cam, hol, radii, shape).mean(axis=1)
        Z.append(float(T.t_mm[2]))
        meas.append(m)
        model.append(d)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            print(f"  frame {e['frame']:3d}  Z {T.t_mm[2]:6.1f} mm  tracked lines "
                  f"{np.nanmedian(m):+.3f}  edge model {np.nanmedian(d):+.3f}")
    if len(Z) < 6:
        print("fewer than 6 tracked frames: no trend")
        return 1
    meas, model, Z = np.array(meas), np.array(model), np.array(Z)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        dm = np.nanmean(meas[-3:], 0) - np.nanmean(meas[:3], 0)
        dd = model[-3:].mean(0) - model[:3].mean(0)
        print(f"change over the approach ({Z[:3].mean():.0f} -> {Z[-3:].mean():.0f} mm), median "
              f"over the edges: tracked lines {np.nanmedian(dm):+.3f} mm, edge model "
              f"{np.nanmedian(dd):+.3f} mm")
        print("  per edge, tracked lines: " + " ".join(f"{v:+.2f}" for v in dm))
        print("  per edge, edge model:    " + " ".join(f"{v:+.2f}" for v in dd))
        # a part fixed in pixels: a_k + b Z / f
        x = Z / f_px
        ok = np.isfinite(meas)
        mean_x = np.array([x[ok[:, k]].mean() if ok[:, k].any() else np.nan
                           for k in range(meas.shape[1])])
        xc = np.where(ok, x[:, None] - mean_x, 0.0)
        oc = np.where(ok, meas - np.nanmean(meas, 0), 0.0)
        b = float((xc * oc).sum() / (xc ** 2).sum())
        bk = (xc * oc).sum(0) / np.maximum((xc ** 2).sum(0), 1e-12)

        def rms(res):
            return float(np.sqrt(np.mean(res[ok] ** 2)))

        print(f"a part fixed in pixels, a_k + b Z/f: rms about a constant per edge "
              f"{rms(oc):.3f} mm, with one b = {b:.2f} px {rms(oc - b * xc):.3f} mm, with b per "
              f"edge {rms(oc - bk * xc):.3f} mm (b per edge {np.nanmin(bk):.1f}..."
              f"{np.nanmax(bk):.1f} px)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
