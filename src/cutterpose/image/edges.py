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
from .params import signed_area

if TYPE_CHECKING:
    from .params import FeatureParams

def fit_line(p: np.ndarray, w: np.ndarray | None = None):
    """Total least squares line: centroid, unit direction, unit normal."""
    if w is None:
        c = p.mean(axis=0)
        q = p - c
        C = q.T @ q
    else:
        c = (w[:, None] * p).sum(axis=0) / w.sum()
        q = p - c
        C = (w[:, None] * q).T @ q
    evals, evecs = np.linalg.eigh(C)
    d = evecs[:, 1]
    n = evecs[:, 0]
    return c, d, n


# ------------------------------------------------------------------------------------------
# lines and corners
def line_from(c, n) -> np.ndarray:
    return np.array([n[0], n[1], -(n @ c)])


def intersect_consecutive(lines: np.ndarray) -> np.ndarray:
    """Corner k = intersection of lines k and k + 1 (cyclic), as (N, 2) points."""
    L = np.asarray(lines, float)
    X = np.cross(L, np.roll(L, -1, axis=0))
    with np.errstate(divide="ignore", invalid="ignore"):
        return X[:, :2] / X[:, 2:3]


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


def _half_max_centroids(g: np.ndarray, o0: float, step: float):
    """Sub-pixel edge position of each profile derivative ``g`` (rows): the centroid of
    ``g - g_max / 2`` over the contiguous run around the maximum where ``g > g_max / 2``.

    For a symmetric point-spread function the derivative of the edge profile is symmetric about
    the edge, and so is its half-maximum run: the centroid is the edge, for narrow (Gaussian) and
    flat-topped (defocus disk) blur alike. Rows whose run touches the window's end, or whose
    maximum is weak (< 0.3 of the median maximum), are rejected.

    Returns
    -------
    offsets : edge positions of the accepted rows; rows : their indices.
    """
    G = g.shape[1]
    j = np.argmax(g, axis=1)
    peak = g[np.arange(len(g)), j]
    half = 0.5 * peak
    idx = np.arange(G)
    below = g <= half[:, None]
    left = np.where(below & (idx < j[:, None]), idx, -1).max(axis=1)
    right = np.where(below & (idx > j[:, None]), idx, G).min(axis=1)
    inside = (idx > left[:, None]) & (idx < right[:, None])
    w = np.where(inside, g - half[:, None], 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        cen = (w * idx).sum(axis=1) / w.sum(axis=1)
    ok = (left >= 0) & (right < G) & (peak > 0) & np.isfinite(cen)
    if ok.any():
        ok &= peak > 0.3 * np.median(peak[ok])
    rows = np.nonzero(ok)[0]
    return o0 + step * cen[rows], rows


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
        o, rows = _half_max_centroids(g, offsets[0] + 0.125, 0.25)
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
    img = image.astype(np.float32)
    n = len(lines_ideal)
    dark, off = np.full(n, np.nan), np.full(n, np.nan)
    for k, (t0, t1, c, d) in enumerate(spans):
        t0, t1 = t0 + 2 * params.refine_trim_px, t1 - 2 * params.refine_trim_px
        if t1 - t0 < 8:
            continue
        L = lines_ideal[k]
        ts = np.arange(t0, t1, 4.0)  # a median profile: every 4th px is plenty
        base = c + ts[:, None] * d
        base = base - ((base @ L[:2]) + L[2])[:, None] * L[:2]
        q = base[:, None, :] - offsets[None, :, None] * inward[k]
        obs = camera.distort_px(q.reshape(-1, 2)) - roi_origin
        prof = cv2.remap(img, obs[:, 0].reshape(q.shape[:2]).astype(np.float32),
                         obs[:, 1].reshape(q.shape[:2]).astype(np.float32), cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_REPLICATE)
        m = gaussian_filter1d(np.median(prof, axis=0), params.refine_sigma_px / step)
        g = np.diff(m)
        go = offsets[:-1] + step / 2
        near = np.abs(go) <= hw
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
        contrast = float(np.median(m[far]) - pocket)
        if contrast <= 0:
            continue
        dark[k] = 1.0 - (np.interp(e + 2 * w, offsets, m) - pocket) / contrast
        off[k] = max(abs(dark[k]) - 0.05, 0.0) * w
    return dark, off


# ------------------------------------------------------------------------------------------
# robust line estimation for the field chain (issue 10)
TUKEY_C = 4.685   #: Tukey's biweight constant: 95 % efficiency under Gaussian residuals
MAD_TO_SIGMA = 1.4826


def tukey_weights(r: np.ndarray, scale: float) -> np.ndarray:
    """Tukey biweight ``(1 - (r / c)^2)^2`` for ``|r| < c = 4.685 scale``, else 0 (a
    redescending M-estimator: points far off the line get no weight at all)."""
    u = np.asarray(r, float) / (TUKEY_C * max(scale, 1e-12))
    return np.where(np.abs(u) < 1.0, (1.0 - u * u) ** 2, 0.0)


def mad_scale(r: np.ndarray, floor: float = 0.0) -> float:
    """Robust standard deviation of residuals about a fitted line: ``1.4826 median |r|``."""
    return max(MAD_TO_SIGMA * float(np.median(np.abs(r))), floor)


def lmeds_line(p: np.ndarray, hypotheses: int = 64, prior: np.ndarray | None = None,
               seed: int = 0, gate_points: np.ndarray | None = None, gate_px: float = np.inf):
    """Least-median-of-squares line through points ``p`` (n, 2): among lines through random
    pairs of points (and ``prior``, a homogeneous line, if given) the one whose median squared
    residual is smallest. Robust to just under 50 % outliers with no threshold (Rousseeuw
    1984). With ``gate_points`` only hypotheses passing within ``gate_px`` of all of them are
    admitted (the ends of the predicted edge: a line must stay near the outline fit). Returns
    the line and its LMedS scale ``1.4826 (1 + 5 / (n - 2)) sqrt(med r^2)``."""
    n = len(p)
    rng = np.random.default_rng(seed)
    i = rng.integers(0, n, hypotheses)
    j = rng.integers(0, n, hypotheses)
    keep = i != j
    a, b = p[i[keep]], p[j[keep]]
    d = b - a
    nrm = np.column_stack([-d[:, 1], d[:, 0]])
    ln = np.linalg.norm(nrm, axis=1)
    ok = ln > 1e-9
    nrm = nrm[ok] / ln[ok, None]
    L = np.column_stack([nrm, -(nrm * a[ok]).sum(axis=1)])
    if prior is not None:
        L = np.vstack([np.asarray(prior, float)[None], L])
    if gate_points is not None:
        L = L[np.abs(gate_points @ L[:, :2].T + L[:, 2]).max(axis=0) <= gate_px]
    if len(L) == 0:
        c, _, nn = fit_line(p)
        return line_from(c, nn), np.inf
    med = np.median((p @ L[:, :2].T + L[:, 2]) ** 2, axis=0)
    k = int(np.argmin(med))
    return L[k], MAD_TO_SIGMA * (1 + 5 / max(n - 2, 1)) * float(np.sqrt(med[k]))


def tukey_line(p: np.ndarray, line0: np.ndarray, scale0: float, floor_px: float = 0.02,
               iterations: int = 20):
    """IRLS total least squares line with Tukey weights from ``line0`` (a robust start); the
    scale is re-estimated from the weighted points' residuals each step (MAD of the current
    inliers, never above the previous scale). Returns line, scale and the final weights."""
    L = np.asarray(line0, float)
    s = max(float(scale0), floor_px)
    w = tukey_weights(p @ L[:2] + L[2], s)
    for _ in range(iterations):
        if np.count_nonzero(w) < 3:
            break
        c, _, nn = fit_line(p, w)
        if nn @ L[:2] < 0:
            nn = -nn
        L1 = line_from(c, nn)
        r = p @ L1[:2] + L1[2]
        s = min(s, mad_scale(r[w > 0], floor_px))
        w = tukey_weights(r, s)
        moved = abs(L1[2] - L[2]) + float(np.linalg.norm(L1[:2] - L[:2])) * 1e3
        L = L1
        if moved < 1e-4:
            break
    return L, s, w


def sample_profiles(img: np.ndarray, roi_origin, camera: Camera, base_ideal: np.ndarray,
                    n_out: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """Grey profiles ``I(distort(q + o n_out))`` for base points ``q`` (T, 2, ideal px) at
    offsets ``o`` (O,), as a (T, O) float32 array (bilinear, on ``img`` whose pixel (0, 0) is
    ``roi_origin``). The distortion is linearised along each short profile (two
    :meth:`Camera.distort_px` calls for T points instead of T x O)."""
    if len(base_ideal) == 0:
        return np.zeros((0, len(offsets)), np.float32)
    n_out = np.broadcast_to(np.asarray(n_out, float), base_ideal.shape)
    o0 = camera.distort_px(base_ideal)
    d1 = camera.distort_px(base_ideal + n_out) - o0
    obs = o0[:, None, :] + offsets[None, :, None] * d1[:, None, :] - np.asarray(roi_origin)
    return cv2.remap(img, obs[..., 0].astype(np.float32), obs[..., 1].astype(np.float32),
                     cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def robust_edge_lines(img: np.ndarray, roi_origin, camera: Camera, pred_ideal: np.ndarray,
                      params: FeatureParams):
    """The 20 lines on their sub-pixel gradient edge points, robustly (field chain).

    ``pred_ideal`` (N, 2): the corners predicted by the outline fit, in holder order; edge
    ``k`` runs from corner ``k`` to ``k + 1``. Along each predicted edge, away from its
    corners by ``corner_trim_px``, a profile every ``refine_step_px`` across
    ``+-refine_half_width_px`` (0.25 px steps, unfiltered image) gives an edge point (centroid
    of the half-maximum run of the dark-to-bright derivative, :func:`_half_max_centroids`).
    Points on slurry, on the cutter's silhouette, on a chip or a highlight are outliers: the
    line starts from the least-median-of-squares line (:func:`lmeds_line`, the predicted line
    among the hypotheses) and is refined by Tukey IRLS with a MAD scale (:func:`tukey_line`).
    A line is *seen* if its inliers cover ``min_line_support`` of the profiled length and it
    stays within ``max_line_shift_px`` of the prediction.

    Returns
    -------
    lines : (N, 3) lines (NaN where not seen); seen : (N,) bool; edge_points_px : per line
    the inlier edge points (observed px); support : (N,) covered fraction; scale_px : (N,)
    the final robust scale.
    """
    n = len(pred_ideal)
    nxt = np.roll(pred_ideal, -1, axis=0)
    sign = np.sign(signed_area(pred_ideal))
    hw = params.refine_half_width_px
    offsets = np.arange(-hw, hw + 1e-9, 0.25)
    lines = np.full((n, 3), np.nan)
    seen = np.zeros(n, bool)
    support = np.zeros(n)
    scale = np.full(n, np.nan)
    edges: list = []
    trim = params.corner_trim_px
    for k in range(n):
        a, b = pred_ideal[k], nxt[k]
        length = float(np.linalg.norm(b - a))
        d = (b - a) / max(length, 1e-9)
        n_in = sign * np.array([-d[1], d[0]])
        ts = np.arange(trim, length - trim + 1e-9, params.refine_step_px)
        if len(ts) < 5:
            edges.append(np.zeros((0, 2)))
            continue
        base = a + ts[:, None] * d
        prof = sample_profiles(img, roi_origin, camera, base, -n_in, offsets)
        if params.refine_sigma_px > 0:
            prof = gaussian_filter1d(prof, params.refine_sigma_px / 0.25, axis=1)
        o, rows = _half_max_centroids(np.diff(prof, axis=1), offsets[0] + 0.125, 0.25)
        pts = base[rows] - o[:, None] * n_in
        if len(pts) < 5:
            edges.append(np.zeros((0, 2)))
            continue
        pred = line_from(a, n_in)
        ends = base[[0, -1]]
        L0, s0 = lmeds_line(pts, prior=pred, seed=k, gate_points=ends,
                            gate_px=params.max_line_shift_px)
        L, s, w = tukey_line(pts, L0, s0)
        inl = w > 0
        support[k] = np.count_nonzero(inl) * params.refine_step_px / max(ts[-1] - ts[0], 1.0)
        scale[k] = s
        # the fitted line's distance to the prediction at both ends of the profiled run
        shift = np.abs(ends @ L[:2] + L[2]).max()
        if support[k] >= params.min_line_support and shift <= params.max_line_shift_px:
            seen[k] = True
            lines[k] = L
        edges.append(camera.distort_px(pts[inl]))
    # a line much noisier than the others rests on something else (a lump's outline)
    if seen.sum() >= 3:
        noisy = seen & (scale > 3.0 * np.median(scale[seen]))
        seen &= ~noisy
        lines[noisy] = np.nan
    return lines, seen, edges, support, scale
