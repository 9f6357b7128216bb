"""Corners: intersections of consecutive characteristic lines (paper section 2.1, step 6)
and the consistency checks that refuse a wrong set of lines.

Convention:
    Lines and corners in ideal pixels; corners returned also in observed pixels.
"""

from __future__ import annotations

import numpy as np

from ..errors import FeatureError
from ..geometry.camera import Camera
from .lines import intersect_consecutive
from .params import where_px


def corners_from_lines(lines, camera: Camera):
    """Corners of consecutive lines, ideal and observed pixels."""
    corners_ideal = intersect_consecutive(lines)
    corners_px = camera.distort_px(corners_ideal)
    if not np.all(np.isfinite(corners_px)):
        raise FeatureError("consecutive characteristic lines do not intersect")
    return corners_ideal, corners_px


def check_corners_on_contour(corners_ideal, corners_px, contour_ideal, params):
    """A corner must lie near the contour: one the contour detours around is occluded (or
    broken off), and the lines meeting there may not be the holder's."""
    d2 = ((corners_ideal[:, None, :] - contour_ideal[None, ::2, :]) ** 2).sum(axis=2)
    gap = np.sqrt(d2.min(axis=1))
    bad = np.nonzero(gap > params.max_corner_gap_px)[0]
    if len(bad):
        where = ", ".join(f"{where_px(corners_px[k])} ({gap[k]:.0f} px)" for k in bad)
        raise FeatureError(f"{len(bad)} corner(s) not on the contour, occluded or damaged: "
                           f"at {where} from the nearest contour point "
                           f"(> {params.max_corner_gap_px:g} px)")


def check_families(lines, params, segs, camera):
    """The holder's edges alternate between its X and Y directions; within the working range
    each family stays nearly parallel in the image (vanishing points far away). A line off its
    family's direction is not a holder edge (an occluder's or a stain's outline)."""
    ang = np.arctan2(lines[:, 1], lines[:, 0])
    for fam in (0, 1):
        idx = np.arange(fam, len(lines), 2)
        z = np.exp(2j * ang[idx])
        mean = np.angle(z.sum()) / 2
        dev = np.degrees(np.abs(np.angle(np.exp(2j * (ang[idx] - mean))) / 2))
        k = int(np.argmax(dev))
        if dev[k] > params.max_family_spread_deg:
            i = int(idx[k])
            p = camera.distort_px(segs[i].points_ideal_px.mean(axis=0))
            raise FeatureError(
                f"segment {i} near {where_px(p)} px is {dev[k]:.0f} deg off the direction of its "
                f"family of parallel edges (> {params.max_family_spread_deg:g}): an occluded or "
                "damaged edge, or a pose far outside the working range")


def check_corner_angles(lines, params, segs):
    n = lines[:, :2]
    cosang = np.abs((n * np.roll(n, -1, axis=0)).sum(axis=1))
    bad = np.nonzero(cosang > np.cos(np.radians(params.min_corner_angle_deg)))[0]
    if len(bad):
        k = int(bad[0])
        raise FeatureError(
            f"characteristic segments {k} and {(k + 1) % len(lines)} are nearly parallel "
            f"(they meet at {np.degrees(np.arccos(min(1.0, cosang[k]))):.0f} deg): a segment is "
            f"missing near {where_px(segs[k].points_ideal_px[-1])} ideal px")
