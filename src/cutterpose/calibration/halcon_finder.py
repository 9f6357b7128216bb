"""Detection of HALCON's hexagonal calibration plates by their finder patterns.

Pipeline (one grey image, a :class:`~cutterpose.calibration.halcon_plate.HexagonalPlate`):

1. marks: adaptive threshold (``cv2.adaptiveThreshold``, robust to uneven light) of the marks'
   polarity, outer contours (``cv2.findContours``), ellipse fit and a roundness test per
   contour (``cv2.fitEllipse``); a mark *has a hole* when its centre is darker than its rim
   by 25 % of the mark's contrast (measured on the grey levels, so blur that fills the hole in
   the binary image does not hide it);
2. sub-pixel centres: ellipse fit on sub-pixel grey-level crossings of the mark's outer edge
   (the hole's edge is left out);
3. finder patterns: around every mark with holed marks near it, the rings ``+-a, +-b,
   +-(b - a)`` of pairs of lattice vectors to its nearest marks are candidate hexagons (the six
   nearest marks are not the ring under strong tilt); a ring's hole flags (centre first, then
   anticlockwise on the page) are compared with each finder pattern of the description under
   the six rotations; a match whose seven points a homography of the plate's hexagon fits
   gives a plate-to-image homography;
4. hexagonal indexing: from the finder the match grows ring by ring over the plate's
   neighbour graph: each unmatched mark next to matched ones is predicted by a homography of
   the matched marks around it (local, so lens distortion does not accumulate) and takes the
   nearest detected mark of about its neighbours' size within a third of the local spacing;
   marks that a robust local homography of their neighbours does not place (occluded,
   fused with clutter) are dropped, and the holes seen must be the plate's (F1 >= 0.7: the
   lattice fits itself under shifts and shears, only the holes tell the indexing).
   Every mark found carries its plate index (``ids``), so partial views of the plate are
   usable.

Why by hand: OpenCV's ``findCirclesGrid`` knows rectangular and OpenCV's own asymmetric grids,
needs the whole grid in view, and has no notion of holes or finder patterns; no library in
reach decodes HALCON's hexagonal plates. Mark extraction, ellipse fits and homographies are
OpenCV's; the matching of finder patterns and the lattice indexing are written here.

References:
    MVTec HALCON reference manual, ``create_caltab`` (finder patterns) and
    ``find_calib_object``. R. Hartley, A. Zisserman, "Multiple View Geometry", 2nd ed., 4.1
    (homography from point correspondences).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .targets import TargetDetection

__all__ = ["detect_hexagonal", "find_marks"]


# ------------------------------------------------------------------------------------------
# marks
@dataclass
class _Marks:
    centre: np.ndarray  # (n, 2) rough centres
    axes: np.ndarray  # (n, 2) full ellipse axes
    angle: np.ndarray  # (n,) degrees
    hole: np.ndarray  # (n,) bool


def find_marks(gray: np.ndarray, light_marks: bool, min_area_px: float = 12.0) -> _Marks:
    """Round blobs of the marks' polarity, with a flag for a central hole."""
    import cv2

    g = gray if light_marks else 255 - gray
    h, w = g.shape
    block = max(15, (min(h, w) // 8) | 1)
    # a light smoothing first: sensor noise on flat ground would otherwise leave thousands of
    # speckles (contour tracing then dominates the time); marks are several pixels wide
    smooth = cv2.GaussianBlur(g, (5, 5), 1.0)
    binary = cv2.adaptiveThreshold(smooth, 255, cv2.ADAPTIVE_THRESH_MEAN_C, cv2.THRESH_BINARY,
                                   block, -5)
    contours, hier = cv2.findContours(binary, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_NONE)
    out = []
    if hier is None:
        return _Marks(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0), np.zeros(0, bool))
    hier = hier[0]
    for k, c in enumerate(contours):
        if hier[k, 3] != -1 or len(c) < 8:
            continue  # holes are handled with their parent
        area = cv2.contourArea(c)
        x, y, bw, bh = cv2.boundingRect(c)
        if area < min_area_px or x <= 0 or y <= 0 or x + bw >= w or y + bh >= h:
            continue  # too small, or cut by the image border
        (cu, cv_), (a1, a2), ang = cv2.fitEllipse(c)
        ell = np.pi / 4 * a1 * a2
        if not (0.8 < area / max(ell, 1e-9) < 1.2) or min(a1, a2) < 0.25 * max(a1, a2):
            continue
        out.append((cu, cv_, a1, a2, ang, *_hole_levels(g, (cu, cv_), (a1, a2), ang)))
    if not out:
        return _Marks(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0), np.zeros(0, bool))
    a = np.array(out, float)
    return _Marks(a[:, :2], a[:, 2:4], a[:, 4], _holes(a[:, :2], a[:, 5:]))


