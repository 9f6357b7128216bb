"""Model-guided recovery of the 20 characteristic lines (beyond the paper's section 2.1).

When the paper's segmentation does not give 20 consistent segments (wear, an occluder, a bad
threshold), the holder's pocket outline is fitted to the thresholded contour by a homography of
the holder plane, refined by repeated nearest-edge matching; the 20 edges then go through the
same gradient refinement as the paper's lines (:mod:`cutterpose.image.edges`). An edge supported
along too little of its length is refused.

Convention:
    Ideal pixels and homogeneous lines as in :mod:`cutterpose.image.features`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import cv2
import numpy as np

from ..errors import FeatureError
from ..geometry.camera import Camera
from ..geometry.holder import Holder
from ..geometry.pose import Pose
from .edges import sample_profiles, smooth_rows
from .lines import MAD_TO_SIGMA, line_from, mad_scale, median_rows, tukey_weights
from .params import Segment, signed_area, where_px

if TYPE_CHECKING:
    from .params import FeatureParams


# ------------------------------------------------------------------------------------------
# model-guided fallback (beyond the paper)
def _homography_nominal(camera: Camera, holder: Holder) -> np.ndarray:
    """Homography holder plane (mm) -> ideal pixels at the nominal pose."""
    R, t = Pose.nominal().R, Pose.nominal().t_mm
    return camera.K @ np.column_stack([R[:, 0], R[:, 1], t])


def apply_homography(H: np.ndarray, p: np.ndarray) -> np.ndarray:
    q = np.column_stack([p, np.ones(len(p))]) @ H.T
    return q[:, :2] / q[:, 2:3]


def _moments(p: np.ndarray):
    m = cv2.moments(p.astype(np.float32).reshape(-1, 1, 2))
    if abs(m["m00"]) < 1e-9:
        return None
    c = np.array([m["m10"], m["m01"]]) / m["m00"]
    theta = 0.5 * np.arctan2(2 * m["mu11"], m["mu20"] - m["mu02"])
    return abs(m["m00"]), c, theta


def _h_line_system(model_lines, pts):
    """The unweighted rows of :func:`_fit_h_lines` (one per point) and the normalisation
    ``T``: fixed while only the weights change (IRLS)."""
    c = pts.mean(axis=0)
    s = np.sqrt(2) / max(np.sqrt(((pts - c) ** 2).sum(axis=1)).mean(), 1e-9)
    T = np.array([[s, 0, -s * c[0]], [0, s, -s * c[1]], [0, 0, 1.0]])
    ph = np.column_stack([(pts - c) * s, np.ones(len(pts))])
    return (model_lines[:, :, None] * ph[:, None, :]).reshape(len(pts), 9), T


def _fit_h_lines(model_lines, pts, w, system=None):
    """Homography H (plane -> image) with each image point ``pts[i]`` on the plane line
    ``model_lines[i]``: ``l^T H^-1 p = 0`` is linear in ``G = H^-1``; weighted SVD on
    normalised pixels. ``system``: :func:`_h_line_system` of the same points, if known."""
    A, T = system if system is not None else _h_line_system(model_lines, pts)
    _, v = np.linalg.eigh((A * (w * w)[:, None]).T @ A)  # 9 x 9: cheaper than A's SVD
    G = v[:, 0].reshape(3, 3) @ T
    H = np.linalg.inv(G)
    return H / H[2, 2]


def _edge_distances(H, model, pts):
    """Distance of each point to each projected model edge (segment), (M, N)."""
    C = apply_homography(H, model)
    a, d = C, np.roll(C, -1, axis=0) - C
    tt = np.clip(((pts[:, None, :] - a[None]) * d[None]).sum(axis=2) / (d ** 2).sum(axis=1),
                 0, 1)
    return np.linalg.norm(pts[:, None, :] - (a[None] + tt[..., None] * d[None]), axis=2)


def fit_model_to_contour(contour_ideal: np.ndarray, camera: Camera, holder: Holder,
                         gates_px=(40.0, 20.0, 10.0, 6.0, 4.0, 4.0)):
    """Fit the holder's inner contour (a plane polygon) to an image contour by a homography.

    Initial guess: the nominal projection moved, turned and scaled onto the contour's centroid,
    principal axis and area (image moments). Then closest-edge assignment (ICP) with a
    shrinking gate, each time a Huber-weighted fit of the points to their model lines
    (:func:`_fit_h_lines`, a few reweighting steps).

    Returns
    -------
    H : (3, 3) homography holder plane (mm) -> ideal pixels.
    assign : (M,) index of the model edge each contour point is closest to.
    dist : (M,) its distance to that edge (ideal px).
    """
    model = np.asarray(holder.corners_mm, float)
    lines = holder.edge_lines
    H0 = _homography_nominal(camera, holder)
    mi, mn = _moments(contour_ideal), _moments(apply_homography(H0, model))
    if mi is None or mn is None:
        raise FeatureError("the inside contour encloses no area")
    (ai, ci, ti), (an, cn, tn) = mi, mn
    dt = (ti - tn + np.pi / 2) % np.pi - np.pi / 2  # the axis is known up to 180 deg
    s = np.sqrt(ai / an)
    cs, sn = s * np.cos(dt), s * np.sin(dt)
    S = np.array([[cs, -sn, 0], [sn, cs, 0], [0, 0, 1.0]])
    S[:2, 2] = ci - S[:2, :2] @ cn
    H = S @ H0
    H = H / H[2, 2]
    all_pts = np.asarray(contour_ideal, float)
    for gate in gates_px:
        # coarse gates: every 4th contour point is plenty (one point per pixel); speed
        pts = all_pts[::4] if gate > 6.0 else all_pts
        D = _edge_distances(H, model, pts)
        assign = np.argmin(D, axis=1)
        dist = D[np.arange(len(pts)), assign]
        use = dist < gate
        if use.sum() < 16:
            raise FeatureError("the inside contour does not resemble the holder's pocket")
        p, ln = pts[use], lines[assign[use]]
        w = np.ones(len(p))
        for _ in range(3):
            H = _fit_h_lines(ln, p, w)
            # geometric residual: plane distance (mm) times the local scale (px / mm)
            q = np.column_stack([p, np.ones(len(p))]) @ np.linalg.inv(H).T
            r_mm = (ln * q).sum(axis=1) / q[:, 2]
            r = r_mm * np.sqrt(abs(np.linalg.det(H[:2, :2])))
            k = max(1.0, gate / 4)
            w = np.where(np.abs(r) <= k, 1.0, k / np.maximum(np.abs(r), 1e-12)) / np.abs(q[:, 2])
    D = _edge_distances(H, model, all_pts)
    assign = np.argmin(D, axis=1)
    return H, assign, D[np.arange(len(all_pts)), assign]


def model_features(contours: list, sub, roi, camera: Camera, holder: Holder,
                    params: FeatureParams):
    """Lines of the holder's 20 edges from the model fitted to the thresholded contour, then the
    gradient refinement; the fallback when the paper's segmentation does not give the 20
    characteristic segments (worn, chipped or stained edges, occluded corners).

    ``contours``: (level, contour_px, contour_ideal) of each threshold tried. The one whose fit
    covers most of the model's perimeter is used. Returns what :func:`detect_features` needs.
    """
    model = np.asarray(holder.corners_mm, float)
    n = len(model)
    tol = params.line_tol_px
    best = None
    perimeter = np.linalg.norm(np.diff(apply_homography(_homography_nominal(camera, holder), model),
                                       axis=0, append=np.nan), axis=1)
    perimeter = float(np.nansum(perimeter))
    for level, cpx, cid in contours:
        if len(cid) < 0.5 * perimeter:  # a stain's hole, not the pocket
            continue
        try:
            H, assign, dist = fit_model_to_contour(cid, camera, holder)
        except (FeatureError, np.linalg.LinAlgError, ValueError):
            continue
        C = apply_homography(H, model)
        lengths = np.linalg.norm(np.roll(C, -1, axis=0) - C, axis=1)
        inl = np.abs(dist) < tol
        covered = np.bincount(assign[inl], minlength=n)[:n]
        # coverage: contour points (about 1 per px) on an edge, over its length
        score = float(np.minimum(covered / np.maximum(lengths, 1), 1.0) @ lengths
                      / lengths.sum())
        if best is None or score > best[0]:
            best = (score, level, cpx, cid, H, assign, inl, C)
    if best is None:
        raise FeatureError("the model of the pocket could not be fitted to any inside contour")
    score, level, cpx, cid, H, assign, inl, C = best
    if score < 0.5:
        raise FeatureError(f"only {100 * score:.0f} % of the pocket's outline found on the "
                           f"best contour (threshold {level}): holder hidden or not in view")
    sign = np.sign(signed_area(C))
    segs, lines0, inward, spans = [], np.zeros((n, 3)), np.zeros((n, 2)), []
    margin = params.refine_half_width_px
    for k in range(n):
        a, b = C[k], C[(k + 1) % n]
        L = float(np.linalg.norm(b - a))
        d = (b - a) / L
        n_in = sign * np.array([-d[1], d[0]])
        lines0[k] = line_from(a, n_in)
        inward[k] = n_in
        spans.append((margin, L - margin, a, d))
        idx = np.nonzero((assign == k) & inl)[0]
        segs.append(Segment("line", int(idx.min()) if len(idx) else 0,
                            int(idx.max()) + 1 if len(idx) else 0, cid[idx], float(len(idx))))
    return level, cpx, cid, segs, lines0, inward, spans, score


def check_edge_support(lines, edges, spans, camera, params):
    """Each refined line must rest on gradient edge points along a good part of its length
    (a hidden or broken edge gives few, scattered points)."""
    for k, (L, e, sp) in enumerate(zip(lines, edges, spans)):
        length = max(sp[1] - sp[0] - 2 * params.refine_trim_px, 1.0)
        if len(e):
            r = np.abs(camera.undistort_px(e) @ L[:2] + L[2])
            support = float((r < 1.0).sum()) * params.refine_step_px / length
        else:
            support = 0.0
        min_fraction = params.min_edge_support
        if support < min_fraction:
            mid = camera.distort_px((sp[2] + 0.5 * (sp[0] + sp[1]) * sp[3])[None])[0]
            raise FeatureError(
                f"edge {k} near {where_px(mid)} px: gradient edge found along only "
                f"{100 * support:.0f} % of it (< {100 * min_fraction:.0f} %): occluded or "
                "damaged")


# ------------------------------------------------------------------------------------------
# field chain (issue 10): the outline found on the gradient, robustly
def _line_distances_px(H: np.ndarray, plane_lines: np.ndarray, pts: np.ndarray,
                       which: np.ndarray | None = None) -> np.ndarray:
    """Signed distance (ideal px) of image points to the images ``H^-T l`` of plane lines
    (``pts[i]`` to line ``plane_lines[i]``, or to ``plane_lines[which[i]]``: each distinct
    line mapped once)."""
    Li = plane_lines @ np.linalg.inv(H)  # rows: image lines l^T H^-1
    Li = Li / np.linalg.norm(Li[:, :2], axis=1, keepdims=True)
    if which is not None:
        Li = Li[which]
    return Li[:, 0] * pts[:, 0] + Li[:, 1] * pts[:, 1] + Li[:, 2]


def _innermost_peak(g: np.ndarray, j_max: np.ndarray, fraction: float) -> np.ndarray:
    """Per row of ``g``, the first local maximum (from the pocket side) reaching ``fraction``
    of the row's maximum ``g[j_max]``; ``j_max`` where there is none."""
    gmax = g[np.arange(len(g)), j_max]
    cand = np.zeros(g.shape, bool)
    cand[:, 1:-1] = ((g[:, 1:-1] >= g[:, :-2]) & (g[:, 1:-1] > g[:, 2:])
                     & (g[:, 1:-1] >= fraction * gmax[:, None]))
    return np.where(cand.any(axis=1), np.argmax(cand, axis=1), j_max)


