"""The band of a broken pocket edge, measured across the edge (issue 10: "measure the break").

A rounded or chamfered edge of size ``r`` images as a band between two geometric junctions: where
the break meets the wall (depth ``r`` below the face) and where it meets the face (``r`` out from
the design edge). From the corners alone only the band's innermost rise is seen, and that is the
design polygon moved in depth by ``r`` (docs/notes/edge_model.md, section 3): ``r`` and ``Z``
cannot be told apart. The profile *across* the band holds both junctions, about ``a_s r`` px
apart (4 px per mm at 600 mm), so fitting the edge model's profile
(:func:`cutterpose.image.edge_model.profiles`) to the measured profile gives, per piece of edge,
the radius and where the *design* edge lies in the image. :mod:`cutterpose.solvers.edge_band`
then fits the pose to those design-edge points.

The fit per segment (a third to a half of one edge, ``n_seg`` per edge):

* the measured profile ``y(w)`` is the median, over ``positions`` normals spread along the
  segment, of the image sampled (bilinear) every ``step_px`` along the predicted edge's outward
  normal; normals whose profile departs from the median (slurry, a chip, the cutter's
  silhouette) are dropped before a second median;
* the model ``m(w; r, look)`` is the edge model's blurred profile (its design edge at ``w = 0``)
  for a shape (fillet or 45 deg chamfer) and a photometric variant (``LOOK_VARIANTS``);
* ``y(w) ~ a + b m(w - shift)``, ``b > 0``: the grey offset and gain are solved in closed form,
  ``(r, shift)`` on a grid (coarse over the whole range on a 0.4 px grid, then fine round the
  best on 0.2 px and 9 radii with a parabola), the look is shared by every segment of the
  image (one material, one light) and chosen by the trimmed sum of the segments' costs;
* each segment's shift variance with its radius free, from the Hessian of the cost round its
  minimum (:func:`_shift_variance`): the pose fit's weights;
* a look calibrated in the cell on a reference holder at known poses (:class:`BandLooks`,
  :mod:`cutterpose.calibration.edge_look`) replaces the generic variants: one photometry for
  both shapes, and per shape a calibrated design-edge offset added to the fitted shifts.

The result per segment: the design edge's point ``q + shift n`` (ideal px), the radius, the
residual RMS, the gain (contrast), and the same for the other plausible looks (their spread is
the edge model's share of the error budget).

Convention:
    Holder frame and pose of :mod:`cutterpose.geometry.pose` (``x_cam = R x_holder + t``, mm);
    ``*_ideal_px`` ideal (undistorted) pixels of ``camera.K``; ``w`` and ``shift`` in px along
    the edge's outward image normal (away from the pocket); radii in mm. Segments are ordered
    edge by edge (holder order), ``n_seg`` per edge.

References:
    Seed paper, section 2.1; the same group's follow-up (Sensors 2023, 23(3), 1536) on the
    rounded-edge profile under strong and weak light; :mod:`cutterpose.image.edge_model` for the
    radiometry.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field, replace

import cv2
import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from ..errors import InputError
from ..geometry.camera import Camera
from ..geometry.holder import Holder
from . import edge_model as em

__all__ = ["BandProfiles", "BandFit", "BandLooks", "DesignEdgeOffsets", "sample_band",
           "fit_band", "band_looks", "profile_costs", "model_grid_px", "view_lean",
           "CAL_RADII_MM", "scan_cost"]

#: the radii the coarse scan tries (mm) and the fine step
COARSE_RADII_MM = np.array([0.0, 0.25, 0.5, 0.75, 1.0, 1.25, 1.5, 2.0, 2.5, 3.0, 3.5, 4.0, 4.5,
                            5.0, 5.75, 6.5])
#: the fine scan's radius step: 0.05 mm up to 2 mm (where the coarse grid is 0.25 mm), 0.1 mm
#: beyond (coarse 0.5 mm); FINE_RADII radii round the coarse best (+-0.2 mm: the coarse step's
#: half and a node either side; 13 (+-0.3 mm) cost a third more and gave the same poses within
#: their scatter, eighth session)
FINE_STEP_MM = 0.05
FINE_RADII = 9
#: the coarse shift scan: +- this many px (the start may be a few mm off in depth) in steps of
COARSE_SHIFT_PX = 6.0
COARSE_SHIFT_STEP_PX = 0.4
#: fine scan: +- 0.6 px in STEP_PX round the coarse best, then a parabola
FINE_SHIFT_STEPS = 3
#: the profile step (px): samples and model grid alike, so that a shift is an index offset
STEP_PX = 0.2
#: lens blurs tried for the chosen variant (px, Gaussian std)
BLURS_PX = (0.6, 0.9, 1.2)
#: a look is plausible (its poses enter the budget's model spread) when the best total cost is
#: at least this fraction of its own (the same margin as dm+r's shape choice)
PLAUSIBLE = 0.7
#: at most this many plausible looks (the most likely) are kept, and only those whose
#: likelihood weight relative to the best (``(C_best / C)^(n / 2)``, the budget's) is at least
MAX_PLAUSIBLE = 3
MIN_LOOK_WEIGHT = 0.01
#: the radii over which :func:`profile_costs` profiles each segment's radius out (mm): the fine
#: scan's steps (0.05 mm below 2 mm, 0.1 mm above) over the coarse scan's range
CAL_RADII_MM = np.r_[np.arange(0.0, 2.0, FINE_STEP_MM), np.arange(2.0, 6.5 + 1e-9,
                                                                    2 * FINE_STEP_MM)]


#: how far beyond its reference poses' depths a calibration's measured offsets are trusted,
#: and beyond its reference breaks' radii (mm: the coarse scan's step)
RANGE_MARGIN = 0.05
RADIUS_MARGIN_MM = 0.25


@dataclass(frozen=True)
class DesignEdgeOffsets:
    """Where a look calibrated in the cell still puts the design edge, measured at the known
    poses of its reference images (:func:`cutterpose.calibration.edge_look.calibrate_offsets`),
    per shape (``(shape, value)`` pairs).

    ``offset_mm``: the uniform outward offset (mm in the face plane) and ``depth_mm`` the depth
    ``d`` below the face at which the located design edge behaves: a point ``d`` below the face
    images like the face point ``d tan(theta)`` outwards (``tan(theta)`` the segment's
    :func:`view_lean`), so a segment's offset is ``offset_mm - d tan(theta)`` (:meth:`offset`);
    ``scatter_mm``: how far one image's design edge may still be off (1 sigma, the offsets'
    scatter over the reference images); ``cov_mm2``: the covariance of the calibrated (offset,
    depth) (their own uncertainty, correlated through the segments' mean lean);
    ``distance_range_mm`` and ``radius_range_mm``: the reference poses' depths and, per shape,
    the reference breaks' median radii: where the measured scatter vouches (:meth:`covers`).
    A falsy instance: no calibrated offsets.
    """

    offset_mm: tuple[tuple[str, float], ...] = ()
    scatter_mm: tuple[tuple[str, float], ...] = ()
    depth_mm: tuple[tuple[str, float], ...] = ()
    cov_mm2: tuple[tuple[str, tuple[tuple[float, float], tuple[float, float]]], ...] = ()
    distance_range_mm: tuple[float, float] | None = None
    radius_range_mm: tuple[tuple[str, tuple[float, float]], ...] = ()

    def __bool__(self) -> bool:
        return bool(self.offset_mm or self.depth_mm)

    def offset(self, shape: str, lean=0.0):
        """The calibrated design-edge offset of ``shape`` (mm outwards; 0 when not calibrated)
        at segments of view lean ``lean`` (:func:`view_lean`; scalar or (S,))."""
        return (dict(self.offset_mm).get(shape, 0.0)
                - dict(self.depth_mm).get(shape, 0.0) * np.asarray(lean, float))

    def sd(self, shape: str) -> tuple[float, float]:
        """1-sigma of the calibrated (offset, depth) of ``shape`` (mm; 0 when not calibrated)."""
        c = dict(self.cov_mm2).get(shape)
        if c is None:
            return 0.0, 0.0
        return (math.sqrt(max(c[0][0], 0.0)), math.sqrt(max(c[1][1], 0.0)))

    def covers(self, z_mm: float, shape: str | None = None,
               radius_mm: float | None = None) -> bool:
        """Whether a pose at depth ``z_mm`` lies where the offsets were measured (the reference
        poses' range widened by :data:`RANGE_MARGIN`), and a break of ``shape`` with median
        radius ``radius_mm`` is like the reference breaks (their range, +-
        :data:`RADIUS_MARGIN_MM`): the blur, the pixels per mm and the view change with the
        distance (on an approach from 900 mm the calibrated Z error drifts by ~0.4 mm), and a
        new holder's calibration applied to a sharp edge is worse than the generic looks."""
        if self.distance_range_mm is None:
            return False
        lo, hi = self.distance_range_mm
        if not lo * (1 - RANGE_MARGIN) <= z_mm <= hi * (1 + RANGE_MARGIN):
            return False
        rr = dict(self.radius_range_mm).get(shape) if shape is not None else None
        if rr is None or radius_mm is None:
            return True
        return rr[0] - RADIUS_MARGIN_MM <= radius_mm <= rr[1] + RADIUS_MARGIN_MM


@dataclass(frozen=True)
class BandLooks:
    """Photometric candidates calibrated in the cell (:mod:`cutterpose.calibration.edge_look`)
    in place of the generic :func:`band_looks`.

    ``look``: the calibrated photometry (its ``shape`` is replaced by each shape fitted; the
    shape is still chosen per image by the profiles' cost, the blur among ``blurs_px``);
    ``variants``: looks round it (the calibration's uncertainty) that are never chosen, only
    fitted for the error budget's edge-model term, each weighted by its relative likelihood as
    the generic plausible looks are; ``offsets``: where the look still puts the design edge
    (:class:`DesignEdgeOffsets`), added to every fitted shift and in the budget.
    """

    look: em.EdgeLook
    variants: tuple[em.EdgeLook, ...] = ()
    blurs_px: tuple[float, ...] = BLURS_PX
    offsets: DesignEdgeOffsets = DesignEdgeOffsets()

    def for_shape(self, shape: str) -> em.EdgeLook:
        return replace(self.look, shape=shape, profile_sigma_px=0.0)


def band_looks(shapes=("round", "chamfer")) -> list[em.EdgeLook]:
    """The photometric candidates: every shape x ``LOOK_VARIANTS`` at 0.9 px blur (the sampling
    is direct: no profile smoothing)."""
    out = []
    for s in shapes:
        for lk in em.LOOK_VARIANTS:
            lk = replace(lk, shape=s, blur_sigma_px=0.9, profile_sigma_px=0.0,
                         ring_radius_mm=0.0)
            if lk not in out:       # the blur variant is the nominal look here
                out.append(lk)
    return out


@dataclass
class BandProfiles:
    """Profiles across the edges (module doc).

    Attributes
    ----------
    w_px : (G,) sample offsets along the outward normal (px; 0 = the predicted design edge).
    values : (S, G) robust profile of each segment (grey levels), NaN where not sampled.
    edge, frac : (S,) the segment's edge (holder order) and centre as a fraction of the edge.
    points_ideal_px : (S, 2) predicted design-edge point at the segment centre.
    normals_ideal : (S, 2) unit outward image normal there.
    points_holder_mm : (S, 3) the same point on the holder (``Z = 0``).
    used : (S,) normals kept for the median; valid : (S,) enough of them.
    px_per_mm : (S,) image displacement (px) of 1 mm outwards in the face plane (``a_s``).
    """

    w_px: np.ndarray
    values: np.ndarray
    edge: np.ndarray
    frac: np.ndarray
    points_ideal_px: np.ndarray
    normals_ideal: np.ndarray
    points_holder_mm: np.ndarray
    used: np.ndarray
    valid: np.ndarray
    px_per_mm: np.ndarray


def _project(R, t, K, P):
    X = P @ R.T + t
    return (X[..., :2] / X[..., 2:]) @ K[:2, :2].T + K[:2, 2]


def sample_band(image: np.ndarray, camera: Camera, holder: Holder, R_cam_holder,
                t_cam_holder_mm, edges_seen=None, n_seg: int = 2, positions: int = 20,
                step_px: float = STEP_PX, inner_px: float = 10.0, r_max_mm: float = 6.5,
                trim: float = 0.12) -> BandProfiles:
    """Sample every edge's band at the pose ``(R, t)`` (module doc).

    Parameters
    ----------
    image : (H, W) grey image (uint8 or float), observed pixels.
    edges_seen : (N,) bool, edges to sample (default all).
    trim : fraction of each edge left out at either end (the corners' neighbourhood).
    """
    img = np.asarray(image)
    if img.ndim != 2:
        raise InputError("sample_band needs a grey image")
    R = np.asarray(R_cam_holder, float)
    t = np.asarray(t_cam_holder_mm, float).reshape(3)
    K = camera.K
    c = np.asarray(holder.corners_mm, float)
    n = len(c)
    seen = np.ones(n, bool) if edges_seen is None else np.asarray(edges_seen, bool)
    nxt = np.roll(c, -1, axis=0)
    d = (nxt - c) / np.linalg.norm(nxt - c, axis=1, keepdims=True)
    o = holder.edge_normals
    span = (1 - 2 * trim) / n_seg
    seg_edge = np.repeat(np.arange(n), n_seg)
    j = np.tile(np.arange(n_seg), n)
    lo = trim + j * span
    frac_c = lo + 0.5 * span
    f = lo[:, None] + span * (np.arange(positions) + 0.5)[None, :] / positions   # (S, P)
    P2 = c[seg_edge][:, None, :] + f[..., None] * (nxt - c)[seg_edge][:, None, :]
    P3 = np.concatenate([P2, np.zeros(P2.shape[:2] + (1,))], axis=-1)
    q = _project(R, t, K, P3)                                                  # (S, P, 2)
    Po = P3.copy()
    Po[..., :2] += o[seg_edge][:, None, :]
    qo = _project(R, t, K, Po)
    tang = _project(R, t, K, P3 + np.concatenate([d[seg_edge], np.zeros((len(seg_edge), 1))],
                                                 axis=1)[:, None, :]) - q
    nrm = np.stack([-tang[..., 1], tang[..., 0]], axis=-1)
    nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
    nrm *= np.sign(np.sum(nrm * (qo - q), axis=-1))[..., None]
    a_s_seg = np.linalg.norm(qo - q, axis=-1).mean(axis=1)
    w = np.arange(-inner_px, a_s_seg.max() * r_max_mm + 8.0 + step_px / 2, step_px)
    # each normal is a straight line in ideal pixels and a gently curved one in observed
    # pixels: the distortion at its two ends and middle, then the parabola through them
    # (within ~1e-6 px of distorting every sample over the band's ~50 px)
    ends = _distorted_normals(camera, q, nrm, w)
    # only the samples' bounding box is converted to float (the image is 12 MP, the band a
    # few percent of it; the parabolas bulge < 0.1 px past their ends); outside the image the
    # samples are NaN
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)          # all NaN: no box
        box = [(np.nanmin(ends[..., i]), np.nanmax(ends[..., i])) for i in (0, 1)]
    if not np.all(np.isfinite(box)):
        box = [(0.0, 0.0), (0.0, 0.0)]
    x0, y0 = (int(np.clip(np.floor(b[0]) - 2, 0, m)) for b, m in zip(box, img.shape[::-1]))
    x1, y1 = (int(np.clip(np.ceil(b[1]) + 3, 0, m)) for b, m in zip(box, img.shape[::-1]))
    crop = img[y0:max(y1, y0 + 1), x0:max(x1, x0 + 1)].astype(np.float32)
    if y1 <= y0 or x1 <= x0:
        crop[:] = np.nan
    mx, my = _along_normals(ends, w, (x0, y0))
    vals = cv2.remap(crop, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                     borderValue=np.nan)
    vals = vals.reshape(q.shape[:2] + (len(w),))
    vals[~seen[seg_edge]] = np.nan
    # edges not seen are all NaN: their medians are NaN (and marked invalid below)
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        med = _median_rows(vals)
        dev = np.sqrt(np.nanmean((vals - med[:, None, :]) ** 2, axis=2))     # (S, P)
        ref = np.nanmedian(dev, axis=1, keepdims=True)
        keep = np.isfinite(dev) & (dev <= 3.0 * np.maximum(ref, 1.0))
        kept = np.where(keep[..., None], vals, np.nan)
        prof = _median_rows(kept)
    used = keep.sum(axis=1)
    valid = seen[seg_edge] & (used >= max(4, positions // 3)) & np.isfinite(prof).all(axis=1)
    return BandProfiles(w, prof, seg_edge, frac_c, q.mean(axis=1), nrm.mean(axis=1),
                        np.concatenate([P2.mean(axis=1), np.zeros((len(j), 1))], axis=1),
                        used, valid, a_s_seg)


def _distorted_normals(camera: Camera, q, nrm, w) -> np.ndarray:
    """(S, P, 3, 2) observed pixels of each normal's first, middle and last sample.

    A normal is a straight line in ideal pixels and a gently curved one in observed pixels:
    the parabola through these three points (:func:`_along_normals`) stays within ~1e-4 px of
    distorting every sample over the band's ~50 px, at a fraction of the cost."""
    w3 = np.array([w[0], 0.5 * (w[0] + w[-1]), w[-1]])
    pts = q[:, :, None, :] + w3[None, None, :, None] * nrm[:, :, None, :]
    return camera.distort_px(pts.reshape(-1, 2)).reshape(q.shape[:2] + (3, 2))


def _along_normals(ends: np.ndarray, w: np.ndarray, origin_px=(0, 0)):
    """(x, y) float32 maps (S P, G) of every sample, relative to ``origin_px``, on the
    parabolas through ``ends`` (:func:`_distorted_normals`); ``w`` equally spaced."""
    u = ((w - w[0]) / (w[-1] - w[0])).astype(np.float32)                   # 0 .. 1
    maps = []
    for i, o in enumerate(origin_px):
        e0, e1, e2 = (ends[:, :, k, i].reshape(-1, 1) for k in range(3))
        d1, d2 = e1 - e0, e2 - 2 * e1 + e0
        maps.append(((e0 - o).astype(np.float32) + u * (2 * d1 - d2).astype(np.float32))
                    + (u * u) * (2 * d2).astype(np.float32))
    return maps[0], maps[1]


def _median_rows(v: np.ndarray) -> np.ndarray:
    """NaN-median over axis 1 of (S, P, G), NaN where a column has no number.

    From one sort (several times faster than np.nanmedian and np.median's partition along a
    middle axis): NaN sort last, so a column's median sits at its count of numbers."""
    srt = np.sort(v, axis=1)
    P = v.shape[1]
    cnt = np.count_nonzero(~np.isnan(v), axis=1)[:, None, :]                 # (S, 1, G)
    lo = np.take_along_axis(srt, np.clip((cnt - 1) // 2, 0, P - 1), axis=1)[:, 0]
    hi = np.take_along_axis(srt, np.clip(cnt // 2, 0, P - 1), axis=1)[:, 0]
    out = 0.5 * (lo + hi)
    out[cnt[:, 0] == 0] = np.nan
    return out


@dataclass
class LookFit:
    """One look's fit of every segment: radius (mm), shift (px), cost (grey^2), gain, RMS."""

    look: em.EdgeLook
    radius_mm: np.ndarray
    shift_px: np.ndarray
    cost: np.ndarray
    gain: np.ndarray
    rms: np.ndarray
    total: float = np.inf
    #: (S,) variance of the shift (px^2) with the radius free (fine scan; inf: no information)
    shift_var_px2: np.ndarray | None = None

    def moved(self, offset_mm, px_per_mm) -> LookFit:
        """The same fit with every design-edge point moved outwards by ``offset_mm`` (in the
        face plane; ``px_per_mm`` per segment)."""
        return replace(self, shift_px=self.shift_px + offset_mm * np.asarray(px_per_mm, float))


@dataclass
class BandFit:
    """The chosen look's fit and the other plausible looks' (module doc)."""

    best: LookFit
    plausible: list = field(default_factory=list)
    profiles: BandProfiles | None = None

    @property
    def radius_median_mm(self) -> float:
        """The chosen look's median radius over the sampled segments (mm; NaN without any)."""
        r = self.best.radius_mm[self.profiles.valid & np.isfinite(self.best.radius_mm)]
        return float(np.median(r)) if len(r) else math.nan

    def design_points_px(self, lf: LookFit | None = None) -> np.ndarray:
        lf = lf or self.best
        p = self.profiles
        return p.points_ideal_px + lf.shift_px[:, None] * p.normals_ideal


def model_grid_px(bp: BandProfiles) -> tuple[float, float]:
    """The model profiles' extent (px) for the samples of ``bp``: the samples, the shifts
    scanned (<= COARSE_SHIFT_PX + a fine step) and the blur's reach (<= 7 px) either side."""
    return float(bp.w_px[0]) - 14.0, float(bp.w_px[-1]) + 14.0


class _ModelBank:
    """The edge model at one pose for the band fit: each look's radius- and blur-free
    cross-section (:func:`~cutterpose.image.edge_model.cross_section`) is computed once and
    shared by its scans, blurs and radii; the looks of one shape are computed together
    (:func:`~cutterpose.image.edge_model.cross_sections`)."""

    def __init__(self, view: em.EdgeView, grid_px: tuple[float, float]):
        self.view = view
        self.grid_px = grid_px
        self._sections: dict = {}

    @staticmethod
    def _key(look: em.EdgeLook) -> em.EdgeLook:
        return replace(look, blur_sigma_px=0.0, profile_sigma_px=0.0)

    def sections(self, looks) -> em.CrossSection:
        """The looks' cross-sections stacked (one shape), the missing ones computed at once."""
        keys = [self._key(lk) for lk in looks]
        missing = list(dict.fromkeys(k for k in keys if k not in self._sections))
        if missing:
            cs = em.cross_sections(self.view, missing)
            for i, k in enumerate(missing):
                self._sections[k] = em.CrossSection(cs.F[i], cs.w_end, cs.face[i],
                                                    cs.beyond[i])
        got = [self._sections[k] for k in keys]
        return em.CrossSection(np.stack([c.F for c in got]), got[0].w_end,
                               np.stack([c.face for c in got]),
                               np.stack([c.beyond for c in got]))

    def section(self, look: em.EdgeLook) -> em.CrossSection:
        key = self._key(look)
        if key not in self._sections:
            self.sections([look])
        return self._sections[key]

    def profiles(self, radius_mm, looks, step_px: float):
        """(w0, [(N, 2, M, G0) per look]) for looks that differ only by their blur."""
        return em.blurred_profiles(radius_mm, self.view, self.section(looks[0]),
                                   [(lk.blur_sigma_px, lk.profile_sigma_px) for lk in looks],
                                   self.grid_px, step_px)

    def profiles_looks(self, radius_mm, looks, step_px: float):
        """(w0, (L, N, 2, M, G0)) for any looks; ``radius_mm`` (M,), (N, 2, M) or per look
        (L, N, 2, M). Looks that differ only by their blur at shared radii share one raw
        profile; the rest are computed a shape at a time."""
        looks = list(looks)
        r = np.asarray(radius_mm, float)
        per_look = r.ndim == 4
        if not per_look and len({self._key(lk) for lk in looks}) == 1:
            w0, bls = self.profiles(r, looks, step_px)
            return w0, np.stack(bls)
        out = [None] * len(looks)
        w0 = None
        for shape in dict.fromkeys(lk.shape for lk in looks):
            idx = [i for i, lk in enumerate(looks) if lk.shape == shape]
            grp = [looks[i] for i in idx]
            w0, bls = em.blurred_profiles(r[idx] if per_look else r, self.view,
                                          self.sections(grp),
                                          [(lk.blur_sigma_px, lk.profile_sigma_px)
                                           for lk in grp], self.grid_px, step_px)
            for i, b in zip(idx, bls):
                out[i] = b
        return w0, np.stack(out)


def _along_segments(bl: np.ndarray, edge: np.ndarray, frac: np.ndarray) -> np.ndarray:
    """(S, M, G0) model profiles of segments from the edge ends' ``bl`` (N, 2, M, G0): linear
    between the edge's first end (corner ``k``, side 1) and its last (corner ``k + 1``,
    side 0) at the segment's centre ``frac``. With ``bl`` (L, N, 2, M, G0) of L looks:
    (S, L, M, G0)."""
    if bl.ndim == 5:
        bl = np.moveaxis(bl, 0, 2)                                # (N, 2, L, M, G0)
    n = bl.shape[0]
    f = frac.reshape((-1,) + (1,) * (bl.ndim - 2)).astype(np.float32)
    return (1 - f) * bl[edge, 1] + f * bl[(edge + 1) % n, 0]


def view_lean(view: em.EdgeView, edge: np.ndarray, frac: np.ndarray) -> np.ndarray:
    """(S,) ``tan(theta)`` of each segment: the lean of its direction to the camera across the
    edge, outwards positive (``v_o / -v_z``, linear between the edge's ends as the segments'
    profiles are, :func:`_along_segments`).

    Convention:
        Holder frame ``+Z`` away from the camera (``v_z < 0`` for a face the camera sees);
        ``o`` the edge's outward normal in the face plane. A point ``d`` below the face on the
        design edge images like the face point ``d tan(theta)`` outwards of it.
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(view.v_z < 0, view.v_o / -view.v_z, 0.0)              # (N, 2)
    n = t.shape[0]
    return (1 - frac) * t[edge, 1] + frac * t[(edge + 1) % n, 0]


def scan_cost(Y, models, m0, w_idx, shifts_idx, dtype=np.float64):
    """Cost of ``Y ~ a + b model(w - shift)`` for every segment, radius and shift.

    Y : (S, G) measured; models : (S, M, G0); w_idx : (G,) consecutive sample offsets in model
    steps; shifts_idx : (S, H) or (H,) shifts in model steps. Returns cost, gain (S, M, H).

    With ``Yc = Y - mean(Y)`` and the model window ``m`` at a shift, the least-squares gain is
    ``b = <m, Yc> / |m - mean(m)|^2`` and the cost ``|Yc|^2 - b <m, Yc>``. The three window
    products (``<m, Yc>``, ``sum m``, ``sum m^2``) of every radius and shift are two matrix
    products per segment: the model rows (only the columns some window covers) times a matrix
    whose column ``h`` holds ``Yc``, or ones, at shift ``h``'s window (its (S, G0, 2 H) is
    small; the windows themselves, (S, H, M, G), would be copied).

    ``dtype``: of the products. The cost is a small difference of large sums (a good fit
    leaves ~1e-3 of ``|Yc|^2``): float32 products leave it to ~1e-3 of itself, and so leave
    radii and shifts whose costs are that close (as often on a clean edge) to the summation
    order. float32 only for a scan whose minima :func:`_exact_minima` settles in float64.
    """
    S, G = Y.shape
    M, G0 = models.shape[1:]
    sh = np.asarray(shifts_idx)
    if sh.ndim == 1:
        sh = np.broadcast_to(sh, (S, len(sh)))
    H = sh.shape[1]
    if np.any(np.diff(w_idx) != 1):
        raise ValueError("scan_cost: the samples must be consecutive model steps")
    start = m0 + int(w_idx[0]) - sh                                         # (S, H)
    inside = (start >= 0) & (start <= G0 - G)
    start = np.clip(start, 0, G0 - G)
    lo, hi = int(start.min()), int(start.max()) + G
    Yc = Y - Y.mean(axis=-1, keepdims=True)
    # a constant per model row changes neither the gain nor the cost: taking each row's mean
    # (over the columns used) out keeps the window sums clear of cancellation
    mf = np.asarray(models)[:, :, lo:hi].astype(dtype)
    mf -= mf.mean(axis=-1, keepdims=True)
    Gw = hi - lo
    # row h of Bt: Yc (then ones) from column start - lo on, zeros elsewhere: windows of
    # G zeros, Yc, Gw zeros (a view), each row one contiguous copy
    k = G - (start - lo)                                                   # (S, H)
    pad = np.zeros((S, 2 * G + Gw), dtype)
    pad[:, G:2 * G] = Yc
    ones = np.zeros(2 * G + Gw, dtype)
    ones[G:2 * G] = 1.0
    Bt = np.concatenate([sliding_window_view(pad, Gw, axis=-1)[np.arange(S)[:, None], k],
                         sliding_window_view(ones, Gw)[k]], axis=1)         # (S, 2 H, Gw)
    prod = np.matmul(mf, Bt.transpose(0, 2, 1))                            # (S, M, 2 H)
    s2 = np.matmul(np.square(mf), Bt[:, H:].transpose(0, 2, 1))
    num, s1 = prod[..., :H], prod[..., H:]
    den = s2 - s1 * s1 / G
    gain = num / np.maximum(den, 1e-12)
    # a residual sum of squares; rounding can leave a perfect fit a hair below 0
    cost = np.maximum(np.sum(Yc * Yc, axis=-1)[:, None, None] - gain * num, 0.0)
    ok = (gain > 0) & inside[:, None, :]
    return np.where(ok, cost, np.inf), gain


#: a float32 scan's cells within this fraction of ``|Yc|^2`` of a minimum are costed again in
#: float64 (its error is ~1e-6 of ``|Yc|^2``: ten times that)
EXACT_MARGIN = 1e-5


def _exact_minima(Y, models, m0, w_idx, shifts_idx, cost, gain, groups: int):
    """The minimum of each segment's scan in each of ``groups`` equal parts of its rows
    (``cost``, ``gain`` (S, groups * M, H) from a float32 :func:`scan_cost`), the near-ties (within
    :data:`EXACT_MARGIN` of ``|Yc|^2``) costed again in float64: the minimum's flat index over
    (M, H), its cost and gain, (S, groups) each, as a float64 scan finds them (the first of
    equal costs), at a float32 scan's price.
    """
    S, G = Y.shape
    sh = np.asarray(shifts_idx)
    sh = np.broadcast_to(sh, (S, sh.shape[-1])) if sh.ndim == 1 else sh
    H = sh.shape[1]
    flat = cost.reshape(S, groups, -1)                                      # (S, L, M H)
    idx = np.argmin(flat, axis=2)
    out_c = np.take_along_axis(flat, idx[..., None], 2)[..., 0].astype(np.float64)
    out_g = np.take_along_axis(gain.reshape(S, groups, -1), idx[..., None], 2)[..., 0].astype(
        np.float64)
    Yc = Y - Y.mean(axis=-1, keepdims=True)
    syy = np.sum(Yc * Yc, axis=-1)
    near = np.isfinite(flat) & (flat <= out_c[..., None] + EXACT_MARGIN * syy[:, None, None])
    s_i, l_i, c_i = np.nonzero(near)                  # C order: each (s, l) by flat index
    m_i, h_i = np.divmod(c_i, H)
    start = m0 + int(w_idx[0]) - sh[s_i, h_i]
    rows = models[s_i, l_i * (models.shape[1] // groups) + m_i]             # (n, G0)
    win = np.take_along_axis(rows, start[:, None] + np.arange(G), axis=1).astype(np.float64)
    win -= win.mean(axis=1, keepdims=True)
    num = np.einsum("ng,ng->n", win, Yc[s_i])
    g = num / np.maximum(np.einsum("ng,ng->n", win, win), 1e-12)
    c = np.where(g > 0, np.maximum(syy[s_i] - g * num, 0.0), np.inf)
    key = s_i * groups + l_i
    best = np.full(S * groups, np.inf)
    np.minimum.at(best, key, c)
    win_k = np.flatnonzero((c == best[key]) & np.isfinite(c))
    keys, first = np.unique(key[win_k], return_index=True)
    k = win_k[first]
    idx.flat[keys], out_c.flat[keys], out_g.flat[keys] = c_i[k], c[k], g[k]
    return idx, out_c, out_g


def _fit_looks(bp: BandProfiles, bank: _ModelBank, looks, coarse=None,
               shift_range_px: float = COARSE_SHIFT_PX) -> list[LookFit]:
    """Coarse scan of every look (or, given ``coarse``, the fine scan round it: one
    :class:`LookFit` for all the looks, or one per look): one :class:`LookFit` per look.
    All the looks are scanned together (their model profiles in one pass, one window scan)."""
    looks = list(looks)
    L = len(looks)
    h = STEP_PX
    S = len(bp.edge)
    Y = np.where(bp.valid[:, None], bp.values, 0.0)
    G = len(bp.w_px)
    ar = np.arange(S)
    if coarse is None:
        # every second sample on a model grid of twice the step: the coarse scan needs no more
        hc = 2 * h
        radii = COARSE_RADII_MM
        w0, bl = bank.profiles_looks(radii, looks, hc)                     # (L, N, 2, M, G0)
        M = len(radii)
        m0 = int(round(-w0[0] / hc))
        keep = slice(0, None, 2)
        w_idx = np.rint(bp.w_px[keep] / hc).astype(int)
        st = max(1, int(round(COARSE_SHIFT_STEP_PX / hc)))
        k = int(round(shift_range_px / COARSE_SHIFT_STEP_PX))
        shifts = st * np.arange(-k, k + 1)
        models = _along_segments(bl, bp.edge, bp.frac).reshape(S, L * M, -1)
        # float32 products, the near-ties settled in float64: the coarse scan is the band
        # fit's largest (S, L M, H), and only its minima are used
        cost, gain = scan_cost(Y[:, keep], models, m0, w_idx, shifts, np.float32)
        jb, c, g = _exact_minima(Y[:, keep], models, m0, w_idx, shifts, cost, gain, L)
        mi, hi = np.unravel_index(jb, (M, len(shifts)))                    # (S, L) each
        c = c * (G / len(w_idx))
        return [_look_fit(bp, look, radii[mi[:, i]], shifts[hi[:, i]] * hc, c[:, i], g[:, i],
                          np.full(S, np.nan)) for i, look in enumerate(looks)]
    # per-segment radius windows round the coarse radius; the n_seg segments of an edge share
    # its two ends, each end's model runs for every segment index's window at once
    coarse = list(coarse) if isinstance(coarse, (list, tuple)) else [coarse] * L
    shared = all(c is coarse[0] for c in coarse)
    nr = FINE_RADII
    n = bank.view.a_s.shape[0]
    n_seg = S // n
    cr = np.stack([c.radius_mm for c in coarse])                              # (L, S)
    step = np.where(cr < 2.0, FINE_STEP_MM, 2 * FINE_STEP_MM)[..., None]
    rad_seg = np.clip(cr[..., None] - step * (nr // 2), 0, None) + step * np.arange(nr)
    end1 = rad_seg.reshape(L, n, n_seg * nr)                                  # edge k's window
    per_end = np.stack([np.roll(end1, 1, axis=1), end1], axis=2)              # (L, N, 2, .)
    w0, bl = bank.profiles_looks(per_end[0] if shared else per_end, looks, h)
    m0 = int(round(-w0[0] / h))
    bl = bl.reshape(bl.shape[:3] + (n_seg, nr, -1))                         # (L, N, 2, j, r, G0)
    jseg = ar % n_seg
    f = bp.frac.astype(np.float32)[None, :, None, None]
    models = ((1 - f) * bl[:, bp.edge, 1, jseg]
              + f * bl[:, (bp.edge + 1) % n, 0, jseg])                      # (L, S, nr, G0)
    w_idx = np.rint(bp.w_px / h).astype(int)
    centre = np.rint(np.stack([c.shift_px for c in coarse]) / h).astype(int)  # (L, S)
    nh = 2 * FINE_SHIFT_STEPS + 1
    shifts = centre[..., None] + np.arange(-FINE_SHIFT_STEPS, FINE_SHIFT_STEPS + 1)
    cost_all, gain_all = scan_cost(np.tile(Y, (L, 1)), models.reshape(L * S, nr, -1), m0, w_idx,
                               shifts.reshape(L * S, nh))
    cost_all = cost_all.reshape(L, S, nr, nh)
    gain_all = gain_all.reshape(L, S, nr, nh)
    out = []
    for i, (look, cost_l, gain_l) in enumerate(zip(looks, cost_all, gain_all)):
        flat = cost_l.reshape(S, -1)
        jb = np.argmin(flat, axis=1)
        mi, hi = np.unravel_index(jb, cost_l.shape[1:])
        s = (centre[i] + hi - FINE_SHIFT_STEPS) * h
        # parabola through the shift neighbours at the best radius
        cm = cost_l[ar, mi]
        inner = (hi > 0) & (hi < nh - 1)
        i0 = np.clip(hi, 1, nh - 2)
        c_l, c_0, c_r = cm[ar, i0 - 1], cm[ar, i0], cm[ar, i0 + 1]
        with np.errstate(invalid="ignore", divide="ignore"):
            den = c_l - 2 * c_0 + c_r
            dx = np.where(inner & np.isfinite(den) & (den > 0), 0.5 * (c_l - c_r) / den, 0.0)
        s = s + np.clip(dx, -0.5, 0.5) * h
        var = _shift_variance(cost_l, mi, hi, step[i, :, 0], h, rad_seg[i, :, 0] == 0, G)
        out.append(_look_fit(bp, look, rad_seg[i, ar, mi], s, flat[ar, jb],
                             gain_l.reshape(S, -1)[ar, jb], var))
    return out


def _look_fit(bp: BandProfiles, look, r, s, c, g, var) -> LookFit:
    c = np.where(bp.valid, c, np.inf)
    rms = np.sqrt(c / len(bp.w_px))         # c >= 0: scan_cost clamps the residual sum
    var = np.where(bp.valid, var, np.inf)
    return LookFit(look, r, s, c, g, rms, _trimmed_total(c, bp.valid), var)


def _shift_variance(cost, mi, hi, dr, ds, r_at_zero, n_samples) -> np.ndarray:
    """(S,) variance (px^2) of each segment's design-edge shift with its radius free.

    The cost ``C(r, shift)`` (sum of squared residuals) round its grid minimum is taken as a
    quadratic, Hessian ``H`` by central differences; with Gaussian residuals of variance
    ``s^2 = C_min / (G - 4)`` the Fisher information is ``H / (2 s^2)``, so
    ``var(shift) = 2 s^2 [H^-1]_ss`` (the radius marginalised). A radius pinned at 0 (a sharp
    edge, the grid's end) is held: ``2 s^2 / H_ss``. A minimum on the window's edge, or a cost
    that does not curve upwards, gives no information: ``inf``."""
    S, nr, nh = cost.shape
    ar = np.arange(S)
    m1, mp = np.clip(mi - 1, 0, nr - 1), np.clip(mi + 1, 0, nr - 1)
    h1, hp = np.clip(hi - 1, 0, nh - 1), np.clip(hi + 1, 0, nh - 1)
    c0 = cost[ar, mi, hi]
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        s2 = c0 / max(n_samples - 4, 1)
        css = (cost[ar, mi, hp] - 2 * c0 + cost[ar, mi, h1]) / ds ** 2
        crr = (cost[ar, mp, hi] - 2 * c0 + cost[ar, m1, hi]) / dr ** 2
        crs = (cost[ar, mp, hp] - cost[ar, mp, h1] - cost[ar, m1, hp]
               + cost[ar, m1, h1]) / (4 * dr * ds)
        det = crr * css - crs ** 2
        free = np.where((det > 0) & (crr > 0), 2 * s2 * crr / det, np.inf)
        held = np.where(css > 0, 2 * s2 / css, np.inf)
    at_zero = r_at_zero & (mi == 0)
    var = np.where(at_zero, held, free)
    edge = (hi == 0) | (hi == nh - 1) | (~at_zero & ((mi == 0) | (mi == nr - 1)))
    # not (var >= 0): NaN or a negative variance (a cost curving the wrong way) informs nothing
    return np.where(edge | ~np.isfinite(var) | ~(var >= 0), np.inf, var)


def _trimmed_total(cost, valid) -> float:
    c = np.sort(cost[valid & np.isfinite(cost)])
    if len(c) == 0:
        return np.inf
    return float(c[: max(1, int(np.ceil(0.75 * len(c))))].sum())


def fit_band(bp: BandProfiles, camera: Camera, holder: Holder, R_cam_holder, t_cam_holder_mm,
             shapes=("round", "chamfer"), previous: BandFit | None = None,
             fine_plausible: bool = True, looks: BandLooks | None = None) -> BandFit:
    """Fit the edge model to every segment's profile (module doc).

    ``previous``: a fit at a nearby pose whose looks (chosen and plausible) are fitted again,
    with no look scan. ``fine_plausible=False`` leaves the plausible looks at their coarse
    fit (a first pass that only needs to know which they are). ``looks``: a look calibrated
    in the cell (:class:`BandLooks`) instead of the generic :func:`band_looks`: the shape is
    chosen among ``shapes`` with it, the blur among its ``blurs_px``, and its variants are
    fitted for the budget only (never chosen).

    Returns
    -------
    BandFit : ``best`` the chosen look (its blur fitted), ``plausible`` the other looks whose
        trimmed cost is within :data:`PLAUSIBLE` of the best (fine-fitted too), and with
        ``looks`` its variants at the chosen shape and blur.
    """
    if not bp.valid.any():
        raise InputError("fit_band: no segment of any edge was sampled")
    if looks is None:
        candidates, blurs = band_looks(shapes), BLURS_PX
        light = em.EdgeLook()
    else:
        candidates, blurs = [looks.for_shape(s) for s in shapes], tuple(looks.blurs_px)
        light = looks.look                  # a calibrated ring light (edge_views' lights)
    bank = _ModelBank(em.edge_views(R_cam_holder, t_cam_holder_mm, camera.K, holder, light),
                      model_grid_px(bp))
    if previous is not None:
        # a second pass at a pose that moved little: the looks chosen before, scanned anew
        # (coarse, then fine) only for the chosen and the plausible ones
        before = [lf.look for lf in [previous.best] + previous.plausible]
        out = _fit_looks(bp, bank, before, _fit_looks(bp, bank, before, shift_range_px=2.0))
        return _offset(BandFit(out[0], out[1:], bp), looks, bank.view)
    # the look is chosen on all the pass's segments: a coarse scan's cost is the edge model's
    # profiles, one per edge end whatever the number of segments, so choosing it on every
    # other segment (as before) saved nothing and needed the chosen look scanned again
    coarse = _fit_looks(bp, bank, candidates)
    totals = np.array([lf.total for lf in coarse])
    order = np.argsort(totals)
    best_i = int(order[0])
    n_eff = max(1, int(np.ceil(0.75 * int(bp.valid.sum()))))
    # the chosen variant at each blur (one raw profile), then the plausible others at the
    # chosen blur
    fine = _fit_looks(bp, bank, [replace(candidates[best_i], blur_sigma_px=b) for b in blurs],
                      coarse[best_i])
    best = min(fine, key=lambda lf: lf.total)
    chosen = []
    for i in order[1:]:
        ratio = totals[best_i] / totals[i] if np.isfinite(totals[i]) else 0.0
        # plausible: close in cost, and of a likelihood weight that matters in the budget
        if (ratio < PLAUSIBLE or ratio ** (0.5 * n_eff) < MIN_LOOK_WEIGHT
                or len(chosen) == MAX_PLAUSIBLE):
            continue
        chosen.append(int(i))
    lks = [replace(candidates[i], blur_sigma_px=best.look.blur_sigma_px) for i in chosen]
    if not lks:
        plausible = []
    elif fine_plausible:
        plausible = _fit_looks(bp, bank, lks, [coarse[i] for i in chosen])
    else:
        plausible = [replace(coarse[i], look=lk) for i, lk in zip(chosen, lks)]
    if looks is not None and looks.variants:
        # the calibration's variants at the chosen shape and blur: for the budget only (a first
        # pass only needs to name them; the last fits them)
        vs = [replace(v, shape=best.look.shape, blur_sigma_px=best.look.blur_sigma_px,
                      profile_sigma_px=0.0) for v in looks.variants]
        if fine_plausible:
            plausible += _fit_looks(bp, bank, vs, _fit_looks(bp, bank, vs))
        else:
            plausible += [replace(best, look=lk) for lk in vs]
    return _offset(BandFit(best, plausible, bp), looks, bank.view)


def _offset(fit: BandFit, looks: BandLooks | None, view: em.EdgeView) -> BandFit:
    """The calibrated design-edge offsets (:meth:`DesignEdgeOffsets.offset`, at each segment's
    :func:`view_lean` in ``view``) added to every look's shifts (none without a
    calibration)."""
    if looks is None or not looks.offsets:
        return fit
    bp = fit.profiles
    px = bp.px_per_mm
    lean = view_lean(view, bp.edge, bp.frac)

    def moved(lf: LookFit) -> LookFit:
        return lf.moved(looks.offsets.offset(lf.look.shape, lean), px)

    fit.best = moved(fit.best)
    fit.plausible = [moved(lf) for lf in fit.plausible]
    return fit


def profile_costs(bp: BandProfiles, view: em.EdgeView, looks, radii_mm=CAL_RADII_MM,
                  shifts_px=(0.0,)):
    """The fit's cost of every segment under looks that differ only by their blur, over a grid
    of radii and shifts (the calibration's scan, :mod:`cutterpose.calibration.edge_look`).

    Parameters
    ----------
    view : :func:`~cutterpose.image.edge_model.edge_views` at the profiles' pose (lit as the
        looks are).
    looks : looks sharing all but ``blur_sigma_px`` (one raw profile for all of them).
    radii_mm : (M,) radii (mm) given to every segment; shifts_px : (H,) multiples of
        :data:`STEP_PX`.

    Returns
    -------
    cost, gain : (L, S, M, H) residual sum of squares (grey^2; inf for invalid segments) and
        the profile gain of ``y ~ a + b m(w - shift)``.
    """
    looks = list(looks)
    h = STEP_PX
    bank = _ModelBank(view, model_grid_px(bp))
    Y = np.where(bp.valid[:, None], bp.values, 0.0)
    w0, bls = bank.profiles(np.asarray(radii_mm, float), looks, h)
    m0 = int(round(-w0[0] / h))
    w_idx = np.rint(bp.w_px / h).astype(int)
    shifts = np.rint(np.asarray(shifts_px, float) / h).astype(int)
    cost, gain = zip(*(scan_cost(Y, _along_segments(bl, bp.edge, bp.frac), m0, w_idx, shifts)
                       for bl in bls))
    cost = np.stack(cost)
    cost[:, ~bp.valid] = np.inf
    return cost, np.stack(gain)
