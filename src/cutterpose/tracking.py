"""Tracking the holder while the robot approaches it: one pose per frame, fast.

The first frame (and any frame where tracking fails) is measured in full
(:func:`cutterpose.pipeline.measure`: region search, threshold, contour segmentation, dm+).
From the second frame on, the previous poses predict where every edge of the holder's inner
contour lies, and the region search, threshold and contour segmentation are skipped:

1. **prediction** (constant velocity on SE(3)): with ``T_k = (R_k, t_k)`` the pose of the holder
   in the camera frame at frame ``k``, the camera's motion over one frame is
   ``D = T_k T_{k-1}^{-1}`` (its body velocity, in the camera frame); the prediction is
   ``T_pred = D T_k``; without two consecutive tracked poses, ``T_pred = T_k``;
2. **edges**: the field chain's line step :func:`cutterpose.image.edges.robust_edge_lines` on
   the 20 model edges projected with ``T_pred`` (grey-level profiles across each edge within
   +-``band_half_width_px``, the *innermost* rise of a broken edge, LMedS + Tukey IRLS lines, an
   edge *seen* when its inliers cover ``min_support`` of it and it lies within
   ``shift_fraction`` of the band of its prediction): an edge under a slurry lump, behind the
   cutter's silhouette or rounded beyond recognition is left out, not forced;
3. **pose**: Gauss-Newton on the distances of the projected ends of every *seen* edge to its
   line (ideal px), started at ``T_pred`` (Drummond & Cipolla 2002), no coarse search: a corner
   whose other edge is hidden still counts through its seen one. A seen edge far off the
   fitted model while the others fit (``line_outlier_*``) is left out and the pose fitted
   again. The bands are re-centred on the fitted pose and the edges found again while the fit
   moved them (by more than ``centred_fraction`` of the band, up to ``max_passes``). The std
   per DOF is the Gauss-Newton covariance ``s^2 (J^T J)^-1`` as in :mod:`cutterpose.pipeline`;
4. **checks** (every tracked frame): at least half the holder's edges seen
   (``min_line_share``; two per direction),
   the bands settled (the last pass's fit moved them little), the RMS and largest model-to-edge
   distance below ``max_rms_px`` / ``max_corner_residual_px``, and the seen edges fixing
   every DOF within ``max_std_ratio`` of the std all edges would give (a family of short edges
   lost far away leaves X or Z loose: that is not the full measurement's accuracy). A frame
   that fails any of them (a jump, an occluder, lost edges) falls back to the full
   measurement and says why.

**Broken edges** (``method="dm+b"``, the default): the edges tracking finds are the innermost
rise of the broken pocket edge, off the design edge that ``dm+b`` measures. The tracker fits
a *moved model* instead: design edge ``k`` shifted by ``d_k`` mm along its outward normal in
the face plane (:func:`offset_polygon_mm`), the offsets measured at full measurements and
re-measured (*re-anchored*) by the band fit as the view changes, the edge model predicting
their change between anchors; a tracked pose is then the design edge's.

**Jobs beside the tracking** (``TrackParams.anchor_lag = L > 0``): re-anchors and fall-backs
(full measurements) run on a worker and are applied at the start of frame ``j + L``, fixed,
so the poses do not depend on the worker or the machine's speed; a fall-back's frame is
answered at once without a pose and the frames until ``j + L`` are tracked from the last
pose. **Frame times** (``update(image, t_s=)``) keep the motion per second over skipped
frames. **Temporal filter** (optional): a constant-velocity alpha-beta filter on SE(3),
reported beside the raw pose, never instead of it, reset at a jump.

All of this in detail, with the conventions of frames, times and deferred jobs:
``docs/tracking.md`` (its sections are cited below as "docs/tracking.md, ...").

Convention:
    Poses ``T_cam_holder`` as in :mod:`cutterpose.geometry.pose` (``x_cam = R x_holder + t``,
    mm, deg). Twists ``xi = (omega [rad], rho [mm])`` with ``Exp(xi) = (Exp(omega),
    V(omega) rho)``. Pixels: ``*_px`` observed, ``*_ideal_px`` undistorted (ideal pinhole ``K``).
    Edge ``k`` of the model runs from corner ``k`` to corner ``k + 1`` (``holder.json``
    order) and corner ``i`` is the intersection of edges ``i - 1`` and ``i``, as in the field
    chain (:func:`cutterpose.image.features.detect_features_field`).

References:
    T. Drummond, R. Cipolla, "Real-time visual tracking of complex structures", PAMI 24(7),
    2002 (edge search along normals of the projected model); T. Barfoot, *State Estimation for
    Robotics*, 2017, sec. 7.1 (SE(3) exponential map, ``V = J_l``); P. Kalata, "The tracking
    index", IEEE TAES 20(2), 1984 (alpha-beta filter); Benedict & Bordner (1962) for
    ``beta = alpha^2 / (2 - alpha)``.
"""

from __future__ import annotations

import math
import operator
import time
import weakref
from concurrent.futures import Future, ProcessPoolExecutor, ThreadPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.spatial.transform import Rotation

from .budget import Tolerance
from .errors import CutterposeError, InputError
from .frames import load_frame
from .geometry.camera import Camera, default_camera
from .geometry.holder import Holder, default_holder, outward_edge_normals
from .geometry.pose import Pose, pixel_jacobian, wrap_deg
from .image import FeatureParams, as_grey_u8
from .image import edge_model as em
from .image.edges import intersect_consecutive, robust_edge_lines
from .image.region import prepare_outline_search
from .methods import get_method
from .pipeline import (
    DOF_NAMES,
    EDGE_SHAPE_FITS,
    Measurement,
    QualityLimits,
    band_verdict,
    corner_residual_px,
    measure,
)
from .solvers.edge_band import as_band_looks, measure_band
from .solvers.estimate import PoseEstimate

__all__ = ["TrackParams", "TrackResult", "Tracker", "PoseFilter", "approach_limits",
           "approach_params", "se3_exp", "se3_log", "offset_polygon_mm",
           "offset_edge_ends_mm", "line_offsets_mm"]


# ------------------------------------------------------------------------------------------
# SE(3)
def _v_matrix(w: np.ndarray) -> np.ndarray:
    """``V(w) = I + (1 - cos a)/a^2 [w]x + (a - sin a)/a^3 [w]x^2`` (the left Jacobian)."""
    a2 = float(w @ w)
    W = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    if a2 < 1e-12:
        return np.eye(3) + 0.5 * W + (W @ W) / 6.0
    a = math.sqrt(a2)
    return np.eye(3) + ((1 - math.cos(a)) / a2) * W + ((a - math.sin(a)) / (a2 * a)) * (W @ W)


