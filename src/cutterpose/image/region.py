"""Region of interest (paper section 2.1, step 1): the holder's face template at the nominal
pose matched on the reduced image by normalised correlation.

Convention:
    ROI ``(u0, v0, u1, v1)`` in full-image pixels, ``u1, v1`` exclusive.
"""

from __future__ import annotations

import threading
from collections import OrderedDict

import cv2
import numpy as np

from ..errors import FeatureError
from ..geometry.camera import Camera
from ..geometry.holder import Holder
from ..geometry.pose import Pose
from .params import FeatureParams
from .preprocessing import reduce_image

_TEMPLATE_CACHE: dict = {}


def _nominal_outlines_px(camera: Camera, holder: Holder, band_mm: float):
    pose = Pose.nominal()
    pocket = camera.project(pose.apply(holder.points_holder_mm))
    lo = holder.corners_mm.min(axis=0) - band_mm
    hi = holder.corners_mm.max(axis=0) + band_mm
    rect = holder.outer_rectangle_mm
    lo = np.maximum(lo, rect.min(axis=0))
    hi = np.minimum(hi, rect.max(axis=0))
    box_mm = np.array([[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]]])
    box = camera.project(pose.apply(np.column_stack([box_mm, np.zeros(4)])))
    return pocket, box


def _template(camera: Camera, holder: Holder, params: FeatureParams):
    key = (repr(camera), holder.corners_mm.tobytes(), holder.outer_length_x_mm,
           holder.outer_width_y_mm, params.roi_downscale, params.roi_band_mm)
    if key in _TEMPLATE_CACHE:
        return _TEMPLATE_CACHE[key]
    pocket, box = _nominal_outlines_px(camera, holder, params.roi_band_mm)
    if not (np.all(np.isfinite(pocket)) and np.all(np.isfinite(box))):
        raise FeatureError("the holder model does not project into this camera at the nominal "
                           "pose")
    s = float(params.roi_downscale)
    origin = np.floor(box.min(axis=0) / s)
    size = np.ceil(box.max(axis=0) / s - origin).astype(int) + 1
    tpl = np.zeros((size[1], size[0]), np.float32)
    shift = 4
    scale = 1 << shift
    # pixel centres: small pixel j covers full pixels [s j - 0.5, s (j + 1) - 0.5)

    def to_small(p):
        return (p + 0.5) / s - 0.5 - origin

    cv2.fillPoly(tpl, [np.rint(to_small(box) * scale).astype(np.int32)], 1.0, cv2.LINE_AA,
                 shift)
    cv2.fillPoly(tpl, [np.rint(to_small(pocket) * scale).astype(np.int32)], 0.0, cv2.LINE_AA,
                 shift)
    out = (tpl, origin.astype(int), pocket)
    _TEMPLATE_CACHE[key] = out
    return out


def find_roi(image: np.ndarray, camera: Camera, holder: Holder, params: FeatureParams,
             small: np.ndarray | None = None) -> tuple[tuple[int, int, int, int], float]:
    """Region of interest holding the whole inside contour.

    A template of the holder's top face at the nominal pose (face bright, pocket dark, a band of
    ``roi_band_mm`` around the pocket) is matched on the reduced image by normalised correlation;
    the ROI is the nominal pocket's bounding box moved by the best match, widened by a margin that
    covers the working range's rotation and scale changes.

    Returns
    -------
    roi : (u0, v0, u1, v1) in full-image pixels, clipped to the image.
    score : the best normalised correlation.

    Raises
    ------
    FeatureError
        No position matches the template well (no holder in the image).
    """
    s = params.roi_downscale
    if small is None:
        small = reduce_image(image, s)
    tpl, origin, pocket = _template(camera, holder, params)
    if tpl.shape[0] > small.shape[0] or tpl.shape[1] > small.shape[1]:
        raise FeatureError("the holder template is larger than the image: check the camera model")
    res = cv2.matchTemplate(small.astype(np.float32), tpl, cv2.TM_CCOEFF_NORMED)
    _, score, _, loc = cv2.minMaxLoc(res)
    if not np.isfinite(score) or score < params.roi_min_score:
        raise FeatureError(f"no holder found: the best template match scores {score:.2f} "
                           f"(< {params.roi_min_score}); is the holder in view?")
    shift_px = (np.array(loc) - origin) * s
    lo = pocket.min(axis=0) + shift_px
    hi = pocket.max(axis=0) + shift_px
    margin = params.roi_margin_frac * (hi - lo).max() + params.roi_margin_px
    h, w = image.shape
    # aligned on the reduced image's grid so that ROI tiles map onto whole reduced pixels
    u0, v0 = (np.maximum(np.floor((lo - margin) / s), 0) * s).astype(int)
    u1 = int(min(np.ceil(hi[0] + margin) + 1, w))
    v1 = int(min(np.ceil(hi[1] + margin) + 1, h))
    return (int(u0), int(v0), u1, v1), float(score)


