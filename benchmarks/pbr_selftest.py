"""Self-test of the pbr renderer (docs/notes/render_pbr.md): where is the intensity step of a
``sharp`` image relative to the projected design edge?

Renders noise-free, unblurred ``sharp`` images (clean face: grime 0, so that the texture does
not move the step) at random poses of the real-image protocol with the Table 1 camera and
prints, per image, the step offset of each of the 20 edges (area estimate,
``pbr.edge_step_offsets``) and the totals.

    PYTHONPATH=src python benchmarks/pbr_selftest.py --count 3 --spp 32
"""

import argparse

import numpy as np

from cutterpose.geometry.camera import default_camera
from cutterpose.geometry.holder import default_holder
from cutterpose.render import pbr
from cutterpose.render.analytic import random_pose


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--count", type=int, default=3)
    ap.add_argument("--spp", type=int, default=32)
    ap.add_argument("--grime", type=float, default=0.0)
    ap.add_argument("--seed", type=int, default=1000)
    a = ap.parse_args()
    cam, hol = default_camera("table1"), default_holder()
    preset = pbr.field_preset("sharp").with_(grime=a.grime)
    offs = []
    for i in range(a.count):
        pose = random_pose(np.random.default_rng(a.seed + i))
        r = pbr.render_field(pose, cam, hol, preset, seed=a.seed + i, spp=a.spp, sensor=False)
        o = pbr.edge_step_offsets(r.value, pose, cam, hol)
        offs.append(o)
        print(f"image {i} ({r.variant}, {r.timings_s['total']:.0f} s): "
              f"offsets {np.array2string(o, precision=3)}")
    o = np.array(offs)
    print(f"{np.isfinite(o).sum()} edges: mean {np.nanmean(o):+.4f} px, rms "
          f"{np.sqrt(np.nanmean(o ** 2)):.4f} px, max |offset| {np.nanmax(np.abs(o)):.3f} px")


if __name__ == "__main__":
    main()