def se3_exp(xi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``Exp`` of a twist ``(omega [rad], rho [mm])`` -> ``(R, t_mm)``."""
    xi = np.asarray(xi, float)
    w = xi[:3]
    return Rotation.from_rotvec(w).as_matrix(), _v_matrix(w) @ xi[3:]


def se3_log(R: np.ndarray, t_mm: np.ndarray) -> np.ndarray:
    """``Log`` of ``(R, t_mm)`` -> twist ``(omega [rad], rho [mm])``."""
    w = Rotation.from_matrix(R).as_rotvec()
    return np.concatenate([w, np.linalg.solve(_v_matrix(w), np.asarray(t_mm, float))])


def _relative(a: Pose, b: Pose) -> tuple[np.ndarray, np.ndarray]:
    """``a b^{-1}`` as ``(R, t)``."""
    R = a.R @ b.R.T
    return R, a.t_mm - R @ b.t_mm


def _left(R: np.ndarray, t: np.ndarray, pose: Pose) -> Pose:
    """``(R, t) pose``."""
    Rn = R @ pose.R
    # re-orthonormalise: products of many rotations drift by ~1e-16 per step
    u, _, vt = np.linalg.svd(Rn)
    return Pose(u @ vt, R @ pose.t_mm + t)


# ------------------------------------------------------------------------------------------
# re-anchors beside the tracking
def band_fit(img: np.ndarray, camera: Camera, holder: Holder, pose: Pose,
             edges_used: np.ndarray, shapes, passes: int, looks, limits: QualityLimits):
    """A re-anchor's band fit from a tracked ``pose`` (:func:`measure_band`) and its verdict
    (``dm+b``'s own, :func:`band_verdict`): ``(estimate, quality, ms)``."""
    t = time.perf_counter()
    start = PoseEstimate("track", pose.R, pose.t_mm.copy())
    est = measure_band(img, camera, holder, start, edges_used, shapes, passes, looks=looks)
    return est, band_verdict(est, limits), (time.perf_counter() - t) * 1e3


def full_measurement(img: np.ndarray, camera: Camera, holder: Holder, method: str,
                     params: FeatureParams, limits: QualityLimits, edge_look) -> Measurement:
    """A fall-back's full measurement (:func:`measure`, with the corners the tracker's
    offsets start from)."""
    return measure(img, camera, holder, method, params, limits, edge_look=edge_look,
                   corners=True)


def _run_shared(fn, shm_name: str, shape: tuple, *args):
    """``fn(frame, *args)`` in the worker process, on the frame in shared memory
    ``shm_name`` (``fn``: :func:`band_fit` or :func:`full_measurement`)."""
    from multiprocessing import shared_memory

    # attached, not owned: the tracker's process unlinks it (a spawned worker shares its
    # resource tracker, which holds the name once however often it is registered)
    shm = shared_memory.SharedMemory(name=shm_name)
    try:
        # copied out (~2 ms for 12 MP): a measurement keeps views of its frame, which must
        # outlive the block (pickling a view of a closed block crashes the worker), and the
        # block is free for the next job
        img = np.ndarray(shape, np.uint8, buffer=shm.buf).copy()
    finally:
        shm.close()
    return fn(img, *args)


def _warm_worker(camera: Camera | None = None, holder: Holder | None = None,
                 params: FeatureParams | None = None) -> None:
    """Import the band fit in the worker before the first re-anchor needs it, and build the
    full measurement's outline templates before the first fall-back does."""
    from .solvers import edge_band  # noqa: F401

    if camera is not None:
        prepare_outline_search(camera, holder, params)


class AnchorProcess:
    """One worker process for the deferred re-anchors and fall-backs
    (``anchor_worker="process"``): the frame goes through a shared-memory block of its size
    (one pending job at a time, so one block, which the job copies its frame out of; a job
    dropped by a fall-back and still queued may read the next job's frame: its result is
    never read), the rest of the arguments by pickle. A process, not a thread: the band fit is
    ~120 ms of mostly small NumPy calls that hold the interpreter lock, which a thread would
    take from the tracking (spawned, not forked: the caller may have threads of its own; as
    for any spawned process, a script's main module must be importable, i.e. not read from
    standard input: else the worker fails, and each re-anchor falls back to a full
    measurement with that reason)."""

    def __init__(self, shape: tuple, *warm):
        """``warm``: ``(camera, holder, params)`` of the full measurements it may run."""
        import multiprocessing
        from multiprocessing import shared_memory

        self.shape = tuple(shape)
        self._shm = shared_memory.SharedMemory(create=True, size=int(np.prod(self.shape)))
        self._pool = ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"))
        self.warm = self._pool.submit(_warm_worker, *warm)
        # a tracker dropped without close(): the worker and the block go with it
        self._finalizer = weakref.finalize(self, _release_worker, self._pool, self._shm)

    def submit(self, fn, img: np.ndarray, *args) -> Future:
        """``fn(img, *args)`` in the worker (``fn`` a module-level function)."""
        if img.shape != self.shape or img.dtype != np.uint8:
            raise InputError(f"frame {img.shape} {img.dtype} is not the {self.shape} uint8 "
                             "frames of this tracker")
        np.ndarray(self.shape, np.uint8, buffer=self._shm.buf)[:] = img
        return self._pool.submit(_run_shared, fn, self._shm.name, self.shape, *args)

    def shutdown(self, wait: bool = True, cancel_futures: bool = False) -> None:
        self._finalizer.detach()
        _release_worker(self._pool, self._shm, wait, cancel_futures)


def _release_worker(pool, shm, wait: bool = False, cancel_futures: bool = True) -> None:
    pool.shutdown(wait=wait, cancel_futures=cancel_futures)
    shm.close()
    try:
        shm.unlink()
    except FileNotFoundError:
        pass


# ------------------------------------------------------------------------------------------
# the tracked edges of a broken edge: the design contour moved edge by edge in the face plane
def offset_polygon_mm(corners_mm: np.ndarray, offset_mm: np.ndarray) -> np.ndarray:
    """(N, 3) corners (holder frame, ``Z = 0``) of the polygon whose edge ``k`` is the design
    edge ``k`` moved by ``offset_mm[k]`` along its outward normal in the face plane (negative:
    into the pocket); corner ``i`` is where the moved edges ``i - 1`` and ``i`` meet (corners of
    nearly parallel neighbours are moved along the edge normal instead).

    ``offset_mm`` (N,): one offset per edge; (N, 2): an offset at each end of every edge
    (``[k, 0]`` at corner ``k``, ``[k, 1]`` at corner ``k + 1``): the moved edge is the line
    through both moved ends, tilted against the design edge when they differ."""
    c = np.asarray(corners_mm, float)
    d = np.asarray(offset_mm, float)
    n = outward_edge_normals(c)
    if d.ndim == 2:
        a = c + d[:, 0:1] * n                               # edge k: through a_k and b_k
        b = np.roll(c, -1, axis=0) + d[:, 1:2] * n
        t = b - a
        n_m = np.column_stack([t[:, 1], -t[:, 0]]) / np.linalg.norm(t, axis=1)[:, None]
        n_m *= np.sign(np.einsum("ij,ij->i", n_m, n))[:, None]
        rhs = np.einsum("ij,ij->i", n_m, a)
        q = a.copy()
    else:
        n_m = n
        rhs = np.einsum("ij,ij->i", n, c) + d            # edge k: n_k . x = n_k . c_k + d_k
        q = c + d[:, None] * n
    # corner i: edges i - 1 (p . x = e) and i (n_m . x = rhs), Cramer's rule (a 2 x 2 system
    # per corner; np.linalg.solve's overhead was most of a tracked frame's 0.2 ms here)
    pn, e = np.roll(n_m, 1, axis=0), np.roll(rhs, 1)
    det = pn[:, 0] * n_m[:, 1] - pn[:, 1] * n_m[:, 0]
    ok = np.abs(det) > 1e-6
    q[ok, 0] = ((e * n_m[:, 1] - rhs * pn[:, 1]) / np.where(ok, det, 1.0))[ok]
    q[ok, 1] = ((pn[:, 0] * rhs - n_m[:, 0] * e) / np.where(ok, det, 1.0))[ok]
    return np.column_stack([q, np.zeros(len(q))])


def offset_edge_ends_mm(corners_mm: np.ndarray, offset_mm: np.ndarray) -> np.ndarray:
    """(2N, 3) ends of the moved edges (holder frame, ``Z = 0``): rows ``k`` the start of edge
    ``k`` (design corner ``k`` moved by ``offset_mm[k, 0]`` along the edge's outward normal),
    rows ``N + k`` its end (corner ``k + 1`` by ``offset_mm[k, 1]``); ``offset_mm`` (N,) is
    the same offset at both ends."""
    c = np.asarray(corners_mm, float)
    d = np.asarray(offset_mm, float)
    d = np.column_stack([d, d]) if d.ndim == 1 else d
    n = outward_edge_normals(c)
    e = np.concatenate([c + d[:, 0:1] * n, np.roll(c, -1, axis=0) + d[:, 1:2] * n])
    return np.column_stack([e, np.zeros(len(e))])


#: the view model's step along the line of sight for its slope, and how far from the anchor's
#: distance (relative) it is followed linearly (beyond, the offsets stay as there)
VIEW_STEP = 0.05
VIEW_REACH = 0.15
#: the scale (px) of a tracked edge's distance from the model, against which an unmeasured
#: edge's offset prior is weighed (the tracked frames' RMS is 0.3-0.6 px on broken edges)
LINE_SCALE_PX = 0.3
#: the fewest edges a tracked frame may rest on, whatever the holder's design
MIN_LINES = 4


def _offset_slope(pose: Pose, points_mm: np.ndarray, normals: np.ndarray, L: np.ndarray,
                  K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Signed distances (ideal px) of the projected face-plane ``points_mm`` (M, 2) to the
    lines ``L`` (M, 3), and their derivatives w.r.t. an outward shift of each point along its
    ``normals`` (M, 2) in the face plane (px per mm)."""
    X = np.column_stack([points_mm, np.zeros(len(points_mm))]) @ pose.R.T + pose.t_mm
    Rn = np.column_stack([normals, np.zeros(len(normals))]) @ pose.R.T   # d X_cam / d shift
    uv = X[:, :2] / X[:, 2:3] @ K[:2, :2].T + K[:2, 2]
    duv = (Rn[:, :2] - X[:, :2] / X[:, 2:3] * Rn[:, 2:3]) / X[:, 2:3] @ K[:2, :2].T
    return (L[:, 0] * uv[:, 0] + L[:, 1] * uv[:, 1] + L[:, 2],
            L[:, 0] * duv[:, 0] + L[:, 1] * duv[:, 1])


def line_offsets_mm(pose: Pose, lines: np.ndarray, seen: np.ndarray, holder: Holder, K,
                    per_end: bool = True) -> np.ndarray:
    """(N, 2) outward offsets (mm, face plane) of the image ``lines`` (N, 3; ideal px) from
    the design edges seen with ``pose``: the shift of each end of design edge ``k`` along its
    outward normal that puts it, projected, on line ``k`` (Newton); ``per_end=False``: one
    shift for both ends of an edge (least squares). NaN for edges not ``seen``."""
    c = np.asarray(holder.corners_mm, float)
    nrm = holder.edge_normals
    K = np.asarray(K, float)
    out = np.full((len(c), 2), np.nan)
    ks = np.nonzero(seen)[0]
    if len(ks) == 0:
        return out
    ends = np.concatenate([c[ks], np.roll(c, -1, axis=0)[ks]])     # (2m, 2)
    nn = np.concatenate([nrm[ks], nrm[ks]])
    L = np.concatenate([lines[ks], lines[ks]])
    m = len(ks)
    d = np.zeros(2 * m)
    for _ in range(3):   # the projection is nearly linear over a millimetre
        r, g = _offset_slope(pose, ends + d[:, None] * nn, nn, L, K)
        if per_end:
            d = d - r / g
        else:
            step = (r[:m] * g[:m] + r[m:] * g[m:]) / (g[:m] ** 2 + g[m:] ** 2)
            d = d - np.concatenate([step, step])
    out[ks] = np.column_stack([d[:m], d[m:]])
    return out


def _bands_moved_px(r_start: np.ndarray, r: np.ndarray) -> float:
    """How far a pass's pose fit moved the bands' centres (px): the largest change of a seen
    edge end's distance to its line (``r_start`` at the pass's start pose, ``r`` at its
    fitted pose). The next pass centres its bands on the fitted pose, so this is how far they
    move; how far the edges lie from the model (``r`` itself) is the residual checks' to
    judge (a worn edge's break varies along it and leaves a px or two however the bands are
    centred)."""
    return float(np.max(np.abs(np.asarray(r_start) - np.asarray(r))))


# ------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class TrackParams:
    """Parameters of the tracker (pixel lengths for the paper's 12-Mpx camera; scaled with
    the focal length by :meth:`for_camera`)."""

    band_half_width_px: float = 6.0   #: profiles across the predicted edge, +- this
    cold_band_factor: float = 2.0     #: wider band while the velocity is unknown
    profile_step_px: float = 3.0      #: spacing of the profiles along an edge
    passes: int = 1                   #: refinement passes (re-centred on the refined line)
    end_trim_px: float = 10.0         #: profiles kept this far from the predicted corners
    min_support: float = 0.5          #: an edge is seen if its inliers cover this share
    #: RMS model-to-edge distance after the fit (ideal px) and the largest one (at least
    #: 2.5 RMS limits): a broken edge whose radius varies by +-0.5 mm along the contour
    #: (preset ``new``) leaves ~0.4 px of RMS at 600-900 mm that the full measurement has as
    #: well; a wrong edge leaves more. The RMS limit is at least ``rms_ref_factor`` times the
    #: corner RMS of the last full measurement (the tracker's RMS is ~0.7 of it on the same
    #: frames: analytic ``new`` 0.40 / 0.58 px, pbr ``new`` 0.55 / 0.76 px)
    max_rms_px: float = 0.6
    max_corner_residual_px: float = 1.5
    rms_ref_factor: float = 1.0
    #: edges seen for a pose, as a share of the holder's edges (10 of the reference's 20),
    #: at least ``MIN_LINES``, and two per direction (:meth:`lines_needed`)
    min_line_share: float = 0.5
    shift_fraction: float = 0.75      #: a seen edge lies within this share of the band
    #: the last pass's pose fit moved the bands by at most this share of them (the edges may
    #: lie farther from the model: the residual limits judge that)
    centred_fraction: float = 0.35
    max_passes: int = 3               #: band passes, each centred on the previous pose
    #: a seen edge whose ends lie farther than max(line_outlier_px, line_outlier_factor x the
    #: median) from their line after the pose fit is left out (at most max_dropped_lines)
    line_outlier_px: float = 0.25
    line_outlier_factor: float = 4.0
    max_dropped_lines: int = 3
    #: the seen edges must fix every DOF within this factor of all the holder's edges' std
    max_std_ratio: float = 1.5
    filter_alpha: float = 0.5         #: alpha-beta filter gains (beta: Benedict-Bordner)
    filter_beta: float = 0.5 ** 2 / 1.5
    gate_mm: float = 5.0              #: filter reset when the innovation exceeds these
    gate_deg: float = 2.0
    #: ``dm+b``: the tracked edges' offsets from the design edge are measured again (a band
    #: fit from the tracked pose, docs/tracking.md) once the distance to the holder has changed by
    #: this fraction since the last measurement of them (``math.inf``: never) ...
    anchor_scale_change: float = 0.05
    anchor_every: int = 0             #: ... or every this many frames (0: no such rule)
    #: the band fit's passes (``measure_band``; one pass from the tracked pose takes longer:
    #: it chooses the look on all segments)
    anchor_passes: int = 2
    #: the weight of a re-anchor's offsets against those carried (a fading-memory average:
    #: ``1 / n`` for the ``n``-th measurement since the full one while that is larger; 1:
    #: the last measurement only)
    anchor_gain: float = 0.5
    #: after a full measurement, this many tracked frames re-anchor whatever the view's change
    #: (one measurement of the offsets carries its pose's error to every frame after it)
    anchor_warmup: int = 2
    #: an offset at each end of every edge (True) or one per edge: the break of a worn edge
    #: varies along it, so the edge tracked is tilted against the design edge, and one
    #: offset per edge leaves half that tilt at each end for the pose to absorb. Not the
    #: default: on the pbr approaches of the eleventh session it followed the full
    #: measurement more closely (worn), but an edge whose line was bent by an occluder at the
    #: anchor keeps that tilt at its ends, and 8 of 20 frames of a held-back ``new`` approach
    #: fell back (docs/RESULTS.md section 13)
    anchor_ends: bool = False
    #: the band's pose and the tracked pose may differ per DOF by this many combined std;
    #: beyond, one of them is wrong and the frame is measured in full
    anchor_gate_sigma: float = 5.0
    #: a re-anchor's band fit (~120 ms) runs beside the tracking and its offsets are applied
    #: this many frames after the frame it was measured on (docs/tracking.md, "Jobs beside
    #: the tracking"); 0: on that frame itself, which then waits for the fit
    anchor_lag: int = 0
    #: with ``anchor_lag > 0``, a frame the tracking cannot follow is measured in full beside
    #: the tracking too (docs/tracking.md, "Jobs beside the tracking"): it is answered at
    #: once without a pose, the next ones are tracked from the last pose until it is applied
    #: ``anchor_lag`` frames on, instead of waiting ~250 ms for it; False: measured on the
    #: frame itself
    defer_fallbacks: bool = True
    #: ``dm+b``: the offsets follow the view between anchors as the edge model says a broken
    #: edge of the band fit's radius images (docs/tracking.md, "Broken edges: the offsets");
    #: False: a length on the holder, constant until the next anchor
    view_model: bool = True

    def lines_needed(self, n_edges: int) -> int:
        """Edges a tracked frame must see on a holder of ``n_edges`` edges: the share
        ``min_line_share`` of them, at least :data:`MIN_LINES` (six pose DOFs from two lines
        per direction and their spacing) and never more than the holder has."""
        return min(n_edges, max(MIN_LINES, math.ceil(self.min_line_share * n_edges - 1e-9)))

    def for_camera(self, camera: Camera) -> TrackParams:
        k = camera.focal_px / (0.00854103 / 3.45e-6)
        if abs(k - 1) < 0.1:
            return self
        return replace(self, band_half_width_px=max(3.0, self.band_half_width_px * k),
                       profile_step_px=max(1.0, self.profile_step_px * k),
                       end_trim_px=max(4.0, self.end_trim_px * k))


def approach_limits() -> QualityLimits:
    """Quality limits of the full measurement during an approach: the working range's angles,
    lateral shifts up to 60 mm, depths from 580 to 940 mm, and an error budget of 10 mm / 3 deg
    (3 sigma): on the way the pose guides the robot and seeds the tracker; the grasp tolerance
    (1 mm, ``Tolerance()``) is the verdict of the measurement at the final stop."""
    return QualityLimits(range_center_dof=(0.0, 0.0, 0.0, 0.0, 0.0, 760.0),
                         range_half_width_dof=(10.0, 10.0, 10.0, 60.0, 60.0, 180.0),
                         tolerance=Tolerance(position_mm=10.0, angle_deg=3.0))


def approach_params(camera: Camera) -> FeatureParams:
    """Image-stage parameters of the full measurement during an approach: the field chain with
    outline templates at 600-900 mm (``roi_depths_mm``; the default matches only the nominal
    600 mm, where a holder at 800-900 mm, 1.3-1.5 times smaller, scores ~0.3 and lands off
    centre)."""
    return FeatureParams.for_camera(camera, roi_depths_mm=(600.0, 675.0, 750.0, 825.0, 900.0))


@dataclass
class TrackResult:
    """One frame's answer.

    Attributes
    ----------
    frame : the frame's index (0-based, in the order given to the tracker); ``frame_id``
        the camera's frame number given with it (:meth:`Tracker.update`), else ``frame``.
    mode : ``"track"`` (predicted edges), ``"full"`` (the full measurement: first frame or a
        fall-back) or ``"lost"`` (no pose; also a deferred fall-back's frame, docs/tracking.md).
    pose : the raw per-frame pose (None when lost); ``std_dof`` its std per DOF (tracking
        with ``dm+b``: the fit's and the last anchor's in quadrature, docs/tracking.md).
    ok : the pose passed the checks (tracking) or the verdict (full).
    fallback_reason : why tracking was not used on this frame ("" when tracked).
    filtered_pose : the temporal filter's pose (None without filter or pose); ``filter_reset``
        the reason it was reset on this frame ("" otherwise).
    rms_px : RMS residual (tracking: model-to-edge distances; full: corners);
        ``edge_support`` the lowest inlier share of a seen edge.
    corners_px : (20, 2) corners, model order with NaN where an edge is not seen (tracking),
        or those of the full measurement.
    measurement : the full measurement when one was made (on the frame that takes up a
        deferred fall-back: that of the frame it was started on).
    timings_ms : wall time per stage.
    """

    frame: int
    mode: str
    pose: Pose | None
    std_dof: np.ndarray
    ok: bool
    fallback_reason: str = ""
    filtered_pose: Pose | None = None
    filter_reset: str = ""
    rms_px: float = math.nan
    edge_support: float = math.nan
    corners_px: np.ndarray | None = None
    measurement: Measurement | None = None
    timings_ms: dict = field(default_factory=dict)
    passes: int = 0   #: edge passes (tracking: 2 when the first pass's fit moved the bands)
    lines_seen: int = 0    #: tracking: edges with enough inlier support (of the holder's)
    corners_used: int = 0  #: tracking: corners whose two lines were seen
    lines_dropped: int = 0  #: tracking: seen edges left out as off the fitted model
    #: ``dm+b`` tracking: "re-anchored" when the edges' offsets from the design edge were
    #: measured again on this frame, "re-anchor refused: ..." when the band fit was refused
    #: (the previous offsets kept); deferred (``TrackParams.anchor_lag``): "re-anchor
    #: started" on the frame measured, "re-anchored (frame j)" / "re-anchor (frame j)
    #: refused ..." on the frame its result is applied on; "" otherwise
    anchor: str = ""
    #: tracking: the (N, 3) edge lines (ideal px, NaN where not seen) and which edges the pose
    #: rests on (after the outliers were left out)
    lines_ideal: np.ndarray | None = field(default=None, repr=False)
    edges_used: np.ndarray | None = field(default=None, repr=False)
    #: tracking: every edge line found (before the outlier test) and which edges they are:
    #: an anchor measures the offsets of the edges used and of those found whose offset no
    #: anchor has measured yet
    lines_found: np.ndarray | None = field(default=None, repr=False)
    edges_found: np.ndarray | None = field(default=None, repr=False)
    frame_id: int = -1

    def to_dict(self) -> dict:
        """One JSON object of ``cutterpose track --json-lines``."""
        def f(x):
            return None if x is None or not math.isfinite(float(x)) else float(x)

        return {"frame": self.frame, "frame_id": self.frame_id, "mode": self.mode,
                "ok": self.ok,
                "fallback_reason": self.fallback_reason,
                "pose": None if self.pose is None else self.pose.to_dict(),
                "std": {k: f(v) for k, v in zip(DOF_NAMES, self.std_dof)},
                "filtered_pose": None if self.filtered_pose is None
                else self.filtered_pose.to_dict(),
                "filter_reset": self.filter_reset, "rms_residual_px": f(self.rms_px),
                "edge_support": f(self.edge_support), "passes": self.passes,
                "lines_seen": self.lines_seen, "corners_used": self.corners_used,
                "lines_dropped": self.lines_dropped, "anchor": self.anchor,
                "timings_ms": {k: round(float(v), 3) for k, v in self.timings_ms.items()}}


class PoseFilter:
    """Constant-velocity alpha-beta filter on SE(3) (docs/tracking.md, "Temporal filter")."""

    def __init__(self, alpha: float = 0.5, beta: float = 0.5 ** 2 / 1.5, gate_mm: float = 5.0,
                 gate_deg: float = 2.0):
        if not (0 < alpha <= 1 and 0 <= beta < 2):
            raise InputError(f"filter gains need 0 < alpha <= 1, 0 <= beta < 2; got "
                             f"{alpha}, {beta}")
        self.alpha, self.beta = float(alpha), float(beta)
        self.gate_mm, self.gate_deg = float(gate_mm), float(gate_deg)
        self.reset()

    def reset(self, pose: Pose | None = None) -> None:
        self.pose, self.xi = pose, np.zeros(6)
        self._fresh = True   # one pose since the reset: the velocity is not known yet

    def update(self, z: Pose, force_reset: str = "", dt: float = 1.0) -> tuple[Pose, str]:
        """Filter the measured pose ``z``, ``dt`` after the last one (in the twist's unit: a
        frame, or a second with frame times); returns the filtered pose and the reset
        reason."""
        if self.pose is None or force_reset:
            self.reset(z)
            return z, force_reset or "first pose"
        if not dt > 0:
            raise InputError(f"filter: the time step must be > 0, got {dt}")
        if self._fresh:
            # two-point start: the velocity from the first two poses, the state on the second
            Rn, tn = _relative(z, self.pose)
            self.xi = se3_log(Rn, tn) / dt
            self.pose, self._fresh = z, False
            return z, ""
        Rp, tp = se3_exp(self.xi * dt)
        pred = _left(Rp, tp, self.pose)
        nu = se3_log(*_relative(z, pred))
        # gate on what a jump looks like: the holder's displacement and rotation angle
        rot_deg = math.degrees(float(np.linalg.norm(nu[:3])))
        trans_mm = float(np.linalg.norm(z.t_mm - pred.t_mm))
        if rot_deg > self.gate_deg or trans_mm > self.gate_mm:
            self.reset(z)
            return z, (f"innovation {trans_mm:.1f} mm / {rot_deg:.2f} deg beyond the gate "
                       f"({self.gate_mm} mm / {self.gate_deg} deg)")
        Ru, tu = se3_exp(self.alpha * nu)
        self.pose = _left(Ru, tu, pred)
        self.xi = self.xi + self.beta * nu / dt
        return self.pose, ""


@dataclass
class _DeferredAnchor:
    """A re-anchor measured beside the tracking (docs/tracking.md, "Jobs beside the
    tracking")."""

    at: int                 #: the frame it is applied on
    future: Future          #: its band fit
    frame: int              #: the tracked frame it measures
    pose: Pose              #: that frame's tracked pose
    std: np.ndarray         #: and its std
    lines: np.ndarray       #: the lines tracking found there (ideal pixels)
    used: np.ndarray        #: which edges they are


@dataclass
class _DeferredFull:
    """A fall-back measured beside the tracking (docs/tracking.md, "Jobs beside the
    tracking")."""

    at: int                 #: the frame it is applied on
    frame: int              #: the frame measured
    future: Future          #: its full measurement
    image: np.ndarray | None   #: that frame, for the offsets (methods that carry them)
    last: Pose | None       #: the last pose before it
    last_k: int             #: that pose's frame
    vel: tuple | None       #: the motion per unit of time then


class Tracker:
    """Pose of the holder in a sequence of frames (module doc).

    Parameters
    ----------
    camera, holder : defaults: the Table 1 camera and ``holder.json``.
    method : the full measurement's pose method (first frame and fall-backs; default ``dm+b``,
        as :func:`~cutterpose.pipeline.measure`'s). With ``dm+b`` (and ``dm+r``) the tracker
        fits the design contour moved edge by edge onto the edges it tracks (the innermost
        rise of the broken edge), the offsets measured at the full measurement; ``dm+b``
        measures them again from the tracked pose as the view changes (docs/tracking.md, "Broken
        edges").
    params, limits : the full measurement's image parameters and quality limits (default: an
        approach from 940 to 580 mm, :func:`approach_params` and :func:`approach_limits`).
    track : :class:`TrackParams`.
    filter : also report the temporal filter's pose.
    edge_look : the edge look calibrated in the cell
        (:func:`cutterpose.calibration.edge_look.load_edge_look`): ``dm+b``'s full measurements
        and re-anchors fit it instead of the generic looks.
    anchor_worker : with ``TrackParams.anchor_lag > 0``, where the deferred re-anchors' band
        fits run: ``"process"`` (a worker process, started with the tracker), ``"thread"`` or
        ``"inline"`` (on the frame they are measured on); the same poses with each.
        :meth:`close` (or ``with Tracker(...)``) ends the worker.

    Examples
    --------
    >>> tracker = Tracker(camera, holder, filter=True)          # doctest: +SKIP
    >>> for frame in frames:                                    # doctest: +SKIP
    ...     r = tracker.update(frame)
    ...     print(r.mode, r.pose.dof, r.fallback_reason)
    """

    def __init__(self, camera: Camera | None = None, holder: Holder | None = None,
                 method: str = "dm+b", params: FeatureParams | None = None,
                 limits: QualityLimits | None = None, track: TrackParams | None = None,
                 filter: bool = False, edge_look=None, anchor_worker: str = "process"):
        if anchor_worker not in ("process", "thread", "inline"):
            raise InputError(f"anchor_worker must be process, thread or inline, got "
                             f"{anchor_worker!r}")
        self.camera = camera or default_camera("table1")
        self.anchor_worker = anchor_worker
        self._executor: ThreadPoolExecutor | AnchorProcess | None = None
        self.edge_look = edge_look
        self.holder = holder or default_holder()
        self.method = method
        #: the method refines dm+'s pose beyond the corners (dm+b, dm+r): the tracker carries
        #: its edges' offsets from the design edge
        self._refines = get_method(method).base is not None
        self.params = params or approach_params(self.camera)
        self.limits = limits or approach_limits()
        self.tp = (track or TrackParams()).for_camera(self.camera)
        self.K = np.array(self.camera.K, float)
        self._refine_params = FeatureParams.for_camera(
            self.camera, refine_half_width_px=self.tp.band_half_width_px,
            refine_step_px=self.tp.profile_step_px, refine_passes=self.tp.passes,
            refine_trim_px=self.tp.end_trim_px)
        self._line_cache: dict = {}
        self.filter = PoseFilter(self.tp.filter_alpha, self.tp.filter_beta, self.tp.gate_mm,
                                 self.tp.gate_deg) if filter else None
        self.reset()
        # the full measurement's outline templates (~190 ms for the approach's five depths,
        # once per process): built now, before the first frame arrives
        prepare_outline_search(self.camera, self.holder, self.params)
        if anchor_worker == "process" and self.tp.anchor_lag > 0 and (
                method == "dm+b" or self.tp.defer_fallbacks):
            # started now: the spawn and its imports (~1 s) run beside the first frame's full
            # measurement instead of delaying the first re-anchor
            w, h = self.camera.image_size_px
            self._executor = AnchorProcess((h, w), self.camera, self.holder, self.params)

    def reset(self) -> None:
        """Forget the past: the next frame is measured in full."""
        # the model the tracked edges are fitted with: the design corners, or (dm+b, dm+r)
        # the design contour moved by the offsets of the edges tracked from the design edge
        self._offset_mm: np.ndarray | None = None
        self._measured: np.ndarray | None = None   # (N,) edges an anchor has measured
        self._offset_spread_mm = 0.0   # the measured edges' offsets' spread about the median
        self._model_mm = self.holder.points_holder_mm
        # the ends of every model edge (2N, 3): P_k, then P_k+1, fitted to the tracked lines
        self._ends_mm = np.concatenate([self._model_mm, np.roll(self._model_mm, -1, axis=0)])
        # the offsets' view-dependent part (dm+b, ``view_model``): the edge model's offset of
        # the innermost rise at each edge end (N, 2) in the current view, for the band fit's
        # radius at each end and its edge shape (None: no model, offsets are lengths)
        self._view_radius_mm: np.ndarray | None = None
        self._view_look = None
        self._delta_mm = np.zeros((len(self.holder.corners_mm), 2))
        #: the view model linearised at the last anchor along the line of sight: (distance
        #: |t| there, the offsets there, their change per relative change of distance)
        self._view_ref: tuple | None = None
        self._anchor_t_mm: np.ndarray | None = None   # where the offsets were measured
        self._anchor_frame = -1
        self._anchor_std = np.zeros(6)   # std of the pose the offsets were measured at
        self._anchors = 0   # measurements of the offsets since the last full measurement
        self._attempts = 0  # re-anchors tried since then
        self._last: Pose | None = None
        self._last_k = -1   # its frame
        #: the motion per frame (R, t) that carries _last on (None: not known)
        self._vel: tuple | None = None
        self._after_full = False   # no frame tracked since the last full measurement
        #: frame times (``update(..., t_s=)``); without them a frame's time is its index
        self._frame_t: dict[int, float] = {}
        self._timed = False
        #: the camera's frame numbers (``update(..., frame_id=)``): messages name frames by
        #: them; without them by the update count
        self._frame_ids: dict[int, int] = {}
        self._named = False
        self._filter_k: int | None = None   # the frame the filter last took
        self._rms_ref = 0.0   # corner RMS of the last accepted full measurement (px)
        self._n = 0
        self._pending: _DeferredAnchor | None = None
        self._pending_full: _DeferredFull | None = None
        if self.filter is not None:
            self.filter.reset()

    def ready(self, timeout_s: float | None = None) -> bool:
        """Wait until the worker process (``anchor_worker="process"`` with ``anchor_lag > 0``)
        has started and imported what it runs (~1-2 s after the tracker was made): call it
        before the approach begins, so that the first deferred job does not queue behind the
        start-up. True when ready (at once without a worker process); False after
        ``timeout_s``, or when the worker failed to start (its jobs then fail and fall back
        with the reason)."""
        warm = getattr(self._executor, "warm", None)
        if warm is None:
            return True
        try:
            warm.result(timeout_s)
        except Exception:  # noqa: BLE001 - a timeout or a dead worker: not ready
            return False
        return True

    def close(self) -> None:
        """End the deferred re-anchors' worker (process or thread), if one was started."""
        if self._executor is not None:
            ex, self._executor = self._executor, None
            ex.shutdown(wait=True, cancel_futures=True)

    def __enter__(self) -> Tracker:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- one frame ---------------------------------------------------------------------
    def update(self, image, t_s: float | None = None,
               frame_id: int | None = None) -> TrackResult:
        """Pose in the next frame (array, raw buffer of the camera's size, or a file).

        ``t_s``: the frame's time (s, the camera's timestamp), for a driver that hands over
        the newest frame and skips those that came while the tracker was busy: the motion is
        then predicted per second, not per frame. ``frame_id``: the camera's frame number
        (increasing; frames skipped by such a driver leave gaps): the result carries it
        (``TrackResult.frame_id``) and the messages name frames by it (a job's take-up, due
        a number of updates on, by that number). Give each for every frame or for none."""
        k = self._n
        res = self._update(image, t_s, frame_id)
        res.frame_id = self._frame_ids.get(k, k)
        return res

    def _update(self, image, t_s, frame_id) -> TrackResult:
        t0 = time.perf_counter()
        img = as_grey_u8(load_frame(image, self.camera))
        k = self._n
        self._stamp(k, t_s, frame_id)
        self._n += 1
        timings: dict[str, float] = {}
        reason = "first frame" if k == 0 else "no previous pose"
        # a deferred fall-back (docs/tracking.md): taken up on its frame, pending before it
        full, note_full, fresh = None, "", False
        if self._pending_full is not None and k >= self._pending_full.at:
            j = self._pending_full.frame
            why, full = self._take_full(k, timings)
            if not why:
                note_full, fresh = f"full measurement of {self._name(j)} applied", True
            elif self._last is not None and self._last_k > j:
                # tracked since frame j: the tracking goes on with the offsets it has
                note_full = f"full measurement of {self._name(j)} not applied ({why})"
            else:
                self._last, reason = None, why
        pending = self._pending_full
        if pending is not None:
            note_full = (f"full measurement of {self._name(pending.frame)} pending "
                         f"(applied {self._due(pending.at, k)})")
        # a deferred re-anchor due on this frame is taken up before the frame is tracked
        why, note = self._take_anchor(k, timings) if self._last is not None else ("", "")
        if why:
            reason = why
        elif self._last is not None:
            try:
                res = self._track(img, k, timings)
            except CutterposeError as e:
                res = None
                reason = f"{type(e).__name__}: {e}"
            else:
                if isinstance(res, str):
                    reason, res = res, None
            if res is not None:
                res.anchor = "; ".join(filter(None, [note_full, note]))
                res.measurement = full
                # the offsets were measured at a pose with its own error, which every tracked
                # pose inherits (zero without offsets)
                if self._offset_mm is not None:
                    res.std_dof = np.hypot(res.std_dof, self._anchor_std)
                if self._anchor_due(res.pose, k):
                    if self.tp.anchor_lag > 0:
                        self._start_anchor(img, res)
                    else:
                        try:
                            res = self._reanchor(img, res, timings)
                        except CutterposeError as e:
                            res = f"re-anchor: {type(e).__name__}: {e}"
                        if isinstance(res, str):
                            reason, res = res, None
            if res is not None:
                self._moved_to(res.pose, k)
                res.timings_ms = timings | {"total": (time.perf_counter() - t0) * 1e3}
                self._filter(res, f"fall-back: {note_full}" if fresh else "")
                return res
            if note_full:
                reason = f"tracking after the {note_full}: {reason}" if fresh else \
                    f"{reason} ({note_full})"
        if pending is not None:
            # its full measurement is on its way: this frame goes without a pose
            return self._no_pose(k, reason, None, timings, t0, forget=False)
        # full measurement (a pending re-anchor belongs to the poses before it: a band fit
        # still queued on the worker is not run, one running is left to finish unread)
        if self._pending is not None:
            self._pending.future.cancel()
        self._pending = None
        if k > 0 and self.tp.anchor_lag > 0 and self.tp.defer_fallbacks:
            return self._start_full(img, k, reason, timings, t0)
        t1 = time.perf_counter()
        m = full_measurement(img, self.camera, self.holder, self.method, self.params,
                             self.limits, self.edge_look)
        timings["full"] = (time.perf_counter() - t1) * 1e3
        if not m.ok:
            return self._no_pose(k, f"{reason}; full measurement: {m.quality.reason}", m,
                                 timings, t0)
        self._accept_full(img, k, m)
        res = TrackResult(k, "full", m.pose, m.std_dof, True, reason,
                          rms_px=m.quality.rms_px, corners_px=m.corners_px, measurement=m)
        self._filter(res, f"fall-back: {reason}" if k else "first pose")
        res.timings_ms = timings | {"total": (time.perf_counter() - t0) * 1e3}
        return res

    def _stamp(self, k: int, t_s: float | None, frame_id: int | None = None) -> None:
        """Keep frame ``k``'s time (its index without timestamps) and camera frame number,
        both checked before either is kept: given for every frame or none, increasing."""
        if frame_id is not None:
            try:
                frame_id = operator.index(frame_id)
            except TypeError:
                raise InputError(f"frame_id must be an integer, got {frame_id!r}") from None
        t = None if t_s is None else float(t_s)
        checks = (("frame_id", frame_id, "_named", self._frame_ids, 0),
                  ("t_s", t, "_timed", self._frame_t, -math.inf))
        for name, value, flag, store, low in checks:
            given = value is not None
            if k > 0 and given != getattr(self, flag):
                raise InputError(f"give {name} for every frame of a track or for none (frame "
                                 f"{k}: {'given' if given else 'missing'})")
            prev = store.get(k - 1)
            if given and not (math.isfinite(value) and value >= low
                              and (prev is None or value > prev)):
                floor = f", >= {low}" if low > -math.inf else ""
                raise InputError(f"{name} must be finite{floor} and increase: frame {k} has "
                                 f"{value} after {prev}")
        for _, value, flag, store, _ in checks:
            setattr(self, flag, value is not None)
            if value is not None:
                store[k] = value
        self._prune_times(k)

    def _prune_times(self, k: int) -> None:
        """Keep the times of the frames something refers to (this and the previous frame,
        the last pose's, the filter's, the deferred jobs'), however far back they lie (a
        holder out of sight for minutes while a fall-back is pending); forget the rest."""
        keep = {k, k - 1, self._last_k, self._filter_k}
        if self._pending is not None:
            keep.add(self._pending.frame)
        if self._pending_full is not None:
            keep |= {self._pending_full.frame, self._pending_full.last_k}
        keep.discard(None)
        if len(self._frame_t) > len(keep):
            self._frame_t = {x: t for x, t in self._frame_t.items() if x in keep}
        if len(self._frame_ids) > len(keep):
            self._frame_ids = {x: i for x, i in self._frame_ids.items() if x in keep}

    def _name(self, j: int) -> str:
        """Frame ``j`` (update count) as the messages name it: by the camera's number when
        the frames have them."""
        return f"frame {self._frame_ids.get(j, j)}" if self._named else f"frame {j}"

    def _due(self, at: int, k: int) -> str:
        """When a job due on update ``at`` is taken up, seen from update ``k``: the frame
        (update count), or with camera numbers, whose future ones are not known, how many
        frames on."""
        return f"{at - k} frames later" if self._named else f"at frame {at}"

    def _time(self, k: int) -> float:
        """Frame ``k``'s time: its timestamp (s) or, without timestamps, its index."""
        return self._frame_t[k] if self._timed else float(k)

    def _motion(self, a: Pose, ka: int, b: Pose, kb: int) -> tuple | None:
        """The motion per unit of time (a frame, or a second with timestamps) from pose
        ``b`` on frame ``kb`` to pose ``a`` on frame ``ka``: the same twist in each unit."""
        gap = self._time(ka) - self._time(kb)
        if not gap > 0:
            return None
        R, t = _relative(a, b)
        return (R, t) if gap == 1.0 else se3_exp(se3_log(R, t) / gap)

    def _moved_to(self, pose: Pose, k: int) -> None:
        """``pose`` on frame ``k`` is the last one; the motion since the one before (over a
        gap of frames without a pose: the same twist in each unit of time)."""
        if self._last is not None and k > self._last_k:
            self._vel = self._motion(pose, k, self._last, self._last_k)
        self._last, self._last_k = pose, k
        self._after_full = False

    def _no_pose(self, k: int, reason: str, m: Measurement | None, timings: dict,
                 t0: float, forget: bool = True) -> TrackResult:
        """A frame without a pose ("lost"): the filter forgets its state, and with ``forget``
        the tracker its last pose (without: a deferred fall-back is on its way, and the next
        frames are tracked from the last pose meanwhile)."""
        if forget:
            self._last = None
        res = TrackResult(k, "lost", None, np.full(6, np.nan), False, reason, measurement=m)
        if self.filter is not None:
            self.filter.reset()
            self._filter_k = None
            res.filter_reset = "lost"
        res.timings_ms = timings | {"total": (time.perf_counter() - t0) * 1e3}
        return res

    def _accept_full(self, img: np.ndarray, k: int, m: Measurement) -> None:
        """Start again from an accepted full measurement of frame ``k`` (``img``): its pose,
        the velocity unknown."""
        # a method that refines dm+'s pose with more than the corners (dm+b: the design
        # edge from the bands): the tracker follows the edges the corners come from (the
        # innermost rise), so it measures here, at the measured design pose, how far
        # each of them lies from the design edge (docs/tracking.md, "Broken edges")
        refines = self._refines
        start = m.estimate.info.get("start") if refines and m.estimate else None
        # the residual the tracked edges are held to: the corners' (dm+'s, for dm+b,
        # which starts from the outline and fits no corners itself)
        rms = start.residual_px if start is not None else m.quality.rms_px
        if refines and not np.isfinite(rms) and m.features is not None:
            rms = corner_residual_px(m.features, self.camera, self.holder, self.limits)
        self._rms_ref = float(rms) if np.isfinite(rms) else 0.0
        if refines:
            self._anchor_full(img, k, m)
        self._last, self._last_k, self._vel = m.pose, k, None
        self._after_full = True

    # -- deferred fall-backs -------------------------------------------------------------
    def _start_full(self, img: np.ndarray, k: int, reason: str, timings: dict,
                    t0: float) -> TrackResult:
        """A fall-back measured beside the tracking (docs/tracking.md, "Jobs beside the
        tracking"): this frame is answered at once without a pose, the next ones are tracked
        from the last pose meanwhile."""
        at = k + self.tp.anchor_lag
        fut = self._submit(full_measurement, img, self.camera, self.holder, self.method,
                           self.params, self.limits, self.edge_look)
        # the last pose and motion before the failure carry the measured pose to frame ``at``;
        # the frame itself is kept for the offsets of a method that has them (dm+b, dm+r)
        keep = np.array(img, copy=True) if self._refines else None
        self._pending_full = _DeferredFull(at, k, fut, keep, self._last, self._last_k,
                                           self._vel)
        return self._no_pose(k, f"{reason}; full measurement started (applied "
                                f"{self._due(at, k)})", None, timings, t0, forget=False)

    def _take_full(self, k: int, timings: dict) -> tuple[str, Measurement | None]:
        """Take up the deferred full measurement due on frame ``k`` (waiting for it):
        ``("", measurement)`` with the offsets measured from its frame at its pose, and the
        frame tracked from that pose carried to it by the motion per frame of the poses
        tracked since (or before the failure; or, unknown, from the last pose before it to
        the measured one); or ``(reason, measurement or None)`` when it cannot be applied."""
        p, self._pending_full = self._pending_full, None
        j, fut, img_j, last, last_k, vel = p.frame, p.future, p.image, p.last, p.last_k, p.vel
        t = time.perf_counter()
        try:
            m = fut.result()
        except CutterposeError as e:
            return f"full measurement ({self._name(j)}): {type(e).__name__}: {e}", None
        except BrokenProcessPool as e:
            self.close()
            return (f"full measurement ({self._name(j)}): the worker process failed ({e})",
                    None)
        finally:
            timings["full_wait"] = (time.perf_counter() - t) * 1e3
        timings["full"] = float(m.timings_ms.get("total", math.nan))
        if not m.ok:
            return f"full measurement ({self._name(j)}): {m.quality.reason}", m
        # the poses tracked since frame j rest on the offsets before it: their motion per
        # frame carries the measured pose (a pose of theirs with the new offsets would be
        # off by the offsets' change: 2-3 px on worn holders)
        since = self._vel if self._last is not None and self._last_k > j else None
        self._accept_full(img_j, j, m)
        if since is not None:
            self._vel = since
        elif vel is not None:
            self._vel = vel
        elif last is not None and j > last_k:
            self._vel = self._motion(m.pose, j, last, last_k)
        return "", m

    # -- broken edges: the tracked edges' offsets from the design edge --------------------
    def _anchor_full(self, img: np.ndarray, k: int, m: Measurement) -> None:
        """The offsets from the tracker's own edges in this frame, found from the fully
        measured design pose (the innermost rise of a broken edge, as tracking will see it).
        When those edges fail tracking's checks, the previous offsets are kept and the next
        tracked frame measures them again. With none yet, the lines found round the measured
        pose give them: the checks fit the model, and without offsets the model is what is
        off (a chipped edge's line 2.6 mm out of the design edge sat 8 px off it at 900 mm,
        and no frame could be tracked until a second full measurement's anchor passed)."""
        self._last, self._last_k, self._vel = m.pose, k, None
        self._set_view_model(m.edge_band)
        try:
            res = self._track(img, k, {})
        except CutterposeError:
            res = None
        self._anchors = self._attempts = 0
        if isinstance(res, TrackResult):
            self._set_offsets(m.pose, *self._anchor_lines(res), m.std_dof, k, 1.0)
            return
        self._anchor_t_mm = None
        if self._offset_mm is None:
            tp = self.tp
            found = self._lines_at(img, m.pose, tp.band_half_width_px * tp.cold_band_factor)
            if isinstance(found, str):
                return
            lines, seen, _ = found
            fam = np.bincount(np.nonzero(seen)[0] % 2, minlength=2)
            if seen.sum() >= tp.lines_needed(len(seen)) and fam.min() >= 2:
                self._set_offsets(m.pose, lines, seen, m.std_dof, k, 1.0)

    def _anchor_due(self, pose: Pose, k: int) -> bool:
        """A re-anchor on this tracked frame (``dm+b`` only: its band fit needs nothing but
        the image and a close pose)?"""
        if self.method != "dm+b" or self._pending is not None or \
                self._pending_full is not None:
            return False
        tp = self.tp
        if self._anchor_t_mm is None or self._attempts < tp.anchor_warmup:
            return True
        scale = float(np.linalg.norm(pose.t_mm) / np.linalg.norm(self._anchor_t_mm))
        return (abs(scale - 1.0) > tp.anchor_scale_change
                or (tp.anchor_every > 0 and k - self._anchor_frame >= tp.anchor_every))

    def _set_view_model(self, band) -> None:
        """The edge model the offsets follow the view with (``view_model``), from a band fit
        (:class:`~cutterpose.solvers.edge_band.BandPose`; None keeps the last): the fit's
        median radius over its segments at every edge end and its edge shape, with the nominal
        photometry (the shipped offset grid's). One radius, not each edge's: an edge's own
        radius rests on its four segments, and a wrong one (3.98 mm among 0.2-0.4 on the
        analytic ``field`` approach) put that edge's model 0.86 mm inside and the tracker
        lost it; the common trend, a depth error, is the part that matters (docs/RESULTS.md
        section 14)."""
        if not self.tp.view_model or band is None:
            return
        r = band.fit.radius_median_mm
        if not np.isfinite(r):
            return
        self._view_radius_mm = np.full((len(self.holder.corners_mm), 2), float(r))
        self._view_look = em.EdgeLook(shape=band.fit.best.look.shape)

    def _view_delta(self, pose: Pose) -> np.ndarray | None:
        """The edge model's outward offsets (N, 2; mm in the face plane) of the innermost rise
        at every edge end seen with ``pose``; zeros without a model, None where the view lies
        outside the shipped offset grid (the caller keeps the last)."""
        if self._view_radius_mm is None:
            return np.zeros_like(self._delta_mm)
        view = em.edge_views(pose.R, pose.t_mm, self.K, self.holder, self._view_look)
        w = em.tabulated_w_px(self._view_radius_mm[..., None], view, self._view_look)
        if w is None or not np.all(np.isfinite(w)):
            return None
        return w[..., 0] / view.a_s

    def _follow_view(self, pose: Pose) -> None:
        """The moved model at ``pose``'s distance: the view model linearised at the last
        anchor (``_view_ref``), followed up to ``VIEW_REACH`` of its distance."""
        if self._view_ref is None or self._offset_mm is None:
            return
        s_a, d_a, g = self._view_ref
        u = float(np.clip(np.linalg.norm(pose.t_mm) / s_a - 1.0, -VIEW_REACH, VIEW_REACH))
        self._set_model(d_a + g * u)

    def _set_model(self, delta_mm: np.ndarray) -> None:
        """The moved model (``_model_mm``, ``_ends_mm``) from the carried offsets and the
        view's part ``delta_mm``."""
        self._delta_mm = delta_mm
        if self._offset_mm is None:
            return
        c = np.asarray(self.holder.corners_mm, float)
        # corner i's ends: (i, 0) of edge i - 1, (i, 1) of edge i -> per edge (start, end)
        dv = np.column_stack([self._delta_mm[:, 1], np.roll(self._delta_mm[:, 0], -1)])
        off = self._offset_mm + dv
        self._model_mm = offset_polygon_mm(c, off)
        # one offset per edge: the moved polygon's corners are its edges' ends (as before the
        # ends had offsets of their own)
        self._ends_mm = offset_edge_ends_mm(c, off) if self.tp.anchor_ends else \
            np.concatenate([self._model_mm, np.roll(self._model_mm, -1, axis=0)])

    def _set_offsets(self, pose: Pose, lines: np.ndarray, seen: np.ndarray, std_dof,
                     k: int, gain: float, band=None) -> None:
        """Each seen edge's offsets (mm, face plane, outward normal) from the design edge: the
        shift of each end of design edge ``k`` that puts it, projected at the design ``pose``,
        on the tracked line (Newton; ``anchor_ends=False``: one shift for both ends, least
        squares), weighted by ``gain`` against the offsets carried; an edge not seen keeps its
        last offsets (the seen edges' median the first time)."""
        c = np.asarray(self.holder.corners_mm, float)
        ks = np.nonzero(seen)[0]
        if len(ks) == 0:
            return
        d = line_offsets_mm(pose, lines, seen, self.holder, self.K, self.tp.anchor_ends)[ks]
        # what is carried is the part the view does not explain (the measured offsets minus
        # the edge model's at this pose); without a model, the offsets themselves
        self._set_view_model(band)
        delta = self._view_delta(pose)
        delta = self._delta_mm if delta is None else delta
        self._view_ref = None
        if self._view_radius_mm is not None:
            # the model's slope along the approach: the camera 5 % closer on its line of sight
            # (between anchors the view changes mostly by the distance; evaluating the model
            # at each frame's own pose would add the pose's noise in rotation to the offsets)
            near = self._view_delta(Pose(pose.R, pose.t_mm * (1.0 - VIEW_STEP)))
            if near is not None:
                self._view_ref = (float(np.linalg.norm(pose.t_mm)), delta,
                                  (delta - near) / VIEW_STEP)
        d = d - np.column_stack([delta[:, 1], np.roll(delta[:, 0], -1)])[ks]
        if self._offset_mm is None:
            off, gain = np.full((len(c), 2), float(np.median(d))), 1.0
        else:
            off = self._offset_mm.copy()
        off[ks] += gain * (d - off[ks])
        self._offset_mm = off
        if self._measured is None:
            self._measured = np.zeros(len(c), bool)
        self._measured[ks] = True
        v = off[self._measured].mean(axis=1)
        self._offset_spread_mm = float(1.4826 * np.median(np.abs(v - np.median(v))))
        self._set_model(delta)
        self._anchor_t_mm, self._anchor_frame = pose.t_mm.copy(), k
        self._anchor_std = np.where(np.isfinite(std_dof), std_dof, 0.0)
        self._anchors += 1

    def _anchor_lines(self, res: TrackResult) -> tuple[np.ndarray, np.ndarray]:
        """The lines an anchor measures the offsets of: the edges the tracked pose rests on
        and every edge found whose offset has not been measured yet (fitted by its direction
        until then, :meth:`_weigh_unmeasured`; one left out as an outlier keeps its offset)."""
        new = res.edges_found & ~(self._measured if self._measured is not None
                                  else np.zeros_like(res.edges_found))
        return res.lines_found, res.edges_used | new

    def _band_args(self, pose: Pose, edges_used: np.ndarray) -> tuple:
        """The arguments of :func:`band_fit` after the image (all picklable)."""
        return (self.camera, self.holder, pose, edges_used,
                EDGE_SHAPE_FITS[self.limits.edge_shape], self.tp.anchor_passes,
                as_band_looks(self.edge_look), self.limits)

    def _band_fit(self, img: np.ndarray, pose: Pose, edges_used: np.ndarray):
        """The re-anchor's band fit here (:func:`band_fit`)."""
        return band_fit(img, *self._band_args(pose, edges_used))

    def _apply_band(self, est, q, frame: int, pose: Pose, std_dof: np.ndarray,
                    lines: np.ndarray, edges_used: np.ndarray) -> tuple[str, str]:
        """Take up a re-anchor's band fit of frame ``frame`` (tracked ``pose``, ``lines``):
        ``("", "re-anchored")`` with the offsets measured, ``("", "re-anchor refused ...")``
        with the offsets kept, or ``(reason, "")`` when the band's design edge and the
        tracked pose disagree (the frame is then measured in full)."""
        if not q.ok:
            return "", f"re-anchor refused ({q.reason}): the last offsets kept"
        band = Pose(est.R_cam_holder, est.t_cam_holder_mm)
        std_band = q.budget.std_dof
        diff = band.dof - pose.dof
        diff[:3] = wrap_deg(diff[:3])
        z = np.abs(diff) / np.hypot(std_band, std_dof)
        j = int(np.argmax(z))
        if not z[j] <= self.tp.anchor_gate_sigma:
            return (f"re-anchor: the band's design edge and the tracked pose differ by "
                    f"{diff[j]:.3g} {DOF_NAMES[j].split('_')[1]} in {DOF_NAMES[j]} ({z[j]:.1f} "
                    f"std > {self.tp.anchor_gate_sigma}): the tracking or the band fit is "
                    "wrong"), ""
        self._set_offsets(band, lines, edges_used, std_band, frame,
                          max(self.tp.anchor_gain, 1.0 / (self._anchors + 1)),
                          est.info.get("band"))
        return "", "re-anchored"

    def _reanchor(self, img: np.ndarray, res: TrackResult, timings: dict) -> TrackResult | str:
        """Measure the design edge again on a tracked frame (docs/tracking.md, "Broken
        edges"): the band fit from the tracked pose, judged by its own verdict and against the
        tracked pose; the offsets measured from this frame's tracked edges at the band's pose
        and the edges fitted again with them. The tracked frame (or, when the two poses
        disagree, the reason for a full measurement)."""
        t = time.perf_counter()
        # whatever the outcome, the next attempt after the view has changed as much again
        self._anchor_t_mm, self._anchor_frame = res.pose.t_mm.copy(), res.frame
        self._attempts += 1
        lines, used = self._anchor_lines(res)
        est, q, timings["anchor"] = self._band_fit(img, res.pose, used)
        why, note = self._apply_band(est, q, res.frame, res.pose, res.std_dof, lines, used)
        if why:
            return why
        if note != "re-anchored":
            res.anchor = note
            return res
        # the same edges fitted again with the new offsets, and checked as every tracked frame
        fit = self._fit_lines_pose(res.pose, lines, used)
        if isinstance(fit, str):
            return f"re-anchor: {fit}"
        pose, r, _, J, J2 = fit
        why = self._check(pose, r, J, J2, used)
        if isinstance(why, str):
            return f"re-anchor: {why}"
        res.rms_px, std = why
        res.pose, res.std_dof = pose, np.hypot(std, self._anchor_std)
        res.edges_used, res.lines_seen = used, int(used.sum())
        res.lines_ideal = np.where(used[:, None], lines, np.nan)
        res.anchor = "re-anchored"
        timings["anchor"] = (time.perf_counter() - t) * 1e3
        return res

    def _start_anchor(self, img: np.ndarray, res: TrackResult) -> None:
        """A deferred re-anchor of this tracked frame (docs/tracking.md): the band fit started
        (in the background thread, or here), its result applied ``anchor_lag`` frames on."""
        self._anchor_t_mm, self._anchor_frame = res.pose.t_mm.copy(), res.frame
        self._attempts += 1
        lines, used = self._anchor_lines(res)
        lines, used = lines.copy(), used.copy()
        fut = self._submit(band_fit, img, *self._band_args(res.pose, used))
        at = res.frame + self.tp.anchor_lag
        self._pending = _DeferredAnchor(at, fut, res.frame, res.pose, res.std_dof.copy(),
                                        lines, used)
        res.anchor = "; ".join(filter(None, [res.anchor,
                                             "re-anchor started (applied "
                                             f"{self._due(at, res.frame)})"]))

    def _submit(self, fn, img: np.ndarray, *args) -> Future:
        """``fn(img, *args)`` (:func:`band_fit` or :func:`full_measurement`) on the
        ``anchor_worker``: its future."""
        if self.anchor_worker == "process":
            if self._executor is not None and self._executor.shape != img.shape:
                self.close()     # frames of another size than the camera's (a test's crop)
            if self._executor is None:
                self._executor = AnchorProcess(img.shape, self.camera, self.holder,
                                               self.params)
            return self._executor.submit(fn, img, *args)
        if self.anchor_worker == "thread":
            if self._executor is None:
                self._executor = ThreadPoolExecutor(1, thread_name_prefix="cutterpose-anchor")
            # the caller may reuse its frame buffer (a camera driver's): the thread reads a copy
            return self._executor.submit(fn, np.array(img, copy=True), *args)
        fut = Future()
        try:
            fut.set_result(fn(img, *args))
        except CutterposeError as e:
            fut.set_exception(e)
        return fut

    def _take_anchor(self, k: int, timings: dict) -> tuple[str, str]:
        """Take up the deferred re-anchor due on frame ``k`` (waiting for its band fit):
        ``(reason for a full measurement or "", note for this frame)``."""
        if self._pending is None or k < self._pending.at:
            return "", ""
        p, self._pending = self._pending, None
        fut, j, pose, std, lines, used = p.future, p.frame, p.pose, p.std, p.lines, p.used
        t = time.perf_counter()
        try:
            est, q, fit_ms = fut.result()
        except CutterposeError as e:
            return f"re-anchor ({self._name(j)}): {type(e).__name__}: {e}", ""
        except BrokenProcessPool as e:   # the worker died: a new one at the next re-anchor
            self.close()
            return (f"re-anchor ({self._name(j)}): the band fit's worker process failed "
                    f"({e})", "")
        finally:
            timings["anchor_wait"] = (time.perf_counter() - t) * 1e3
        timings["anchor_fit"] = fit_ms
        why, note = self._apply_band(est, q, j, pose, std, lines, used)
        name = self._name(j)
        if why:
            return why.replace("re-anchor:", f"re-anchor ({name}):", 1), ""
        return "", note.replace("re-anchor", f"re-anchor ({name})", 1) \
            if note != "re-anchored" else f"re-anchored ({name})"

    def _filter(self, res: TrackResult, force: str) -> None:
        if self.filter is not None and res.pose is not None:
            k0 = self._filter_k
            dt = self._time(res.frame) - self._time(k0) if k0 is not None else 1.0
            res.filtered_pose, res.filter_reset = self.filter.update(res.pose, force, dt)
            self._filter_k = res.frame

    def predict(self, t_s: float | None = None) -> Pose | None:
        """The pose predicted for the next frame, or (a track with timestamps) at time
        ``t_s``: the last pose moved on by the last motion, when that is known."""
        if self._timed != (t_s is not None):
            raise InputError("predict: give t_s exactly when the frames have timestamps")
        if self._last is None:
            return None
        dt = (float(t_s) if self._timed else float(self._n)) - self._time(self._last_k)
        return self._carried(dt)

    def _predict(self, k: int) -> Pose | None:
        """The pose predicted for frame ``k`` (already stamped)."""
        return self._carried(self._time(k) - self._time(self._last_k))

    def _carried(self, dt: float) -> Pose:
        """The last pose moved on by the last motion over ``dt`` units of time (whole frames
        one step at a time, as the motion was measured; else on the twist)."""
        pose = self._last
        if self._vel is None or not dt > 0:
            return pose
        if float(dt).is_integer() and dt <= 64:
            for _ in range(int(dt)):
                pose = _left(*self._vel, pose)
            return pose
        R, t = se3_exp(se3_log(*self._vel) * dt)
        return _left(R, t, pose)

    def _project(self, pose: Pose) -> np.ndarray | None:
        """The model corners projected with ``pose`` (ideal px, holder order); None if the
        holder is behind the camera."""
        X = pose.apply(self._model_mm)
        if np.any(X[:, 2] <= 0):
            return None
        return X[:, :2] / X[:, 2:3] @ self.K[:2, :2].T + self.K[:2, 2]

    def _line_params(self, half_width_px: float, shift_px: float) -> FeatureParams:
        """The field chain's line parameters for a band of +-``half_width_px`` about the
        predicted edges; a seen line lies within ``shift_px`` of its prediction (plus the
        field chain's outward allowance for a broken edge, capped by the band)."""
        key = (half_width_px, shift_px)
        p = self._line_cache.get(key)
        if p is None:
            out = min(self._refine_params.max_outward_shift_px,
                      max(half_width_px - shift_px - 1.0, 0.0))
            p = replace(self._refine_params, refine_half_width_px=half_width_px,
                        max_line_shift_px=shift_px, max_outward_shift_px=out,
                        min_line_support=self.tp.min_support,
                        corner_trim_px=max(self.tp.end_trim_px, half_width_px + 4.0))
            self._line_cache[key] = p
        return p

    def _lines_at(self, img: np.ndarray, pose: Pose, hw: float, lap=None):
        """The tracked edges' lines (ideal px) in bands of +-``hw`` px round the model
        projected with ``pose``: ``(lines, seen, support)``, or why there are none."""
        tp = self.tp
        corners_pred = self._project(pose)
        if corners_pred is None:
            return "the predicted holder is behind the camera"
        pred_px = self.camera.distort_px(corners_pred)
        if not np.all(self.camera.in_image(pred_px, 2 * hw)):
            return "the predicted holder leaves the image"
        # a crop round the predicted pocket (float32: sub-pixel grey-level profiles)
        m = hw + 4.0
        u0, v0 = np.maximum(np.floor(pred_px.min(axis=0) - m), 0).astype(int)
        u1, v1 = np.ceil(pred_px.max(axis=0) + m + 1).astype(int)
        sub = img[v0:v1, u0:u1].astype(np.float32)
        if lap is not None:
            lap("predict")
        # the field chain's lines: innermost rise, LMedS + Tukey, support and shift gates
        lines, seen, _, support, _ = robust_edge_lines(
            sub, np.array([u0, v0], float), self.camera, corners_pred,
            self._line_params(hw, tp.shift_fraction * hw))
        if lap is not None:
            lap("edges")
        return lines, seen, support

    def _track(self, img: np.ndarray, k: int, timings: dict) -> TrackResult | str:
        t = time.perf_counter()

        def lap(name):
            nonlocal t
            now = time.perf_counter()
            timings[name] = timings.get(name, 0.0) + (now - t) * 1e3
            t = now

        tp = self.tp
        n = len(self._model_mm)
        pose = self._predict(k)
        self._follow_view(pose)
        # no velocity yet (second frame), or the first frame after a full measurement (its
        # offsets are new; one edge may still sit ~2-3 px off a worn holder's model): a
        # wider band, and its wider centring limit
        cold = self._vel is None or self._after_full
        hw = tp.band_half_width_px * (tp.cold_band_factor if cold else 1.0)
        passes = dropped = 0
        for _ in range(tp.max_passes):
            passes += 1
            found_at = self._lines_at(img, pose, hw, lap)
            if isinstance(found_at, str):
                return found_at
            lines, seen, support = found_at
            # an edge whose offset no anchor has measured yet (hidden then) has only the
            # others' median offset, millimetres off on a worn holder: its position counts as
            # far as the measured offsets agree (:meth:`_weigh_unmeasured`), its direction in
            # full; the next anchor measures it
            found, lines_found = seen, lines
            new = seen & ~self._measured if self._measured is not None else None
            fam = np.bincount(np.arange(n)[seen] % 2, minlength=2)
            if seen.sum() < tp.lines_needed(n) or fam.min() < 2:
                worst = int(np.argmin(support))
                return (f"only {int(seen.sum())} of {n} edges seen (< {tp.lines_needed(n)}, or < 2 "
                        f"per direction; least-supported edge {worst}: "
                        f"{100 * support[worst]:.0f} % of it): jump, occlusion or lost edges")
            start = pose
            for _ in range(tp.max_dropped_lines + 1):
                fit = self._fit_lines_pose(start, lines, seen, new)
                if isinstance(fit, str):
                    return fit
                pose, r, r_start, J, J2 = fit
                # a line far off the rigid model while the others fit rests on something else
                # (a lump's outline, the cutter, the wrong rise): leave it out and fit again
                ks = np.nonzero(seen)[0]
                misfit = np.maximum(np.abs(r[:len(ks)]), np.abs(r[len(ks):]))
                worst = int(np.argmax(misfit))
                bar = max(tp.line_outlier_px, tp.line_outlier_factor * float(np.median(misfit)))
                if misfit[worst] <= bar or seen.sum() <= tp.lines_needed(n):
                    break
                seen = seen.copy()
                seen[ks[worst]] = False
                lines = lines.copy()
                lines[ks[worst]] = np.nan
                dropped += 1
            lap("solve")
            # how far the fit moved the bands' centres (the model's edges, along their
            # normals): profiles sampled off-centre cut a rise at the band's end (a biased
            # edge), so once more, centred on the fitted pose. Not how far the edges lie from
            # the model: a worn edge whose break varies along it lies a few px off the rigid
            # model however the bands are centred (the residual checks judge that)
            moved = _bands_moved_px(r_start, r)
            if moved <= tp.centred_fraction * hw:
                break
        else:
            return (f"the bands did not settle: the pose fit moved the edges by {moved:.1f} px "
                    f"on the last of {tp.max_passes} passes (> "
                    f"{tp.centred_fraction * hw:.1f} px): the prediction is too far off")
        why = self._check(pose, r, J, J2, seen, new)
        if isinstance(why, str):
            return why
        rms, std = why
        lap("check")
        X = intersect_consecutive(np.where(np.isfinite(lines), lines, 0.0))
        corners_ideal = np.roll(X, 1, axis=0)   # corner i: edges i - 1 and i
        visible = seen & np.roll(seen, 1)
        corners_px = np.full((n, 2), np.nan)
        corners_px[visible] = self.camera.distort_px(corners_ideal[visible])
        res = TrackResult(k, "track", pose, std, True, "", rms_px=rms,
                          edge_support=float(support[seen].min()), corners_px=corners_px,
                          lines_seen=int(seen.sum()), corners_used=int(visible.sum()),
                          lines_dropped=dropped, lines_ideal=lines, edges_used=seen,
                          lines_found=lines_found, edges_found=found)
        res.passes = passes
        return res

    def _fit_lines_pose(self, pose: Pose, lines: np.ndarray, seen: np.ndarray,
                        new: np.ndarray | None = None, iterations: int = 8):
        """Gauss-Newton on the model-to-line distances: for every seen edge ``k`` (from model
        corner ``k`` to ``k + 1``), the signed distances of both projected ends to the edge's
        line (ideal px); edges not seen are left out, so that a corner whose other edge is
        hidden still counts through its seen one (Drummond & Cipolla 2002: distances along
        the edge normals). Parameters: the six DOFs. ``new``: the edges whose offsets were not
        measured (:meth:`_weigh_unmeasured`). Returns the pose, the residuals at the end
        (weighted) and at the start (each (2 m,)) and the final Jacobian (2 m, 6), or a
        reason."""
        n = len(self._model_mm)
        ks = np.nonzero(seen)[0]
        rows = np.concatenate([ks, n + ks])        # of the ends (P_k, P_k+1) of all edges
        L = np.concatenate([lines[ks], lines[ks]])
        Pe = self._ends_mm[rows]
        sel = np.nonzero(new[ks])[0] if new is not None else np.zeros(0, int)

        def residuals(ps: Pose):
            X = ps.apply(Pe)
            if np.any(X[:, 2] <= 0):
                return None
            uv = X[:, :2] / X[:, 2:3] @ self.K[:2, :2].T + self.K[:2, 2]
            return L[:, 0] * uv[:, 0] + L[:, 1] * uv[:, 1] + L[:, 2]

        r = residuals(pose)
        if r is None:
            return "the predicted holder is behind the camera"
        # where the edges lie from the bands' centres (an unmeasured edge's position as far as
        # it is known)
        r0 = self._weigh_unmeasured(pose, ks, sel, L, r)[0] if len(sel) else r
        dof = pose.dof
        for _ in range(iterations):
            J2 = self._end_jacobian(pose)
            J = L[:, 0:1] * J2[0::2][rows] + L[:, 1:2] * J2[1::2][rows]
            if len(sel):
                r, J = self._weigh_unmeasured(pose, ks, sel, L, r, J)
            try:
                step = np.linalg.lstsq(J, -r, rcond=None)[0]
            except np.linalg.LinAlgError:
                return "the pose fit failed: singular normal equations"
            dof = dof + step
            try:
                pose = Pose.from_euler(*dof)
            except InputError as e:
                return f"the pose fit failed: {e}"
            r = residuals(pose)
            if r is None:
                return "the fitted holder is behind the camera"
            # converged: the last step is far below the std (>= ~0.005 mm / deg here)
            if np.all(np.abs(step) < 1e-4):
                break
        if len(sel):
            r = self._weigh_unmeasured(pose, ks, sel, L, r, J)[0]
        # the Jacobian of the last step (its pose differs from the result by < 1e-4)
        return pose, r, r0, J, J2

    def _weigh_unmeasured(self, pose: Pose, ks: np.ndarray, sel: np.ndarray, L: np.ndarray,
                          r: np.ndarray, J: np.ndarray | None = None) -> tuple:
        """Residuals and Jacobian rows (start rows, then end rows, of the edges ``ks``) with
        the edges ``ks[sel]``, whose offsets no anchor has measured, weighted as edges with
        an unknown offset ``o`` of prior std ``s_o`` (the measured edges' spread about their
        median, which the unmeasured ones carry): ``o`` moves the pair of end residuals along
        ``g`` (their derivatives w.r.t. ``o``), so that component gets the weight
        ``sqrt(s^2 / (s^2 + |g|^2 s_o^2))`` (``s``: ``LINE_SCALE_PX``, a tracked line's
        scatter about the model) and the orthogonal one, the edge's direction, the weight 1. Equal
        offsets (a uniform break) keep the edge's position; a worn holder's, which differ
        by millimetres, keep its direction only."""
        m = len(ks)
        i = np.concatenate([sel, sel + m])
        k = np.concatenate([ks[sel], ks[sel]])
        ends = self._ends_mm[np.concatenate([ks[sel], len(self._model_mm) + ks[sel]]), :2]
        g = _offset_slope(pose, ends, self.holder.edge_normals[k], L[i], self.K)[1]
        q = len(sel)
        gs, ge = g[:q], g[q:]
        gn = np.hypot(gs, ge)
        us, ue = gs / gn, ge / gn
        s2 = LINE_SCALE_PX ** 2
        c = 1.0 - np.sqrt(s2 / (s2 + gn ** 2 * self._offset_spread_mm ** 2))
        r = r.copy()
        a, b = sel, sel + m
        pr = us * r[a] + ue * r[b]
        r[a] -= c * us * pr
        r[b] -= c * ue * pr
        if J is None:
            return r, None
        J = J.copy()
        pj = us[:, None] * J[a] + ue[:, None] * J[b]
        J[a] -= (c * us)[:, None] * pj
        J[b] -= (c * ue)[:, None] * pj
        return r, J

    def _end_jacobian(self, pose: Pose) -> np.ndarray:
        """Pixel Jacobian (80, 6) of both ends of every edge (``P_k``, then ``P_k+1``)."""
        return pixel_jacobian(pose.R, pose.t_mm, self._ends_mm, self.K)[0]

    def _check(self, pose: Pose, r: np.ndarray, J: np.ndarray, J2: np.ndarray,
               seen: np.ndarray, new: np.ndarray | None = None):
        """The checks of a tracked pose (module doc, step 4) on the model-to-line distances
        ``r`` (Jacobian ``J`` w.r.t. the DOFs): ``(rms_px, std_dof)`` when it passes, else
        the reason. The std is the Gauss-Newton covariance ``s^2 (J^T J)^-1``."""
        tp = self.tp
        rms = float(np.sqrt(np.mean(r ** 2)))
        # the limits follow the residual of the last full measurement (broken edges image
        # off the rigid model by a share of their width that varies along the contour: a
        # residual of the holder, not of the tracking)
        rms_max = max(tp.max_rms_px, tp.rms_ref_factor * self._rms_ref)
        res_max = max(tp.max_corner_residual_px, 2.5 * rms_max)
        if rms > rms_max:
            return (f"model-to-edge RMS {rms:.2f} px > {rms_max:.2f} px: the tracked edges do "
                    "not fit the holder")
        ks = np.nonzero(seen)[0]
        j = int(np.argmax(np.abs(r)))
        if abs(r[j]) > res_max:
            return (f"an end of edge {ks[j % len(ks)]} is {abs(r[j]):.2f} px off its line "
                    f"(> {res_max:.2f} px)")
        s2 = float(r @ r) / max(r.size - 6, 1)
        std = np.sqrt(np.clip(np.diag(s2 * np.linalg.inv(J.T @ J)), 0, None))
        # the edges left out cost information: a DOF that the seen edges pin down much worse
        # than all of them would (a short edge family lost, far away) is not the full
        # measurement's accuracy, so the frame is measured in full
        ratio = self._std_ratio(pose, seen, J2, new)
        j = int(np.argmax(ratio))
        if ratio[j] > tp.max_std_ratio:
            return (f"the {int(seen.sum())} edges seen fix {DOF_NAMES[j]} {ratio[j]:.1f}x less "
                    f"well than all {len(seen)} (> {tp.max_std_ratio}): too few edges")
        return rms, std

    def _std_ratio(self, pose: Pose, seen: np.ndarray, J2: np.ndarray,
                   new: np.ndarray | None = None) -> np.ndarray:
        """Per DOF, the std from the seen edges over the std from all edges (same noise):
        ``sqrt(diag((J_s^T J_s)^-1) / diag((J^T J)^-1))`` with ``J`` the model-to-line
        distances' Jacobian (``J2``: :meth:`_end_jacobian`), the lines the model's edges
        projected with ``pose``."""
        ideal = self._project(pose)
        d = np.roll(ideal, -1, axis=0) - ideal
        nrm = np.column_stack([-d[:, 1], d[:, 0]]) / np.linalg.norm(d, axis=1)[:, None]
        nrm = np.concatenate([nrm, nrm])
        J = nrm[:, 0:1] * J2[0::2] + nrm[:, 1:2] * J2[1::2]      # rows: edge k's two ends
        use = np.concatenate([seen, seen])
        Ju = J[use]
        ks = np.nonzero(seen)[0]
        if new is not None and new[ks].any():   # weighted as in the fit
            L = np.column_stack([nrm, np.zeros(len(nrm))])[np.concatenate([ks, ks + len(seen)])]
            Ju = self._weigh_unmeasured(pose, ks, np.nonzero(new[ks])[0], L,
                                        np.zeros(len(Ju)), Ju)[1]
        with np.errstate(invalid="ignore"):
            return np.sqrt(np.diag(np.linalg.inv(Ju.T @ Ju))
                           / np.diag(np.linalg.inv(J.T @ J)))

    def track(self, frames) -> list[TrackResult]:
        """:meth:`update` over an iterable of frames."""
        return [self.update(f) for f in frames]