def _pct(a: np.ndarray, q: float) -> float:
    """The ``q``-th percentile of a small array, nearest rank (``np.percentile`` costs more
    than the arithmetic for a few hundred values, once per mark)."""
    a = np.sort(a, axis=None)
    return float(a[int(round(q / 100.0 * (len(a) - 1)))])


def _ellipse_radius(shape, origin, centre, axes, angle):
    """Normalised elliptic radius (1 on the ellipse) of every pixel of a window at ``origin``."""
    vv, uu = np.mgrid[origin[1]:origin[1] + shape[0], origin[0]:origin[0] + shape[1]]
    t = np.radians(angle)
    du, dv = uu - centre[0], vv - centre[1]
    p = (du * np.cos(t) + dv * np.sin(t)) / (0.5 * axes[0])
    q = (-du * np.sin(t) + dv * np.cos(t)) / (0.5 * axes[1])
    return np.hypot(p, q)


def _hole_levels(g: np.ndarray, centre, axes, angle):
    """(rim, centre, background) grey levels of one mark: the rim's brightest tenth, the
    centre's darkest tenth, the median around the mark (NaN when out of the image)."""
    h, w = g.shape
    half = int(np.ceil(0.5 * max(axes) * 1.6)) + 1
    u0, v0 = max(int(round(centre[0])) - half, 0), max(int(round(centre[1])) - half, 0)
    roi = g[v0:min(v0 + 2 * half + 1, h), u0:min(u0 + 2 * half + 1, w)].astype(float)
    rho = _ellipse_radius(roi.shape, (u0, v0), centre, axes, angle)
    centre_v, rim, bg = roi[rho < 0.3], roi[(rho > 0.55) & (rho < 0.9)], roi[rho > 1.25]
    if centre_v.size == 0 or rim.size == 0 or bg.size == 0:
        return np.nan, np.nan, np.nan
    return _pct(rim, 90), _pct(centre_v, 10), _pct(bg, 50)


def _holes(centres: np.ndarray, levels: np.ndarray, depth: float = 0.25) -> np.ndarray:
    """Which marks carry a dot-shaped hole, from the grey levels (not the binary image, in
    which blur fills small holes). A hole darkens the mark's centre below its rim; under
    strong blur the hole no longer shows as a dip but still dims the whole mark, so a mark
    whose centre is darker than the typical centre of the marks around it (the median of its
    18 nearest: plain marks are the majority everywhere) by ``depth`` of its contrast counts
    too."""
    from scipy.spatial import cKDTree

    rim, ctr, bg = levels.T
    contrast = rim - bg
    dip = (contrast > 0) & (rim - ctr > depth * contrast)
    if len(centres) >= 7:
        k = min(19, len(centres))
        _, idx = cKDTree(centres).query(centres, k=k)
        typical = np.nanmedian(ctr[idx[:, 1:]], axis=1)
        dip |= (contrast > 0) & (typical - ctr > depth * contrast)
    return dip