# ------------------------------------------------------------------------------------------
# field chain (issue 10): the pocket outline matched on gradient orientation
class _Recent(OrderedDict):
    """A bounded cache that forgets its least recently used entries. (Clearing it whole when
    full, as before, rebuilt all 45 coarse templates of an approach's five depths on about
    every other full measurement: ~190 ms of its ~250.) Keys are built by the callers (the
    camera and holder are not hashable, so not ``functools.lru_cache``); a lock, as the
    service tracks its sessions in threads."""

    def __init__(self, maxsize: int):
        super().__init__()
        self.maxsize = int(maxsize)
        self._lock = threading.Lock()

    def recall(self, key):
        """The entry of ``key`` (None when absent), marked as just used."""
        with self._lock:
            if key not in self:
                return None
            self.move_to_end(key)
            return self[key]

    def keep(self, key, value) -> None:
        with self._lock:
            self[key] = value
            self.move_to_end(key)
            while len(self) > self.maxsize:
                self.popitem(last=False)


#: templates are a few 10 kB (the outline's box at 1/8 or 1/16 scale): ~10 MB at most
_OUTLINE_CACHE = _Recent(256)


def _outline_template(camera: Camera, holder: Holder, downscale: int, gamma_deg: float,
                      line_px: int, depth_mm: float = 600.0):
    """Doubled-angle template of the pocket outline at the nominal pose (at ``depth_mm``) turned
    by ``gamma_deg`` about the optical axis, on the image reduced ``downscale`` times: two float32
    channels ``(cos 2 phi, sin 2 phi)`` along the outline (``phi``: the edge normal's angle, a
    ``line_px`` wide band), zero elsewhere; with the template's origin (reduced px), the
    homography plane (mm) -> ideal px of its pose and its number of outline pixels. Cached."""
    key = (repr(camera), holder.corners_mm.tobytes(), int(downscale), round(gamma_deg, 3),
           int(line_px), round(float(depth_mm), 3))
    hit = _OUTLINE_CACHE.recall(key)
    if hit is not None:
        return hit
    s = float(downscale)
    P = holder.points_holder_mm
    pose = Pose.from_euler(0.0, 0.0, gamma_deg, 0.0, 0.0, float(depth_mm))
    ideal = (P @ pose.R.T + pose.t_mm) @ camera.K.T
    ideal = ideal[:, :2] / ideal[:, 2:3]
    H = camera.K @ np.column_stack([pose.R[:, 0], pose.R[:, 1], pose.t_mm])
    # the outline densely in observed px (distortion bends long edges)
    t = np.linspace(0.0, 1.0, 16, endpoint=False)
    nxt = np.roll(ideal, -1, axis=0)
    dense = (ideal[:, None, :] + t[None, :, None] * (nxt - ideal)[:, None, :]).reshape(-1, 2)
    obs = camera.distort_px(np.vstack([dense, dense[:1]]))
    small = (obs + 0.5) / s - 0.5
    origin = np.floor(small.min(axis=0)) - 2
    size = (np.ceil(small.max(axis=0) - origin) + 3).astype(int)
    tpl = np.zeros((size[1], size[0], 2), np.float32)
    q = small - origin
    for a, b in zip(q[:-1], q[1:]):
        d = b - a
        phi = np.arctan2(d[0], -d[1])  # the normal's angle
        val = (float(np.cos(2 * phi)), float(np.sin(2 * phi)))
        cv2.line(tpl, tuple(np.rint(a * 16).astype(int)), tuple(np.rint(b * 16).astype(int)),
                 val, int(line_px), cv2.LINE_8, 4)
    n_on = float(np.count_nonzero(np.abs(tpl).sum(axis=2)))
    out = (tpl, origin.astype(int), H / H[2, 2], n_on)
    _OUTLINE_CACHE.keep(key, out)
    return out


