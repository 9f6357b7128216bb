"""How the residuals of ``dm+b``'s pose fit hang together: per image, the spread of the edges'
mean residuals against the spread within an edge, and the noise budget with and without a
shared part per edge (docs/notes/edge_band.md, "Errors one edge shares").

Usage: python benchmarks/band_residuals_by_edge.py IMAGE_SET COUNT [--edge-look LOOK.json]
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import cv2
import numpy as np

from cutterpose.geometry.camera import camera_from_dict
from cutterpose.geometry.holder import holder_from_dict
from cutterpose.pipeline import DOF_NAMES, measure
from cutterpose.solvers.edge_band import _jacobian, _sd, edge_noise_cov


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("images", type=Path)
    ap.add_argument("count", type=int)
    ap.add_argument("--edge-look", default=None)
    a = ap.parse_args()
    look = None
    if a.edge_look:
        from cutterpose.calibration.edge_look import load_edge_look
        look = load_edge_look(a.edge_look)
    doc = json.loads((a.images / "truth.json").read_text())
    cam, holder = camera_from_dict(doc["camera"]), holder_from_dict(doc["holder"])
    within, between, ratio = [], [], []
    for e in doc["images"][: a.count]:
        m = measure(cv2.imread(str(a.images / e["file"]), cv2.IMREAD_GRAYSCALE), cam, holder,
                    edge_look=look)
        if not m.estimate or "band" not in m.estimate.info:
            continue
        b = m.estimate.info["band"]
        bp = b.fit.profiles
        v = np.isfinite(b.residuals_px)
        r, edge = b.residuals_px[v], bp.edge[v]
        means = np.array([r[edge == k].mean() for k in np.unique(edge)])
        within += list(r - means[np.searchsorted(np.unique(edge), edge)])
        between += list(means)
        # the noise budget's tilt std with and without the shared part
        sd = _sd(b.fit.best)[v]
        J = _jacobian(b.dof, bp.points_holder_mm[v], bp.normals_ideal[v], cam.K) / sd[:, None]
        z, w = r / sd, b.weights[v]
        shared = edge_noise_cov(J, z, w, edge)
        # the budget before the seventh session: independent segments, chi^2 (J^T W J)^-1 with
        # scipy's Jacobian at the solution, whose rows already carry the soft-L1 curvature
        # (w^1.5), so the information was weighted by w^4
        indep = max(b.chi, 1.0) ** 2 * np.linalg.inv(J.T @ (w[:, None] ** 4 * J))
        ratio.append([math.sqrt(shared[k, k] / indep[k, k]) for k in range(6)])
    print(f"{a.images.name}: {len(ratio)} images; residual std within an edge "
          f"{np.std(within):.3f} px, of the edges' means {np.std(between):.3f} px; "
          "noise std now / before, median (p10, p90): " + ", ".join(
              f"{n} {np.median(q):.2f} ({np.percentile(q, 10):.2f}, {np.percentile(q, 90):.2f})"
              for n, q in zip(DOF_NAMES, np.array(ratio).T)))


if __name__ == "__main__":
    main()