def _refine_centre(g: np.ndarray, centre, axes, angle) -> np.ndarray | None:
    """Ellipse fit on sub-pixel crossings of the mark's outer edge (marks bright in ``g``)."""
    import cv2

    h, w = g.shape
    half = int(np.ceil(0.5 * max(axes) * 1.4)) + 2
    u0, v0 = int(round(centre[0])) - half, int(round(centre[1])) - half
    u1, v1 = u0 + 2 * half + 1, v0 + 2 * half + 1
    if u0 < 0 or v0 < 0 or u1 > w or v1 > h:
        return None
    roi = g[v0:v1, u0:u1].astype(float)
    # a wide band around the mark's edge: under blur the mid-level contour lies well inside
    # the thresholded outline; the hole's edge is told apart by its direction (below)
    rho = _ellipse_radius(roi.shape, (u0, v0), centre, axes, angle)
    band = (rho > 0.3) & (rho < 1.25)
    inner, outer = roi[rho < 0.72], roi[(rho > 1.3) & (rho < 1.6)]
    if inner.size == 0 or outer.size == 0:
        return None
    thr = 0.5 * (_pct(inner, 90) + _pct(outer, 10))
    pts = []
    for a0, a1, m0, m1, horiz in (
            (roi[:, :-1], roi[:, 1:], band[:, :-1], band[:, 1:], True),
            (roi[:-1, :], roi[1:, :], band[:-1, :], band[1:, :], False)):
        m = ((a0 - thr) * (a1 - thr) < 0) & m0 & m1
        v, u = np.nonzero(m)
        f = (thr - a0[m]) / (a1[m] - a0[m])
        p = (np.stack([u + f, v.astype(float)], 1) if horiz
             else np.stack([u.astype(float), v + f], 1))
        # keep the mark's own outer edge: the grey level falls away from its centre (the
        # hole's edge and a close neighbour's blurred edge rise outwards and are left out)
        out = p[:, 0 if horiz else 1] + (u0 if horiz else v0) - centre[0 if horiz else 1]
        pts.append(p[(a1[m] - a0[m]) * out < 0])
    e = np.concatenate(pts)
    if len(e) < 10:
        return None
    mean = e.mean(axis=0)
    (eu, ev), _, _ = cv2.fitEllipse((e - mean).astype(np.float32))
    return np.array([eu + mean[0] + u0, ev + mean[1] + v0])


# ------------------------------------------------------------------------------------------
# finder patterns and indexing
def _ring_order(centre, pts) -> np.ndarray:
    """Order of 6 points around ``centre``, anticlockwise on the page starting nearest to the
    right-hand direction (the plate's neighbour order)."""
    d = pts - centre
    ang = np.degrees(np.arctan2(-d[:, 1], d[:, 0])) % 360.0
    return np.argsort(ang)


def _rings(marks: _Marks, c: int, tree, k: int = 10):
    """Candidate neighbour rings of mark ``c``: for two lattice vectors ``a``, ``b`` among its
    nearest marks, the six marks at ``+-a, +-b, +-(b - a)`` (an affine image of a hexagon).
    Under strong tilt the six nearest marks are not always the ring, so every such pair is
    tried; the hole pattern and the growth decide."""
    _, idx = tree.query(marks.centre[c], k=min(k + 1, len(marks.centre)))
    nb = idx[1:]
    v = marks.centre[nb] - marks.centre[c]
    out = set()
    for i in range(min(6, len(nb))):
        for j in range(i + 1, min(8, len(nb))):
            a, b = v[i], v[j]
            cross = abs(a[0] * b[1] - a[1] * b[0])
            if cross < 0.3 * np.linalg.norm(a) * np.linalg.norm(b):
                continue  # (nearly) collinear
            want = marks.centre[c] + np.array([a, b, b - a, -a, -b, a - b])
            d, j6 = tree.query(want)
            if np.all(d < 0.2 * min(np.linalg.norm(a), np.linalg.norm(b))):
                ring = j6[_ring_order(marks.centre[c], marks.centre[j6])]
                if len(set(ring.tolist())) == 6 and c not in ring:
                    out.add(tuple(ring.tolist()))
    return [np.array(r) for r in out]


def _seeds(marks: _Marks, plate):
    """Image hexagons that match one of the plate's finder patterns: (plate ids, blob ids)."""
    from scipy.spatial import cKDTree

    n = len(marks.centre)
    if n < 7:
        return []
    tree = cKDTree(marks.centre)
    _, near = tree.query(marks.centre, k=min(11, n))
    # a finder's centre has at least three holed marks among its nearest ten
    cands = np.nonzero(marks.hole[near].sum(axis=1) >= 3)[0]
    seeds = []
    for c in cands:
        for ring in _rings(marks, c, tree):
            flags = np.concatenate([[marks.hole[c]], marks.hole[ring]])
            if flags.sum() not in (4, 6):
                continue
            for pc, pring, pflags in plate.finders:
                if flags[0] != pflags[0]:
                    continue
                for k in range(6):
                    if np.array_equal(np.roll(flags[1:], -k), pflags[1:]):
                        # plate ring j <-> image ring (j + k) % 6
                        img = np.concatenate([[c], np.roll(ring, -k)])
                        pl = np.concatenate([[pc], pring])
                        if _is_hexagon(plate.marks_mm[pl], marks.centre[img]):
                            seeds.append((pl, img))
    return seeds