def _percentile(a: np.ndarray, q: float) -> float:
    """``np.percentile(a, q)`` (linear interpolation) from one partition."""
    v = np.ravel(a)
    pos = q / 100.0 * (v.size - 1)
    lo = int(np.floor(pos))
    hi = min(lo + 1, v.size - 1)
    part = np.partition(v, [lo, hi] if hi != lo else [lo])
    return float(part[lo]) + (float(part[hi]) - float(part[lo])) * (pos - lo)


def _orientation_field(img: np.ndarray) -> np.ndarray:
    """Doubled-angle gradient field ``w (cos 2 theta, sin 2 theta)`` (H, W, 2) float32, ``w``
    the gradient magnitude saturated at its 90th percentile."""
    img = cv2.GaussianBlur(img.astype(np.float32), (0, 0), 1.0)
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3)
    m2 = gx * gx + gy * gy
    m = np.sqrt(m2)
    g0 = max(_percentile(m[::2, ::2], 90.0), 1e-3)
    w = np.minimum(m / g0, 1.0) / np.maximum(m2, 1e-12)
    return np.dstack([(gx * gx - gy * gy) * w, 2.0 * gx * gy * w]).astype(np.float32)


#: the coarse image's template spectra are ~0.4 MB each (45 for an approach), the fine
#: windows' ~50 kB: <= ~40 MB
_SPECTRUM_CACHE = _Recent(192)


def _fft_shape(h: int, w: int) -> tuple[int, int]:
    """The transform size of :func:`correlate_templates` for an (h, w) image."""
    from scipy import fft

    return fft.next_fast_len(h), fft.next_fast_len(w, real=True)


def _template_spectrum(t: np.ndarray, shape: tuple) -> np.ndarray:
    """The conjugate spectrum (C, ...) of template ``t`` at transform size ``shape``, cached."""
    from scipy import fft

    key = (id(t), shape)
    hit = _SPECTRUM_CACHE.recall(key)
    if hit is None or hit[0] is not t:   # the template kept in the entry: ids stay unique
        hit = (t, np.conj(fft.rfft2(np.moveaxis(t, -1, 0), s=shape, axes=(1, 2), workers=1)))
        _SPECTRUM_CACHE.keep(key, hit)
    return hit[1]


def correlate_templates(image: np.ndarray, templates: list) -> list:
    """``cv2.matchTemplate(image, t, cv2.TM_CCORR)`` for several multi-channel templates (the
    "valid" cross-correlation, summed over the channels), by FFT (speed, issue 13): the
    image's spectrum once, every template's spectrum computed once per image size and cached
    (the templates themselves are cached per camera, holder and turn), one product and one
    inverse transform per template. Float32 transforms: equal to ``matchTemplate`` to ~1e-6
    of the peak.

    ``image``: (H, W, C) float32; ``templates``: (h_i, w_i, C) float32, no larger than it.
    Returns the (H - h_i + 1, W - w_i + 1) float32 correlation of each."""
    from scipy import fft

    h, w = image.shape[:2]
    shape = _fft_shape(h, w)
    # channels first: contiguous planes for the transforms and the products
    spec_img = fft.rfft2(np.moveaxis(image, -1, 0), s=shape, axes=(1, 2), workers=1)
    out = []
    for t in templates:
        spec_t = _template_spectrum(t, shape)
        prod = spec_img[0] * spec_t[0]
        for ch in range(1, len(spec_img)):
            prod += spec_img[ch] * spec_t[ch]
        c = fft.irfft2(prod, s=shape, workers=1)
        out.append(np.ascontiguousarray(c[: h - t.shape[0] + 1, : w - t.shape[1] + 1],
                                        np.float32))
    return out


def _coarse_templates(camera: Camera, holder: Holder, params: FeatureParams):
    """The coarse stage's (turn, depth) pairs and templates: every turn at every depth (one
    depth, the nominal 600 mm, unless an approach asks more), on the image reduced
    ``2 roi_downscale`` times."""
    gd = [(g, z) for z in params.roi_depths_mm for g in params.roi_gammas_deg]
    return gd, [_outline_template(camera, holder, 2 * int(params.roi_downscale), g, 2, z)
                for g, z in gd]


