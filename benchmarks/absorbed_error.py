"""What `dm+b`'s noise budget cannot see: the part of the design-edge errors that the pose
absorbs (docs/RESULTS.md section 12).

For every image of a set (``truth.json`` with the true poses): ``measure`` with ``dm+b``; then,
with the final band fit's design-edge points ``p_s`` (its inliers), the whitened errors at the
*true* pose ``e_s = n_s . (pi(X_s; T_true) - p_s) / sd_s`` are split by the projector ``P`` onto
the pose fit's Jacobian columns into the absorbed part ``P e`` (it moves the pose and leaves no
residual) and the visible part ``(I - P) e``. The noise part of the budget
(:func:`cutterpose.solvers.edge_band.edge_noise_cov`) models ``e`` as independent segments plus
a part per edge, with variances from the residuals; under that model the expected energies are
``tr(P V)`` and ``tr((I - P) V)``. Printed per image and as medians: visible / expected (1 when
the residuals describe the errors) and absorbed / expected, the latter also without the
uniform outward shift (the budget's model floor) and without the shift and a shift
proportional to each segment's view lean (``depth x tan(theta)``, the apparent depth of the
design edge). And the per-image least-squares (offset, depth) in mm of that two-term pattern:
their mean, std and second moment (what a floor for them would have to carry). Last, the
budget with that second moment as a floor in place of the uniform model floor (the pose
changes for a unit offset and depth per image, :func:`cutterpose.solvers.edge_band.design_pose`):
median Mahalanobis^2 and |e|/std of the actual errors, and the images within the tolerance,
against the budget as it is.

Usage: PYTHONPATH=src python benchmarks/absorbed_error.py IMAGE_SET [--count N] [--edge-look F]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from cutterpose.budget import budget_from_dof_cov
from cutterpose.geometry.pose import Pose, pose_errors, rotation_from_euler_deg
from cutterpose.image import detect_features, load_image
from cutterpose.image import edge_model as em
from cutterpose.image.edge_band import view_lean
from cutterpose.image_set import load_image_set
from cutterpose.pipeline import QualityLimits, measure_features
from cutterpose.solvers.edge_band import (
    _jacobian,
    _residuals,
    _sd,
    design_pose,
    variance_components,
)


def energies(e: np.ndarray, J: np.ndarray, edge: np.ndarray, patterns: np.ndarray) -> dict:
    """Absorbed and visible energies of whitened errors ``e`` (S,) against the fit's Jacobian
    ``J`` (S, 6), with the random-effect model's expectations; ``patterns`` (S, k): the
    absorbed energy is also given with their absorbed parts taken out (k = 1, then 2)."""
    Q, _ = np.linalg.qr(J)
    ea = Q.T @ e
    visible = e - Q @ ea
    s_w2, s_u2 = variance_components(visible, edge)
    same = (edge[:, None] == edge[None, :]).astype(float)
    V = max(s_w2, 1.0 - s_u2) * np.eye(len(e)) + s_u2 * same
    exp_abs = float(np.trace(Q.T @ V @ Q))
    out = {"absorbed": float(ea @ ea), "visible": float(visible @ visible),
           "exp_absorbed": exp_abs, "exp_visible": float(np.trace(V)) - exp_abs}
    for k in (1, 2):
        Lq, _ = np.linalg.qr(Q @ (Q.T @ patterns[:, :k]))
        out[f"absorbed_minus_{k}"] = out["absorbed"] - float(np.sum((Lq.T @ e) ** 2))
        out[f"exp_absorbed_minus_{k}"] = exp_abs * (6 - k) / 6
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("set", type=Path)
    ap.add_argument("--count", type=int, default=None)
    ap.add_argument("--edge-look", default=None)
    a = ap.parse_args()
    look = None
    if a.edge_look:
        from cutterpose.calibration.edge_look import load_edge_look

        look = load_edge_look(a.edge_look)
    camera, holder, entries = load_image_set(a.set)
    K = camera.K
    rows, coefs, kept = [], [], []
    for i, entry in enumerate(entries[:a.count]):
        feats = detect_features(load_image(a.set / entry["file"]), camera, holder)
        m = measure_features(feats, camera, holder, "dm+b", QualityLimits(), edge_look=look)
        band = m.estimate.info.get("band") if m.estimate is not None else None
        if band is None:
            print(f"{i:3d} no band fit: {m.quality.reason[:80]}")
            continue
        bp = band.fit.profiles
        v = np.isfinite(band.residuals_px) & (band.weights > 0.5)
        X, n, sd = bp.points_holder_mm[v], bp.normals_ideal[v], _sd(band.fit.best)[v]
        p = band.fit.design_points_px()[v]
        true = Pose(np.array(entry["R_cam_holder"]), np.array(entry["t_cam_holder_mm"])).dof
        # sign: an error of +o mm is the design point o mm outside the true design edge
        e = -_residuals(true, X, p, n, K) / sd
        J = _jacobian(band.dof, X, n, K) / sd[:, None]
        lean_all = view_lean(em.edge_views(rotation_from_euler_deg(*band.dof[:3]), band.dof[3:],
                                           K, holder), bp.edge, bp.frac)
        lean = lean_all[v]
        u = bp.px_per_mm[v] / sd                    # a 1 mm outward shift, whitened
        # offset (mm outwards) and depth (mm below the face: it images d tan(theta) outwards)
        patterns = np.column_stack([u, lean * u])
        r = energies(e, J, bp.edge[v], patterns)
        coefs.append(np.linalg.lstsq(patterns, e, rcond=None)[0])
        rows.append(r)
        valid = np.isfinite(band.residuals_px)
        unit = [(design_pose(band.fit, band.fit.best.moved(0.1 * f, bp.px_per_mm), K, band.dof,
                             valid) - band.dof) / 0.1 for f in (1.0, lean_all)]
        err = pose_errors(np.array(entry["R_cam_holder"]), np.array(entry["t_cam_holder_mm"]),
                          m.pose.R, m.pose.t_mm).dof[0]
        kept.append((band.cov_parts, band.dof, unit, err))
        print(f"{i:3d} {'accepted' if m.ok else 'refused '} visible/expected "
              f"{r['visible'] / r['exp_visible']:.2f}  absorbed/expected "
              f"{r['absorbed'] / r['exp_absorbed']:.1f}"
              f"  minus offset {r['absorbed_minus_1'] / r['exp_absorbed_minus_1']:.1f}"
              f"  minus offset+depth {r['absorbed_minus_2'] / r['exp_absorbed_minus_2']:.1f}"
              f"  (offset, depth) = ({coefs[-1][0]:+.3f}, {coefs[-1][1]:+.3f}) mm", flush=True)
    if not rows:
        return 1
    med = {k: float(np.median([r[k] / r["exp_" + k] for r in rows]))
           for k in ("visible", "absorbed", "absorbed_minus_1", "absorbed_minus_2")}
    c = np.array(coefs)
    print(f"\n{a.set.name}: {len(rows)} images; median energy / expected: visible "
          f"{med['visible']:.2f}, absorbed {med['absorbed']:.1f}, without the offset "
          f"{med['absorbed_minus_1']:.1f}, without offset and depth {med['absorbed_minus_2']:.1f}")
    print(f"  (offset, depth) mm: mean {c.mean(0).round(3).tolist()}, std "
          f"{c.std(0, ddof=1).round(3).tolist()}, second moment "
          f"{((c.T @ c) / len(c)).round(4).tolist()}")
    M = (c.T @ c) / len(c)
    val, vec = np.linalg.eigh(M)
    tol = QualityLimits().tolerance
    for name in ("as it is", "(offset, depth) floor"):
        d2, z, within = [], [], 0
        for parts, dof, (d_off, d_dep), err in kept:
            parts = dict(parts)
            if name != "as it is":
                parts.pop("model floor", None)
                parts["offset-depth floor"] = sum(
                    np.outer(v, v) for v in (np.sqrt(max(lam, 0.0)) * (q[0] * d_off + q[1] * d_dep)
                                             for lam, q in zip(val, vec.T)))
            b = budget_from_dof_cov(parts, dof, tol=tol)
            d2.append(float(err @ np.linalg.solve(b.dof_cov, err)))
            z.append(np.abs(err) / b.std_dof)
            within += b.exceeds(tol) == ""
        print(f"  budget {name}: median Mahalanobis^2 {np.median(d2):.1f}, median |e|/std "
              f"{np.round(np.median(z, axis=0), 2).tolist()}, within the tolerance {within} of "
              f"{len(kept)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