def _is_hexagon(plate_xy, img_xy, tol: float = 0.12) -> bool:
    """The seven image points are a projected mark hexagon: a homography maps the plate's
    hexagon onto them within ``tol`` of the ring's mean radius (clutter that happens to
    show the hole flags of a finder pattern does not)."""
    import cv2

    H, _ = cv2.findHomography(plate_xy.astype(np.float64), img_xy.astype(np.float64), 0)
    if H is None:
        return False
    ph = np.c_[plate_xy, np.ones(len(plate_xy))] @ H.T
    err = np.linalg.norm(ph[:, :2] / ph[:, 2:] - img_xy, axis=1)
    radius = np.mean(np.linalg.norm(img_xy[1:] - img_xy[0], axis=1))
    return bool(np.all(np.isfinite(err)) and err.max() < tol * radius)


def _local_prediction(src_mm, dst_px, at_mm, spacing_mm: float, method):
    """Image positions of the plate points ``at_mm`` by the homography ``src_mm -> dst_px``
    (``cv2.findHomography`` with ``method``: 0 or ``cv2.RANSAC`` at 1 px), and the local image
    length of one spacing along the plate's x at each; None when no homography is found."""
    import cv2

    H, _ = cv2.findHomography(np.asarray(src_mm, np.float64), np.asarray(dst_px, np.float64),
                              method, 1.0)
    if H is None:
        return None
    q = np.concatenate([at_mm, at_mm + [spacing_mm, 0.0]])
    ph = np.c_[q, np.ones(len(q))] @ H.T
    pred = ph[:, :2] / ph[:, 2:]
    n = len(at_mm)
    return pred[:n], np.linalg.norm(pred[n:] - pred[:n], axis=1)


def _grow(marks: _Marks, plate, seed_plate, seed_img, tol: float = 0.33):
    """Match plate marks to detected marks outward from a seed (module docstring, step 4)."""
    from scipy.spatial import cKDTree

    tree = cKDTree(marks.centre)
    xy = plate.marks_mm
    s = plate.spacing_mm
    match = dict(zip(seed_plate.tolist(), seed_img.tolist()))
    used = set(match.values())
    for _ in range(4 * max(plate.description.rows or 30, plate.description.cols or 30)):
        known = np.array(sorted(match))
        nb = plate.neighbours[known].ravel()
        frontier = np.setdiff1d(nb[nb >= 0], known)
        added = 0
        # one local homography per cell of 3 x 3 spacings: the matched marks nearest to the
        # cell's frontier marks predict them (local, so lens distortion does not accumulate)
        cell = np.floor(xy[frontier] / (3.0 * s)).astype(int)
        _, group = np.unique(cell, axis=0, return_inverse=True)
        for g in range(group.max() + 1 if len(frontier) else 0):
            ms = frontier[group.ravel() == g]
            d = np.linalg.norm(xy[known] - xy[ms].mean(axis=0), axis=1)
            near = known[np.argsort(d)[:12]]
            if len(near) < 4:
                continue
            got = _local_prediction(xy[near], marks.centre[[match[k] for k in near]], xy[ms],
                                    s, 0)
            if got is None:
                continue
            pred, step = got
            dd, j = tree.query(pred)
            # a mark has about the size and shape of its neighbours (a mark cut by an occluder,
            # or clutter, does not)
            ax = marks.axes[[match[k] for k in near]]
            size = np.median(ax.mean(axis=1))
            shape = np.median(ax.min(axis=1) / ax.max(axis=1))
            for m, dm, jm, st in zip(ms, dd, j, step):
                a = marks.axes[jm]
                if not (0.8 < a.mean() / size < 1.25
                        and abs(a.min() / a.max() - shape) < 0.12):
                    continue
                if np.isfinite(dm) and dm < tol * st and int(jm) not in used:
                    match[int(m)] = int(jm)
                    used.add(int(jm))
                    added += 1
        if added == 0:
            break
    ids = np.array(sorted(match))
    return ids, np.array([match[k] for k in ids])