def search_outline(img: np.ndarray, roi_origin, camera: Camera, holder: Holder,
                   H0: np.ndarray, params: FeatureParams):
    """Model-guided search of the pocket outline on the gradient (field chain).

    From the homography ``H0`` (holder plane mm -> ideal px; the outline match), for each gate
    ``W`` of ``search_gates_px``: profiles across every projected edge (one per
    ``search_step_px``, ``corner_trim_px`` away from the corners, ``+-W`` px, smoothed along
    the normal with ``W / 12`` px) give per profile the strongest dark-to-bright step going
    outwards (pocket to face), if it stands out of the profiles' noise (3 robust sigmas of the
    derivative in wide windows, a quarter of the median step in narrow ones: no fixed grey
    level or contrast). The homography is re-fitted to all those
    points at once, each on its edge's line (:func:`_fit_h_lines`), by IRLS with Tukey weights
    whose scale is the MAD of the residuals under the current homography (the robust start).
    Edge points on the cutter's silhouette have the opposite polarity; those on slurry, chips
    or highlights get no weight.

    Returns
    -------
    H : (3, 3) the fitted homography; support : share of the last gate's profiles (over the
    whole outline) whose edge point fits it.
    """
    plane_lines = holder.edge_lines
    model = np.asarray(holder.corners_mm, float)
    n = len(model)
    H = np.asarray(H0, float)
    frac = 0.0
    for W in params.search_gates_px:
        C = apply_homography(H, model)
        sign = np.sign(signed_area(C))
        nxt = np.roll(C, -1, axis=0)
        step = 1.0 if W >= 10 else 0.5
        offsets = np.arange(-W, W + 1e-9, step)
        length = np.linalg.norm(nxt - C, axis=1)
        d = (nxt - C) / np.maximum(length, 1e-9)[:, None]
        if not np.all(np.isfinite(length)):
            raise FeatureError("the pocket outline fit degenerated: holder not in view")
        ts = [np.arange(params.corner_trim_px, float(length[k]) - params.corner_trim_px + 1e-9,
                        params.search_step_px) for k in range(n)]
        which = np.repeat(np.arange(n), [len(t) for t in ts])
        base = C[which] + np.concatenate(ts)[:, None] * d[which]
        n_out = (-sign * np.column_stack([-d[:, 1], d[:, 0]]))[which]
        if len(base) < 16 or not np.all(np.isfinite(base)):
            raise FeatureError("the pocket outline fit degenerated: holder not in view")
        prof = sample_profiles(img, roi_origin, camera, base, n_out, offsets)
        prof = smooth_rows(prof, max(W / 12.0, 0.8) / step)
        g = np.diff(prof, axis=1)
        j = np.argmax(g, axis=1)
        peak = g[np.arange(len(g)), j]
        # wide windows are mostly flat: the derivative's MAD is its noise; narrow ones hold
        # little but the edge, so there a step must reach a quarter of the median step
        g_all = g.reshape(1, -1)
        noise = (MAD_TO_SIGMA * float(median_rows(np.abs(g_all - median_rows(g_all)[0]))[0])
                 if W >= 10 else
                 0.25 / 3.0 * float(np.median(peak[peak > 0])) if np.any(peak > 0) else 0.0)
        if W < 20 and params.edge_innermost > 0:
            # near the outline: the innermost rise of a broken edge, as the line fits take it
            # (edges.half_max_centroids), not whichever of its rises is strongest here
            ji = _innermost_peak(g, j, params.edge_innermost)
            pi = g[np.arange(len(g)), ji]
            # unless most innermost rises drown in the noise (a textured, stained face):
            # then this gate takes the strongest, as a whole (mixing the two per profile
            # would put the points on different rises)
            if np.count_nonzero(pi > 3.0 * noise) >= 0.5 * np.count_nonzero(peak > 3.0 * noise):
                j, peak = ji, pi
        # parabolic sub-sample peak
        jj = np.clip(j, 1, g.shape[1] - 2)
        y0, y1, y2 = (g[np.arange(len(g)), jj + e] for e in (-1, 0, 1))
        den = y0 - 2 * y1 + y2
        frac_j = np.where(np.abs(den) > 1e-12, 0.5 * (y0 - y2) / np.where(den == 0, 1, den), 0)
        o = offsets[0] + step * (jj + 0.5 + np.clip(frac_j, -1, 1))
        ok = (peak > 3.0 * noise) & (j > 0) & (j < g.shape[1] - 1)
        if ok.sum() < 16:
            raise FeatureError(f"no pocket edge found along the outline ({int(ok.sum())} edge "
                               "points): holder hidden or not in view")
        p = base[ok] + o[ok, None] * n_out[ok]
        k_ok = which[ok]
        ln = plane_lines[k_ok]
        r = _line_distances_px(H, plane_lines, p, k_ok)
        s = mad_scale(r, 0.25)
        system = _h_line_system(ln, p)  # only the weights change below
        for _ in range(6):
            w = tukey_weights(r, s)
            if np.count_nonzero(w) < 16:
                break
            q = np.column_stack([p, np.ones(len(p))]) @ np.linalg.inv(H).T
            H1 = _fit_h_lines(ln, p, np.sqrt(w) / np.abs(q[:, 2]), system)
            moved = np.abs(apply_homography(H1, model) - C).max()
            if not np.isfinite(moved) or moved > 2.0 * max(params.search_gates_px):
                # the points do not hold the fit (few edge points, lumps and stains over much
                # of the outline): it left the search's reach, keep the previous fit
                break
            r = _line_distances_px(H1, plane_lines, p, k_ok)
            H = H1
            s = min(s, mad_scale(r[w > 0], 0.1))
        # share of all profiles (the whole outline) whose edge point fits
        frac = float(np.count_nonzero(tukey_weights(r, s) > 0)) / len(base)
    return H, frac
