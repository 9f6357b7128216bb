"""The point order of a symmetric target, chosen per station from the robot's motion.

A plain grid (no orientation mark) looks the same turned by 180 degrees, so a detector returns
its points in one of two orders, and which one can change from image to image. A station read in
the wrong order gives ``B_i S`` instead of ``B_i`` (``S``: the target's symmetry, a rigid motion
of the target frame), and a hand-eye calibration that mixes the two is corrupted.

Resolution by the motion invariants of ``AX = XB`` (Chen 1991; Park & Martin 1994): for two
stations ``i, j`` the flange motion ``M_A = A_j^-1 A_i`` and the camera motion
``M_B = B_j B_i^-1`` are conjugate (``M_A = X M_B X^-1``), so whatever ``X`` is they share

* the rotation angle ``theta``, and
* the translation along the screw axis, ``d = t . n`` (the pitch times the angle).

Replacing ``B_i`` by ``B_i S`` changes both for every pair with a correctly ordered station. So:
for every reference station ``r`` (taken as ordered correctly) each other station gets the
order whose motion relative to ``r`` best matches the robot's (cost ``|dtheta| / 1 deg +
|dd| / 10 mm``); the reference whose labelling has the least total cost over *all* pairs wins.
The labels are then composed so that the most common order is the detector's own (the target
frame is that of the majority). No estimate of ``X`` is needed and every station is judged
against all others, so a few wrong robot poses do not flip the rest.

References:
    H. Chen, "A screw motion approach to uniqueness analysis of head-eye geometry", CVPR 1991.
    F. Park, B. Martin, IEEE Trans. Robotics and Automation 10(5), 1994 (the invariants).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from ..geometry.pose import Pose

__all__ = ["OrderChoice", "resolve_point_orders", "screw_invariants", "motion_mismatch"]

ANGLE_SCALE_DEG = 1.0
PITCH_SCALE_MM = 10.0


@dataclass
class OrderChoice:
    """Per station: the index of the chosen order (0: as detected, k: ``symmetries[k-1]``),
    and the margin (cost of the next best order minus the chosen one's, summed over the other
    stations; large = clear)."""

    labels: np.ndarray
    margins: np.ndarray
    names: list = field(default_factory=list)  #: what each label means ("as detected", ...)


def screw_invariants(R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation angle [deg] and translation along the rotation axis [mm] of motions (..., 3, 3),
    (..., 3)."""
    rv = Rotation.from_matrix(R.reshape(-1, 3, 3)).as_rotvec()
    th = np.linalg.norm(rv, axis=1)
    n = rv / np.maximum(th, 1e-12)[:, None]
    d = np.abs(np.einsum("ni,ni->n", n, t.reshape(-1, 3)))  # the axis' sign is arbitrary
    shape = R.shape[:-2]
    return np.degrees(th).reshape(shape), d.reshape(shape)


def _pair_mismatch(A: list[Pose], B: list[list[Pose]]):
    """``|dtheta|`` [deg] and ``|dd|`` [mm] of the motion i -> j between robot and camera with
    station i in order a, j in b: arrays (i, j, a, b)."""
    RA = np.stack([a.R for a in A])
    tA = np.stack([a.t_mm for a in A])
    RB = np.stack([[b.R for b in row] for row in B])          # (n, m, 3, 3)
    tB = np.stack([[b.t_mm for b in row] for row in B])       # (n, m, 3)
    # M_A = A_j^-1 A_i
    RMA = np.einsum("jkp,ikq->ijpq", RA, RA)
    tMA = np.einsum("jkp,ijk->ijp", RA, tA[:, None, :] - tA[None, :, :])
    thA, dA = screw_invariants(RMA, tMA)
    # M_B = B_j B_i^-1 = (R_j R_i^T, t_j - R_j R_i^T t_i)
    RMB = np.einsum("jbpk,iaqk->iajbpq", RB, RB)               # (n, m, n, m, 3, 3)
    tMB = tB[None, None, :, :, :] - np.einsum("iajbpq,iaq->iajbp", RMB, tB)
    thB, dB = screw_invariants(RMB, tMB)
    dth = np.abs(thB - thA[:, None, :, None]).transpose(0, 2, 1, 3)
    dd = np.abs(dB - dA[:, None, :, None]).transpose(0, 2, 1, 3)
    return dth, dd


