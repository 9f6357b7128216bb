"""Monte Carlo of ``dm+b``'s noise budget on the holder's geometry: design-edge points with
independent errors, a part shared per edge and outliers; the pose fitted each time, and the
predicted std over the fitted poses' observed std for ``edge_noise_cov`` and two alternatives
(docs/notes/edge_band.md, "Errors one edge shares").

* ``edges``: :func:`cutterpose.solvers.edge_band.edge_noise_cov` (the budget);
* ``independent``: ``chi^2 (J^T W J)^-1``, every segment its own observation;
* ``m-estimator``: the soft-L1 M-estimator's sandwich, ``A = J^T Psi' J`` (``psi' = w^3``),
  the variance components taken from ``psi = w z``.

Usage: python benchmarks/band_noise_sim.py [--fits 200]
"""

from __future__ import annotations

import argparse

import numpy as np

from cutterpose.geometry.camera import default_camera
from cutterpose.geometry.holder import default_holder
from cutterpose.geometry.pose import rotation_from_euler_deg
from cutterpose.solvers.edge_band import edge_noise_cov, fit_pose_design_points, variance_components


def segments(dof, K, per_edge=4):
    """Segment centres on the design edges, their projections and outward image normals."""
    h = default_holder()
    c = np.asarray(h.corners_mm, float)
    nxt = np.roll(c, -1, axis=0)
    f = (np.arange(per_edge) + 0.5) / per_edge
    P = (c[:, None, :] + f[None, :, None] * (nxt - c)[:, None, :]).reshape(-1, 2)
    edge = np.repeat(np.arange(len(c)), per_edge)
    X = np.column_stack([P, np.zeros(len(P))])
    R = rotation_from_euler_deg(*dof[:3])

    def proj(Q):
        Xc = Q @ R.T + dof[3:]
        return (Xc[:, :2] / Xc[:, 2:]) @ K[:2, :2].T + K[:2, 2]

    q = proj(X)
    n = proj(X + np.column_stack([h.edge_normals[edge], np.zeros(len(P))])) - q
    return X, q, n / np.linalg.norm(n, axis=1, keepdims=True), edge


def m_estimator(J, z, w, edge):
    labels, idx = np.unique(edge, return_inverse=True)
    E = len(labels)
    s_w2, s_u2 = variance_components(w * z, edge)     # of psi = w z
    g = np.zeros((E, 6))
    np.add.at(g, idx, J)
    Ai = np.linalg.inv(J.T @ (w[:, None] ** 3 * J))
    return Ai @ (max(s_w2, 1 - s_u2) * J.T @ J + s_u2 * g.T @ g) @ Ai


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--fits", type=int, default=200)
    a = ap.parse_args()
    rng = np.random.default_rng(11)
    K = default_camera("table1").K
    dof0 = np.array([4.0, -6.0, 2.0, 10.0, -5.0, 600.0])
    X, q, n, edge = segments(dof0, K)
    sd = np.full(len(X), 0.15)
    print("independent 0.15 px per segment; predicted / observed std (alpha, beta, Z)")
    for shared, outliers in [(0.0, 0.0), (0.15, 0.0), (0.3, 0.0), (0.3, 0.1), (0.0, 0.1)]:
        poses, pred = [], {"edges": [], "independent": [], "m-estimator": []}
        for _ in range(a.fits):
            err = rng.normal(0, 0.15, len(X)) + rng.normal(0, shared, 20)[edge]
            o = rng.random(len(X)) < outliers
            err[o] += rng.choice([-1, 1], o.sum()) * rng.uniform(1, 3, o.sum())
            dof, J, r, w, s = fit_pose_design_points(q + err[:, None] * n, n, X, K, dof0, sd)
            poses.append(dof)
            z = r / sd
            pred["edges"].append(edge_noise_cov(J, z, w, edge))
            pred["independent"].append(max(s, 1.0) ** 2 * np.linalg.inv(J.T @ (w[:, None] * J)))
            pred["m-estimator"].append(m_estimator(J, z, w, edge))
        obs = np.std(np.array(poses), axis=0, ddof=1)
        cols = [0, 1, 5]
        print(f"  shared {shared:.2f} px per edge, outliers {100 * outliers:.0f} %: " + "; ".join(
            f"{k} " + " ".join(f"{v:.2f}" for v in (
                np.median(np.sqrt(np.diagonal(np.array(c), axis1=1, axis2=2)), axis=0)
                / obs)[cols]) for k, c in pred.items()))


if __name__ == "__main__":
    main()
