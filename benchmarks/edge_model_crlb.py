"""How well the edge radius and the depth are told apart with the 20-corner contour: the Fisher
information / CRLB of (pose, r) at the nominal pose and over the real-image working range
(docs/notes/edge_model.md).

    PYTHONPATH=src python benchmarks/edge_model_crlb.py [--poses 100] [--seed 3]

Prints, per radius and corner noise sigma: the bound on the std of Z with r free (and with the
weak prior on r) and with r known, the correlation of r and Z, the bound on r, and the std of
Z with one radius per edge direction; then the same over random poses of the working range
(RMS of the per-pose bounds, median |correlation|).
"""

from __future__ import annotations

import argparse

import numpy as np

from cutterpose.geometry.camera import default_camera
from cutterpose.geometry.holder import default_holder
from cutterpose.geometry.pose import Pose
from cutterpose.render.analytic import random_pose
from cutterpose.solvers.edge_radius import RadiusPrior, crlb_pose_radius

RADII = (0.5, 1.0, 2.0, 3.0, 5.0)
SIGMAS = (0.05, 0.1, 0.3, 1.0)


def row(pose, cam, holder, r, sigma):
    c = crlb_pose_radius(pose, cam, holder, r, sigma)
    cp = crlb_pose_radius(pose, cam, holder, r, sigma, prior=RadiusPrior())
    return (c["std_free"][5], cp["std_free"][5], c["std_known"][5], c["corr_r"][5],
            c["std_free"][6], c["std_per_family"][5])


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--poses", type=int, default=100)
    ap.add_argument("--seed", type=int, default=3)
    a = ap.parse_args()
    cam, holder = default_camera("table1"), default_holder()
    print("nominal pose; std of Z [mm] (CRLB), corner noise sigma px per coordinate")
    print("  r mm  sigma | Z r-free  Z r-free+prior  Z r-known  corr(r,Z)  std r  Z 2 radii")
    for r in RADII:
        for s in SIGMAS:
            zf, zp, zk, cr, sr, z2 = row(Pose.nominal(), cam, holder, r, s)
            print(f"  {r:4.1f} {s:6.2f} | {zf:8.3f} {zp:14.3f} {zk:10.3f} {cr:10.3f} "
                  f"{sr:6.3f} {z2:10.3f}")
    rng = np.random.default_rng(a.seed)
    poses = [random_pose(rng) for _ in range(a.poses)]
    print(f"\nworking range (+-10 deg, +-20 mm), {a.poses} poses, sigma = 0.1 px: RMS of the "
          "bounds, median and max |corr|")
    print("  r mm | Z r-free  Z r-free+prior  Z r-known  med|corr|  max|corr|  std r")
    for r in RADII:
        rows = np.array([row(p, cam, holder, r, 0.1) for p in poses])
        rms = np.sqrt(np.mean(rows ** 2, axis=0))
        print(f"  {r:4.1f} | {rms[0]:8.3f} {rms[1]:14.3f} {rms[2]:10.3f} "
              f"{np.median(np.abs(rows[:, 3])):10.3f} {np.max(np.abs(rows[:, 3])):10.3f} "
              f"{rms[4]:6.3f}")


if __name__ == "__main__":
    main()