def _pair_costs(A: list[Pose], B: list[list[Pose]]) -> np.ndarray:
    """cost[i, j, a, b]: mismatch of the motion i -> j with station i in order a, j in b."""
    dth, dd = _pair_mismatch(A, B)
    return dth / ANGLE_SCALE_DEG + dd / PITCH_SCALE_MM


def motion_mismatch(A: list[Pose], B: list[Pose]) -> tuple[np.ndarray, np.ndarray]:
    """Per station, the median over the other stations of how much the robot's and the
    camera's motion disagree: rotation angle [deg] and translation along the axis [mm].

    Independent of ``X``: a station whose robot pose or image is wrong stands out here before
    any calibration (and the medians bound what any hand-eye method can reach).
    """
    n = len(A)
    if n < 2:
        return np.zeros(n), np.zeros(n)
    dth, dd = _pair_mismatch(A, [[b] for b in B])
    off = ~np.eye(n, dtype=bool)
    th = np.array([np.median(dth[i, off[i], 0, 0]) for i in range(n)])
    d = np.array([np.median(dd[i, off[i], 0, 0]) for i in range(n)])
    return th, d


def resolve_point_orders(A: list[Pose], B: list[list[Pose]], symmetries: list[np.ndarray],
                         allowed: np.ndarray | None = None) -> OrderChoice:
    """Choose each station's point order (module doc).

    Parameters
    ----------
    A : n flange poses ``T_base_flange``.
    B : per station, the target pose ``T_cam_plate`` for each candidate order: ``B[i][0]`` as
        detected, ``B[i][k]`` with the points read through ``symmetries[k-1]``.
    symmetries : the target's point permutations (without the identity).
    allowed : (n, 1 + len(symmetries)) bool, the orders each station may have (its detection's
        own ambiguity; default all). Stations allowed only their own order (a detection whose
        marks fixed it) anchor the target frame: then no relabelling to the majority.

    Returns
    -------
    OrderChoice with labels in 0..len(symmetries).
    """
    n, m = len(A), len(B[0])
    allowed = np.ones((n, m), bool) if allowed is None else np.asarray(allowed, bool)
    fixed = ~allowed[:, 1:].any(axis=1)
    if m == 1 or n < 2 or fixed.all():
        return OrderChoice(np.zeros(n, int), np.full(n, np.inf))
    cost = _pair_costs(A, B)
    big = 1e9
    cost = cost + big * (~allowed)[:, None, :, None] + big * (~allowed)[None, :, None, :]
    best_total, best = np.inf, None
    for r in (np.flatnonzero(fixed) if fixed.any() else range(n)):
        lab = np.argmin(cost[r, :, 0, :], axis=1)
        lab[r] = 0
        total = cost[np.arange(n)[:, None], np.arange(n)[None, :], lab[:, None],
                     lab[None, :]].sum()
        if total < best_total:
            best_total, best = total, lab
    lab = best
    # margins: station i in each order against all the others as labelled
    per = np.take_along_axis(cost, np.broadcast_to(lab[None, :, None, None], (n, n, m, 1)),
                             axis=3)[..., 0]                     # per[i, j, a]
    per[np.arange(n), np.arange(n)] = 0.0
    per = per.sum(axis=1)                                        # (n, m)
    alt = np.where(allowed, per, np.inf)
    alt[np.arange(n), lab] = np.inf
    margins = alt.min(axis=1) - per[np.arange(n), lab]
    if not fixed.any():
        relabelled = _majority_gauge(lab, symmetries)
        if allowed[np.arange(n), relabelled].all():
            lab = relabelled
    return OrderChoice(lab, margins)


def _majority_gauge(lab: np.ndarray, symmetries: list[np.ndarray]) -> np.ndarray:
    """Relabel so the most common order (a tie: the first station's) is the detector's own:
    compose every station's order with the inverse of that one (the symmetries form a group; a
    composition outside the given list leaves the labels as they are)."""
    counts = np.bincount(lab, minlength=len(symmetries) + 1)
    g = int(np.argmax(counts))
    if counts[lab[0]] == counts[g]:
        g = int(lab[0])  # a tie: the first station keeps the detector's order
    if g == 0:
        return lab
    N = len(symmetries[0])
    perms = [np.arange(N)] + [np.asarray(s) for s in symmetries]
    inv = np.argsort(perms[g])
    out = lab.copy()
    for i, k in enumerate(lab):
        c = inv[perms[k]]
        hit = [q for q, p in enumerate(perms) if np.array_equal(p, c)]
        if not hit:
            return lab
        out[i] = hit[0]
    return out