def prepare_outline_search(camera: Camera, holder: Holder, params: FeatureParams) -> None:
    """Build :func:`match_outline`'s coarse templates and their spectra for ``camera``'s
    frames ahead of the first one (cached per process: ~190 ms for an approach's five depths,
    :func:`~cutterpose.tracking.approach_params`), e.g. in a worker process that will measure
    fall-backs. Nothing for the paper's chain (no outline search)."""
    if params.chain != "field":
        return
    w, h = camera.image_size_px
    s8 = int(params.roi_downscale)
    shape = _fft_shape((h // s8) // 2, (w // s8) // 2)   # match_outline's coarse field
    for t in _coarse_templates(camera, holder, params)[1]:
        _template_spectrum(t[0], shape)


def match_outline(small: np.ndarray, camera: Camera, holder: Holder, params: FeatureParams):
    """Find the pocket from gradient orientations alone (field chain; no dark pocket or dark
    surround needed): the image reduced ``roi_downscale`` times is turned into the doubled-angle
    field ``w (cos 2 theta, sin 2 theta)`` of its gradient (``theta`` its direction, ``w`` the
    magnitude saturated at the 90th percentile), and the outline templates
    (:func:`_outline_template`) are correlated with it, coarse to fine (every turn on the
    image reduced twice more, then the best turn +-1.5 deg). ``cos 2 (theta - phi)`` is 1
    where a gradient lies along the outline's normal, whatever its sign (a bright cutter in a
    dark pocket, a face as bright as its surround), and averages to 0 on texture.

    Returns
    -------
    H : (3, 3) homography holder plane (mm) -> ideal px of the best template moved onto the
        match (a similarity of the nominal pose: the start of the outline search).
    score : mean ``w cos 2 (theta - phi)`` over the template's outline (0 .. 1).

    Raises
    ------
    FeatureError
        The best score is below ``roi_min_edge_score`` (no holder outline in view).
    """
    s8 = int(params.roi_downscale)
    field = _orientation_field(small)
    # coarse: every turn on the image reduced twice more; fine: the best turn +-1.5 deg at
    # the reduced scale, in a window round the coarse match
    coarse = cv2.resize(field, (field.shape[1] // 2, field.shape[0] // 2),
                        interpolation=cv2.INTER_AREA)
    best = None
    gd, tpls = _coarse_templates(camera, holder, params)
    for t in tpls:
        if t[0].shape[0] > coarse.shape[0] or t[0].shape[1] > coarse.shape[1]:
            raise FeatureError("the holder outline is larger than the image: check the camera "
                               "model")
    for (g, z), (_tpl, origin, _H, n_on), res in zip(
            gd, tpls, correlate_templates(coarse, [t[0] for t in tpls])):
        _, sc, _, loc = cv2.minMaxLoc(res)
        sc /= n_on
        if best is None or sc > best[0]:
            best = (sc, g, z, (np.array(loc) - origin) * 2)
    _, g0, z0, shift8 = best
    best = None
    # several depths (an approach): the coarse scale separates them by ~12 %, so the fine
    # stage also tries 4 % either side of the coarse depth (one depth: the nominal only)
    zs = (z0,) if len(params.roi_depths_mm) == 1 else (0.96 * z0, z0, 1.04 * z0)
    for g, z in [(g, z) for z in zs for g in (g0 - 1.5, g0, g0 + 1.5)]:
        tpl, origin, H, n_on = _outline_template(camera, holder, s8, g, params.roi_line_px, z)
        th, tw = tpl.shape[:2]
        c0 = np.rint(shift8 + origin).astype(int) - 4  # window's top-left, reduced px
        x0, y0 = max(c0[0], 0), max(c0[1], 0)
        x1 = min(c0[0] + tw + 8, field.shape[1])
        y1 = min(c0[1] + th + 8, field.shape[0])
        if x1 - x0 < tw or y1 - y0 < th:
            continue
        res = correlate_templates(field[y0:y1, x0:x1], [tpl])[0]
        _, sc, _, loc = cv2.minMaxLoc(res)
        sc /= n_on
        if best is None or sc > best[0]:
            best = (sc, (loc[0] + x0, loc[1] + y0), origin, H)
    if best is None:
        raise FeatureError("no holder found: the pocket outline does not fit in the image")
    score, loc, origin, H = best
    if not np.isfinite(score) or score < params.roi_min_edge_score:
        raise FeatureError(f"no holder found: the pocket outline matches the image's edges at "
                           f"{score:.2f} at best (< {params.roi_min_edge_score}); is the holder "
                           "in view?")
    shift = (np.array(loc, float) - origin) * params.roi_downscale
    T = np.array([[1.0, 0.0, shift[0]], [0.0, 1.0, shift[1]], [0.0, 0.0, 1.0]])
    return T @ H, float(score)
