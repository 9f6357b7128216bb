"""Sub-pixel edges (beyond the paper's section 2.1): the characteristic lines refined on the
grey-level gradient, their intersections (the corners), and the edge-wear indicator.

Grey profiles are sampled along each line's normal (through the camera's distortion, on the
unfiltered image); the edge point of a profile is where its derivative peaks (half-maximum
centroid), and the line is fitted with Huber-weighted total least squares. For an edge blurred
by a symmetric point-spread function the gradient maximum is the edge itself, whatever the blur
width and the two grey levels. A worn edge (the face darkened next to the pocket) drags that
point outwards; :func:`edge_wear` measures the darkening and the offset it implies.

Convention:
    Lines are homogeneous ``(a, b, c)`` with ``a u + b v + c = 0`` and ``(a, b)`` a unit normal,
    in ideal (undistorted) pixels; see :mod:`cutterpose.image.features`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import cv2
import numpy as np
from scipy.ndimage import gaussian_filter1d

from ..geometry.camera import Camera
from .lines import (
    TUKEY_C,
    fit_line,
    intersect_consecutive,  # noqa: F401 - also taken from here (cutterpose.pipeline)
    line_from,
    lmeds_lines,
    median_rows,
    tukey_lines,
)
from .params import signed_area

if TYPE_CHECKING:
    from .params import FeatureParams

def _robust_line(p: np.ndarray, iterations: int = 5):
    """Huber-weighted total least squares line (IRLS); returns centroid, direction, normal."""
    c, d, n = fit_line(p)
    for _ in range(iterations):
        r = (p - c) @ n
        a = np.abs(r)
        s = 1.4826 * np.median(a) + 1e-6  # residuals of a fitted line are centred
        k = 1.5 * s
        w = np.where(a <= k, 1.0, k / np.maximum(a, 1e-12))
        c1, d, n1 = fit_line(p, w)
        if n1 @ n < 0:
            n1 = -n1
        moved = abs((c1 - c) @ n1) + float(np.linalg.norm(n1 - n)) * 1e3
        c, n = c1, n1
        if moved < 1e-4:  # converged (offset and tilt over 1000 px below 1e-4 px)
            break
    return c, d, n


def half_max_centroids(g: np.ndarray, o0: float, step: float,
                        groups: np.ndarray | None = None, n_groups: int = 0,
                        innermost: float = 0.0, first: int = 0):
    """Sub-pixel edge position of each profile derivative ``g`` (rows): the centroid of
    ``g - g_j / 2`` over the contiguous run around the chosen peak ``j`` where ``g > g_j / 2``.

    For a symmetric point-spread function the derivative of the edge profile is symmetric about
    the edge, and so is its half-maximum run: the centroid is the edge, for narrow (Gaussian) and
    flat-topped (defocus disk) blur alike. Rows whose run touches the window's end, or whose
    peak is weak (< 0.3 of the median peak), are rejected.

    ``innermost`` = 0: the peak is the row's maximum (the strongest rise). ``innermost`` =
    ``f`` > 0 (field chain): the first local maximum from the window's start (the pocket side)
    reaching ``f`` of the row's maximum, and its run ends at the valley before the next rise.
    A broken edge (fillet or chamfer) images as two or more rises (wall to fillet, a specular
    line on the fillet, fillet to face) whose strengths swap along the edge with the texture and
    the light; the strongest one jumps between them, the innermost one (where the fillet meets
    the wall, within about ``r`` of depth of the design edge, whatever the shading) does not.
    Rises before sample ``first`` are not candidates (farther into the pocket than a line may
    lie: there a rise is an occluder's outline, slurry over the edge or the cutter).

    Returns
    -------
    offsets : edge positions of the accepted rows; rows : their indices.
    """
    rows_all = np.arange(len(g))
    if innermost > 0 and g.shape[1] >= 3:
        gl, gr = row_neighbours(g)
        cand = (g >= gl) & (g > gr) & (g >= innermost * g.max(axis=1)[:, None])
        cand[:, :first] = False
        j = np.where(cand.any(axis=1), np.argmax(cand, axis=1), np.argmax(g, axis=1))
        # the run also stops at a valley towards the next rise, so that two rises merged
        # above half height are not averaged
        cen, ok = run_centroids(g, j, gl, gr)
    else:
        j = np.argmax(g, axis=1)
        cen, ok = run_centroids(g, j)
    peak = g[rows_all, j]
    if groups is not None:  # the profiles of several lines at once: the median per line
        med = group_median(peak[ok], groups[ok], n_groups)
        ok[ok] &= peak[ok] > 0.3 * med[groups[ok]]
    elif ok.any():
        ok &= peak > 0.3 * np.median(peak[ok])
    rows = np.nonzero(ok)[0]
    return o0 + step * cen[rows], rows


def _nearest_rise_centroids(g: np.ndarray, o0: float, step: float, o_expected: np.ndarray,
                            fraction: float, gate_px: float):
    """Per row of ``g``: the rise (a local maximum reaching ``fraction`` of the row's maximum)
    whose peak is nearest ``o_expected`` (same units as the offsets ``o0 + step * index``), and
    its half-maximum centroid as in :func:`half_max_centroids` (the run split at valleys).
    Rows with no rise within ``gate_px`` of ``o_expected`` are left out.

    Returns
    -------
    offsets : edge positions of the kept rows; rows : their indices.
    """
    G = g.shape[1]
    gl, gr = row_neighbours(g)
    gmax = g.max(axis=1)
    cand = (g >= gl) & (g > gr) & (g >= fraction * gmax[:, None]) & (g > 0)
    pos = o0 + step * np.arange(G)
    dist = np.where(cand, np.abs(pos[None, :] - o_expected[:, None]), np.inf)
    j = np.argmin(dist, axis=1)
    near = dist[np.arange(len(g)), j] <= gate_px
    cen, ok = run_centroids(g, j, gl, gr)
    rows = np.nonzero(ok & near)[0]
    return o0 + step * cen[rows], rows


def row_neighbours(g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each sample's left and right neighbour along the rows (+inf / -inf past the ends)."""
    gl, gr = np.empty_like(g), np.empty_like(g)
    gl[:, 0], gl[:, 1:] = np.inf, g[:, :-1]
    gr[:, -1], gr[:, :-1] = -np.inf, g[:, 1:]
    return gl, gr


def run_centroids(g: np.ndarray, j: np.ndarray, gl: np.ndarray | None = None,
                   gr: np.ndarray | None = None, positions: np.ndarray | None = None,
                   bounds: bool = False):
    """Centroid of ``g - g_j / 2`` over the run round peak ``j`` of each row where
    ``g > g_j / 2``, stopped at valleys (local minima below 0.8 of the peak) when the
    neighbours ``gl``, ``gr`` are given; ``ok`` where the run stays inside the row.

    The centroid is in sample indices, or in ``positions`` (G,) when given (the edge model's
    grid: :func:`cutterpose.image.edge_model.gradient_edge_px`, which must find the same edge
    as the detector). With ``bounds`` also the run's ``left`` and ``right`` (exclusive)."""
    G = g.shape[1]
    # small integer types: these masks and index arrays are (profiles x samples)
    idx = np.arange(G, dtype=np.int16)
    peak = g[np.arange(len(g)), j]
    half = 0.5 * peak
    jj = j.astype(np.int16)[:, None]
    below = g <= half[:, None]
    if gl is not None:
        below |= (g <= gl) & (g < gr) & (g < 0.8 * peak[:, None])
    left = np.where(below & (idx < jj), idx, np.int16(-1)).max(axis=1)
    right = np.where(below & (idx > jj), idx, np.int16(G)).min(axis=1)
    inside = (idx > left[:, None]) & (idx < right[:, None])
    w = np.where(inside, g - half[:, None], 0.0)
    pos = np.arange(G, dtype=w.dtype) if positions is None else positions.astype(w.dtype)
    with np.errstate(invalid="ignore", divide="ignore"):
        cen = (w @ pos).astype(float) / w.sum(axis=1)
    ok = (left >= 0) & (right < G) & (peak > 0) & np.isfinite(cen)
    return (cen, ok, left, right) if bounds else (cen, ok)


def refine_lines(image: np.ndarray, roi_origin: np.ndarray, camera: Camera,
                 lines_ideal: np.ndarray, spans: list, inward: np.ndarray,
                 params: FeatureParams):
    """Re-fit each line to sub-pixel edge points on the grey-level gradient.

    For a line with inward normal ``n`` (towards the dark pocket), profiles
    ``g(o) = I(distort(q + o n_out))`` are sampled at ``o in [-h, h]`` (step 0.25 px) for points
    ``q`` spaced ``refine_step_px`` along the line's straight run; the edge point of a profile is
    the sub-pixel maximum of ``dg/do`` (dark to bright). Lines are fitted with Huber IRLS.

    Parameters
    ----------
    image : the ROI of the unfiltered grey image.
    roi_origin : (u0, v0) of the ROI in the full image.
    lines_ideal : (N, 3) initial lines (ideal px).
    spans : per line, (t0, t1, c, d): its straight run as positions along direction d from c.
    inward : (N, 2) unit normals towards the pocket.

    Returns
    -------
    lines : (N, 3) refined lines (a line keeps its initial value if too few edge points).
    edge_points_px : per line, (n_i, 2) observed pixels of the accepted edge points.
    """
    h = params.refine_half_width_px
    offsets = np.arange(-h, h + 1e-9, 0.25)
    img = image.astype(np.float32)
    out_lines = np.array(lines_ideal, float)
    for _ in range(max(1, params.refine_passes)):
        out_lines, edges = _refine_pass(img, roi_origin, camera, out_lines, spans, inward,
                                        params, offsets)
    return out_lines, edges


def _refine_pass(img, roi_origin, camera, lines_ideal, spans, inward, params, offsets):
    out_lines = np.array(lines_ideal, float)
    edges = []
    for k, (t0, t1, c, d) in enumerate(spans):
        t0, t1 = t0 + params.refine_trim_px, t1 - params.refine_trim_px
        if t1 - t0 < 5 * params.refine_step_px:
            edges.append(np.zeros((0, 2)))
            continue
        n_out = -inward[k]
        ts = np.arange(t0, t1 + 1e-9, params.refine_step_px)
        # project the run's points onto the current line
        L = out_lines[k]
        base = c + ts[:, None] * d
        base = base - ((base @ L[:2]) + L[2])[:, None] * L[:2]
        q = base[:, None, :] + offsets[None, :, None] * n_out  # (T, O, 2) ideal px
        obs = camera.distort_px(q.reshape(-1, 2)) - roi_origin
        mx = obs[:, 0].reshape(q.shape[:2]).astype(np.float32)
        my = obs[:, 1].reshape(q.shape[:2]).astype(np.float32)
        prof = cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        if params.refine_sigma_px > 0:
            prof = gaussian_filter1d(prof, params.refine_sigma_px / 0.25, axis=1)
        g = np.diff(prof, axis=1)  # derivative at offsets[:-1] + 0.125
        o, rows = half_max_centroids(g, offsets[0] + 0.125, 0.25)
        pts = base[rows] + o[:, None] * n_out
        if len(pts) < 5:
            edges.append(np.zeros((0, 2)))
            continue
        cc, dd, nn = _robust_line(pts)
        out_lines[k] = line_from(cc, nn)
        edges.append(camera.distort_px(pts))
    return out_lines, edges


def edge_wear(image: np.ndarray, roi_origin: np.ndarray, camera: Camera, lines_ideal: np.ndarray,
              spans: list, inward: np.ndarray, params: FeatureParams):
    """How far each refined edge may lie outside the true edge because the face is not uniform
    up to it (worn, rounded, dull or stained edge); beyond the paper.

    A clean edge is a step from the pocket's grey to a uniform face blurred by the optics: the
    face just outside the blur (2 blur half-widths from the edge) is as bright as farther out.
    On a worn edge the face darkens towards the edge, part of the edge's contrast lies outside
    the sharp step and the gradient's centroid (the refined edge) is pulled outwards by about
    that fraction of the transition's width; where the true edge lies within the transition
    the image cannot tell. Per line, on the median profile along its normal:

    - ``w``: the blur half-width, from the gradient peak to the pocket-side 25 % crossing (the
      pocket side is not worn);
    - ``darkening = 1 - (I(e + 2w) - I_pocket) / (I_face_far - I_pocket)``, ``I_pocket =
      I(e - 2w)``, ``I_face_far`` the median of ``I`` over ``[e + 2w + 6, e + 2w + 12]`` px;
    - ``offset_px = max(|darkening| - 0.05, 0) * w``: the possible outward bias (the 0.05 floor
      is above the +-0.01 measured on unworn faces).

    Returns
    -------
    darkening, offset_px : (N,) per line (NaN where the profile has no usable edge).
    """
    step, hw = 0.5, params.refine_half_width_px
    offsets = np.arange(-3 * hw, 5 * hw + 1e-9, step)  # outwards (face) positive
    img = np.asarray(image, np.float32)  # no copy when the caller has the float ROI
    n = len(lines_ideal)
    dark, off = np.full(n, np.nan), np.full(n, np.nan)
    # every line's profiles in one distortion call and one remap (issue 13)
    bases, which = [], []
    for k, (t0, t1, c, d) in enumerate(spans):
        t0, t1 = t0 + 2 * params.refine_trim_px, t1 - 2 * params.refine_trim_px
        if t1 - t0 < 8:
            continue
        L = lines_ideal[k]
        ts = np.arange(t0, t1, 4.0)  # a median profile: every 4th px is plenty
        base = c + ts[:, None] * d
        bases.append(base - ((base @ L[:2]) + L[2])[:, None] * L[:2])
        which.append(np.full(len(ts), k))
    if not bases:
        return dark, off
    base, which = np.vstack(bases), np.concatenate(which)
    # the distortion linearised along each profile (<= 0.004 px over its 32 px on the Table 1
    # camera, well below remap's 1/32 px grid): two distortion calls instead of one per sample
    prof = sample_profiles(img, roi_origin, camera, base, -np.asarray(inward, float)[which],
                           offsets)
    ks = np.unique(which)
    medians = np.stack([median_rows(np.ascontiguousarray(prof[which == k].T)) for k in ks])
    smooth = smooth_rows(medians, params.refine_sigma_px / step)
    go = offsets[:-1] + step / 2
    near = np.abs(go) <= hw
    for k, m in zip(ks, smooth):
        g = np.diff(m)
        j = int(np.argmax(np.where(near, g, -np.inf)))
        if g[j] <= 0:
            continue
        i = j
        while i > 0 and g[i] > 0.25 * g[j]:
            i -= 1
        w = max(go[j] - go[i], step)
        e = go[j]
        lo, hi = e + 2 * w + 6, e + 2 * w + 12
        far = (offsets >= lo) & (offsets <= hi)
        if not far.any() or e - 2 * w < offsets[0]:
            continue
        pocket = np.interp(e - 2 * w, offsets, m)
        contrast = float(_median1d(m[far]) - pocket)
        if contrast <= 0:
            continue
        dark[k] = 1.0 - (np.interp(e + 2 * w, offsets, m) - pocket) / contrast
        off[k] = max(abs(dark[k]) - 0.05, 0.0) * w
    return dark, off


def smooth_rows(a: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian smoothing of each row of a 2-D float32 array: ``scipy.ndimage.
    gaussian_filter1d(a, sigma, axis=1)`` (same kernel, radius ``int(4 sigma + 0.5)``, same
    "reflect" border) by ``cv2.filter2D`` with a one-row kernel, several times faster (float32
    sums: equal to ~1e-6 relative; ``cv2.sepFilter2D`` would also make a pass with a one-tap
    column kernel)."""
    r = int(4.0 * sigma + 0.5)
    x = np.arange(-r, r + 1, dtype=float)
    k = np.exp(-0.5 / sigma ** 2 * x * x)
    k /= k.sum()
    a = np.ascontiguousarray(a, np.float32)
    return cv2.filter2D(a, -1, k[None, :], borderType=cv2.BORDER_REFLECT)


def _median1d(x: np.ndarray):
    """``np.median`` of a short 1-D array without its overhead (same value and dtype)."""
    s = np.sort(x)
    return (s[(len(s) - 1) // 2] + s[len(s) // 2]) / 2


def group_median(values: np.ndarray, groups: np.ndarray, n_groups: int) -> np.ndarray:
    """Median of ``values`` per group label ``groups`` (0 .. n_groups - 1), as ``np.median``
    of each group (NaN for an empty group), with one sort for all groups; in the values'
    dtype."""
    values = np.asarray(values)
    order = np.lexsort((values, groups))
    v = values[order]
    counts = np.bincount(groups, minlength=n_groups)[:n_groups]
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    med = np.full(n_groups, np.nan, dtype=np.result_type(values.dtype, np.float32))
    has = counts > 0
    lo = start[has] + (counts[has] - 1) // 2
    hi = start[has] + counts[has] // 2
    med[has] = (v[lo] + v[hi]) / 2
    return med


def sample_profiles(img: np.ndarray, roi_origin, camera: Camera, base_ideal: np.ndarray,
                    n_out: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """Grey profiles ``I(distort(q + o n_out))`` for base points ``q`` (T, 2, ideal px) at
    offsets ``o`` (O,), as a (T, O) float32 array (bilinear, on ``img`` whose pixel (0, 0) is
    ``roi_origin``). The distortion is linearised along each short profile (two
    :meth:`Camera.distort_px` calls for T points instead of T x O)."""
    if len(base_ideal) == 0:
        return np.zeros((0, len(offsets)), np.float32)
    n_out = np.broadcast_to(np.asarray(n_out, float), base_ideal.shape)
    # both ends' distortion in one call
    both = camera.distort_px(np.concatenate([base_ideal, base_ideal + n_out]))
    o0, o1 = both[:len(base_ideal)], both[len(base_ideal):]
    d1 = o1 - o0
    origin = np.asarray(roi_origin, float)
    # one coordinate map at a time, straight to float32 (no (T, O, 2) float64 array)
    mx = (o0[:, 0:1] + offsets[None, :] * d1[:, 0:1] - origin[0]).astype(np.float32)
    my = (o0[:, 1:2] + offsets[None, :] * d1[:, 1:2] - origin[1]).astype(np.float32)
    return cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def robust_edge_lines(img: np.ndarray, roi_origin, camera: Camera, pred_ideal: np.ndarray,
                      params: FeatureParams):
    """The 20 lines on their sub-pixel gradient edge points, robustly (field chain).

    ``pred_ideal`` (N, 2): the corners predicted by the outline fit, in holder order; edge
    ``k`` runs from corner ``k`` to ``k + 1``. Along each predicted edge, away from its
    corners by ``corner_trim_px``, a profile every ``refine_step_px`` across
    ``+-refine_half_width_px`` (0.25 px steps, unfiltered image) gives an edge point (centroid
    of the half-maximum run of the dark-to-bright derivative, :func:`half_max_centroids`).
    Points on slurry, on the cutter's silhouette, on a chip or a highlight are outliers: the
    line starts from the least-median-of-squares line (:func:`lmeds_line`, the predicted line
    among the hypotheses) and is refined by Tukey IRLS with a MAD scale (:func:`tukey_line`).
    A line is *seen* if its inliers cover ``min_line_support`` of the profiled length and it
    stays within ``max_line_shift_px`` of the prediction.

    Speed (issue 13): the profiles of all edges are sampled, smoothed and reduced to edge
    points together (one :func:`sample_profiles`, i.e. one ``cv2.remap``), and the IRLS of
    all lines runs batched (:func:`tukey_lines`); per line, the same numbers as one at a time.

    Returns
    -------
    lines : (N, 3) lines (NaN where not seen); seen : (N,) bool; edge_points_px : per line
    the inlier edge points (observed px); support : (N,) covered fraction; scale_px : (N,)
    the final robust scale.
    """
    n = len(pred_ideal)
    pred_ideal = np.asarray(pred_ideal, float)
    nxt = np.roll(pred_ideal, -1, axis=0)
    sign = np.sign(signed_area(pred_ideal))
    hw = params.refine_half_width_px
    offsets = np.arange(-hw, hw + 1e-9, 0.25)
    lines = np.full((n, 3), np.nan)
    seen = np.zeros(n, bool)
    support = np.zeros(n)
    scale = np.full(n, np.nan)
    trim = params.corner_trim_px
    length = np.linalg.norm(nxt - pred_ideal, axis=1)
    d = (nxt - pred_ideal) / np.maximum(length, 1e-9)[:, None]
    n_in = sign * np.column_stack([-d[:, 1], d[:, 0]])
    ts_k = [np.arange(trim, float(length[k]) - trim + 1e-9, params.refine_step_px)
            for k in range(n)]
    counts = np.array([len(t) if len(t) >= 5 else 0 for t in ts_k])
    which = np.repeat(np.arange(n), counts)
    if len(which) == 0:
        return lines, seen, [np.zeros((0, 2))] * n, support, scale
    ts = np.concatenate([t for t, c in zip(ts_k, counts) if c])
    base = pred_ideal[which] + ts[:, None] * d[which]
    prof = sample_profiles(img, roi_origin, camera, base, -n_in[which], offsets)
    if params.refine_sigma_px > 0:
        prof = smooth_rows(prof, params.refine_sigma_px / 0.25)
    o, rows = half_max_centroids(np.diff(prof, axis=1), offsets[0] + 0.125, 0.25, which, n,
                                   innermost=params.edge_innermost,
                                   first=int(np.searchsorted(offsets[:-1] + 0.125,
                                                             -params.max_line_shift_px)))
    pts_all = base[rows] - o[:, None] * n_in[which[rows]]
    w_all = which[rows]
    fit = []  # edges with enough points: (k, points, profiled run's ends)
    for k in range(n):
        pts = pts_all[w_all == k]
        if counts[k] == 0 or len(pts) < 5:
            continue
        ends = pred_ideal[k] + ts_k[k][[0, -1], None] * d[k]
        fit.append((k, pts, ends))
    ks = [f[0] for f in fit]
    # hypotheses must cross the run's end normals within [-shift, shift + outward] px of the
    # prediction (outwards positive): a band centred half the outward allowance out
    mid = 0.5 * params.max_outward_shift_px
    L0, s0 = lmeds_lines([f[1] for f in fit], priors=[line_from(pred_ideal[k], n_in[k])
                                                       for k in ks],
                         seeds=ks, gate_points=[f[2] - mid * n_in[f[0]] for f in fit],
                         gate_px=params.max_line_shift_px + 0.5 * params.max_outward_shift_px)
    Ls, ss, ws = tukey_lines([f[1] for f in fit], L0, s0)
    if params.edge_innermost > 0 and fit:
        Ls, ss, ws = _refit_nearest_rise(fit, Ls, ss, ws, prof, base, which, rows, w_all,
                                         n_in, offsets, params)
    return _judge_lines(fit, Ls, ss, ws, ts_k, n_in, camera, params)

def _judge_lines(fit, Ls, ss, ws, ts_k, n_in, camera: Camera, params: FeatureParams):
    """The lines of :func:`robust_edge_lines` judged: support (inliers' share of the profiled
    length), seen (enough support, within the shift limits of the prediction, not much noisier
    than the others), and the inlier points distorted to observed pixels. Returns its
    ``(lines, seen, edge_points_px, support, scale_px)``."""
    n = len(n_in)
    lines = np.full((n, 3), np.nan)
    seen = np.zeros(n, bool)
    support = np.zeros(n)
    scale = np.full(n, np.nan)
    inliers = {}
    for (k, pts, ends), L, s_k, w in zip(fit, Ls, ss, ws):
        inl = w > 0
        ts = ts_k[k]
        support[k] = np.count_nonzero(inl) * params.refine_step_px / max(ts[-1] - ts[0], 1.0)
        scale[k] = s_k
        # where the fitted line crosses the normals at both ends of the profiled run, outwards
        # positive: a broken edge's rise lies up to its width outside the design edge (the
        # outline fit averages over edges), an occluder's outline (slurry across the edge, the
        # cutter in front of the wall) inside the pocket
        no = -n_in[k]
        o_end = -(ends @ L[:2] + L[2]) / (L[:2] @ no)
        if (support[k] >= params.min_line_support and o_end.min() >= -params.max_line_shift_px
                and o_end.max() <= params.max_line_shift_px + params.max_outward_shift_px):
            seen[k] = True
            lines[k] = L
        inliers[k] = pts[inl]
    # the inlier points of all lines distorted in one call
    keys = sorted(inliers)
    flat = camera.distort_px(np.concatenate([inliers[k] for k in keys])) if keys else None
    edges = [np.zeros((0, 2))] * n
    at = 0
    for k in keys:
        edges[k] = flat[at: at + len(inliers[k])]
        at += len(inliers[k])
    # a line much noisier than the others rests on something else (a lump's outline)
    if seen.sum() >= 3:
        noisy = seen & (scale > 3.0 * np.median(scale[seen]))
        seen &= ~noisy
        lines[noisy] = np.nan
    return lines, seen, edges, support, scale


def _refit_nearest_rise(fit, Ls, ss, ws, prof, base, which, rows, w_all, n_in, offsets,
                        params: FeatureParams):
    """The second pass of :func:`robust_edge_lines` (``edge_innermost > 0``), on the profiles
    whose first point is not an inlier: the rise nearest the fitted line (the innermost rise
    may have been too weak there, or a blemish inside it), so that each line follows one and
    the same rise of a broken edge. Updates ``fit`` in place; returns the lines, scales and
    weights ``(Ls, ss, ws)``."""
    n = len(n_in)
    ks = [f[0] for f in fit]
    lab = np.full(n, -1)
    lab[ks] = np.arange(len(ks))
    redo = lab[which] >= 0
    row_k = {k: rows[w_all == k] for k in ks}
    for e, (k, _, _) in enumerate(fit):
        redo[row_k[k][ws[e] > 0]] = False
    r_idx = np.nonzero(redo)[0]
    if len(r_idx):
        e_r = lab[which[r_idx]]
        Lp, nb = Ls[e_r], -n_in[which[r_idx]]
        o_exp = -(Lp[:, 0] * base[r_idx, 0] + Lp[:, 1] * base[r_idx, 1] + Lp[:, 2]) \
            / (Lp[:, 0] * nb[:, 0] + Lp[:, 1] * nb[:, 1])
        # only rises the first fit would call inliers (Tukey's cut at its scale)
        o2, r2 = _nearest_rise_centroids(np.diff(prof[r_idx], axis=1), offsets[0] + 0.125,
                                         0.25, o_exp, 0.5 * params.edge_innermost,
                                         gate_px=TUKEY_C * ss[e_r])
        rows2 = r_idx[r2]
        pts2 = base[rows2] - o2[:, None] * n_in[which[rows2]]
        w2 = which[rows2]
        grow = [e for e, f in enumerate(fit) if np.any(w2 == f[0])]
        if grow:
            merged = [np.vstack([fit[e][1][ws[e] > 0], pts2[w2 == fit[e][0]]])
                      for e in grow]
            L2, s2, ws2 = tukey_lines(merged, Ls[grow], ss[grow])
            ws = list(ws)
            for i, e in enumerate(grow):
                fit[e] = (fit[e][0], merged[i], fit[e][2])
                Ls[e], ss[e], ws[e] = L2[i], s2[i], ws2[i]
    return Ls, ss, ws