def _prune(img: np.ndarray, plate, ids, blobs, tol: float = 0.06):
    """Drop matched marks (plate ``ids``, image points ``img``, detected ``blobs``) that a
    robust local homography of the matched marks around them
    (``cv2.findHomography`` with RANSAC, one per cell of 3 x 3 spacings) does not place within
    ``tol`` of the local spacing: a mark partly occluded or fused with clutter."""
    import cv2

    if len(ids) < 8:
        return ids, blobs
    xy, s = plate.marks_mm[ids], plate.spacing_mm
    keep = np.ones(len(ids), bool)
    cell = np.floor(xy / (3.0 * s)).astype(int)
    _, group = np.unique(cell, axis=0, return_inverse=True)
    for g in range(group.max() + 1):
        sel = np.nonzero(group.ravel() == g)[0]
        near = np.argsort(np.linalg.norm(xy - xy[sel].mean(axis=0), axis=1))[:max(16, len(sel))]
        if len(near) < 8:
            continue
        got = _local_prediction(xy[near], img[near], xy[sel], s, cv2.RANSAC)
        if got is not None:
            keep[sel] &= np.linalg.norm(got[0] - img[sel], axis=1) < tol * got[1]
    return ids[keep], blobs[keep]


def detect_hexagonal(gray, plate) -> TargetDetection:
    """Find a hexagonal plate's marks (module docstring). Never raises on image content: a
    plate not found gives a falsy :class:`~cutterpose.calibration.targets.TargetDetection`
    whose ``reason`` says why; ``info["finders"]`` counts the finder patterns seen whole."""
    import cv2

    g = np.asarray(gray)
    if g.ndim == 3:
        g = cv2.cvtColor(g, cv2.COLOR_BGR2GRAY)
    if g.ndim != 2 or g.size == 0:
        return TargetDetection.missing(f"not a grey image (shape {g.shape})")
    if g.dtype != np.uint8:
        g = np.clip(g, 0, 255).astype(np.uint8)
    light = plate.polarity == "light_on_dark"
    marks = find_marks(g, light)
    if len(marks.centre) < 7:
        return TargetDetection.missing(f"only {len(marks.centre)} round marks found")
    seeds = _seeds(marks, plate)
    if not seeds:
        return TargetDetection.missing(f"no finder pattern seen whole ({len(marks.centre)} marks, "
                                   f"{int(marks.hole.sum())} with a hole)")
    best = None
    for sp, si in seeds[:12]:
        if best is not None and (si[0] in best[2] and best[3] >= 0.9):
            continue  # a convincing match already explains this finder's centre
        ids, blobs = _grow(marks, plate, sp, si)
        ids, blobs = _prune(marks.centre[blobs], plate, ids, blobs)
        # holes where the plate has them and nowhere else: a wrong indexing (the hexagonal
        # lattice fits itself under many shifts and shears) puts the holes elsewhere
        holed, seen = plate.hole_radius_mm[ids] > 0, marks.hole[blobs]
        both = float(np.sum(holed & seen))
        f1 = 2 * both / max(holed.sum() + seen.sum(), 1) if holed.sum() >= 4 else 0.0
        if best is None or len(ids) * f1 > best[0]:
            best = (len(ids) * f1, ids, blobs, f1)
    _, ids, blobs, f1 = best
    if f1 < 0.7 or len(ids) < 12:
        return TargetDetection.missing(
            f"finder pattern matched but the plate does not follow from it ({len(ids)} marks, "
            f"holes agree F1 = {f1:.2f})")
    gm = g if light else 255 - g
    pts = [_refine_centre(gm, marks.centre[b], marks.axes[b], marks.angle[b]) for b in blobs]
    ok = np.array([p is not None for p in pts])
    if ok.sum() < 7:
        return TargetDetection.missing("too few marks with a measurable edge")
    # once more on the sub-pixel centres: an edge disturbed by clutter moves its centre
    pts = np.array([p for p in pts if p is not None])
    ids, blobs = ids[ok], blobs[ok]
    keep = np.isin(ids, _prune(pts, plate, ids, blobs)[0])
    finders = len({f[0] for f in plate.finders} & set(ids[keep].tolist()))
    return TargetDetection(pts[keep], ids[keep], axes_px=marks.axes[blobs[keep]],
                           info={"finders": finders})
