"""Distance matching (DM): a correspondence-free template search on a distance image.

The seed paper's section 2.3, and a continuous refinement beyond it (``dm+``).

**Distance image.** The detected corners are drawn as the only zero pixels of a binary image
(observed pixels, rounded) and ``cv2.distanceTransform`` (Euclidean, 5x5 chamfer mask: the
paper's "approximate distance image") gives every pixel its distance to the nearest corner
(paper Fig. 4). We compute it over the region the templates can reach (the corners' bounding
box plus a margin), not the full frame; a template point outside that region gets the value at
the nearest border pixel plus its distance to it.

**Score.** A template is the 20 model corners projected through the camera model (distortion
included) at a pose ``p = (alpha, beta, gamma, X, Y, Z)``; its distance to the image is

    D(p) = sqrt( (1/20) sum_k DT(pi(p, P_k))^2 )                 (paper, section 2.3)

which needs no correspondence between model and detected corners. The paper does not say how a
sub-pixel template point reads the integer-pixel distance image. Read at the nearest pixel
(``bilinear=False``), ``D`` is piecewise constant and rugged at the 0.1 mm / 0.1 deg scale, and
the local search stops in its small pits: the Z std is 1.7x the ML std at 2.5 px and still 1.7x
at 5 px (200 trials per level, docs/notes/dm.md). Read bilinearly (the default), the search
reaches the ML accuracy from 2.5 px on.

**Search.** Coarse to fine with steps 5, 1, 0.5, 0.2, 0.1 (mm and deg) over all six DOFs, within
the known motion range (:class:`~cutterpose.geometry.working_range.MotionRange`). At each level the
``3^6``
neighbours of the current pose are scored and the best taken until the centre is best (a local
search; ties keep the centre), so the coarse level can walk several steps from the start.
Options: ``n_starts`` > 1 searches from the top initial candidates, ``coarse_radius`` = 2 first
scans a ``5^6`` window (+-10 mm / +-10 deg). With the sphere-based initial pose neither is needed
(11 000 trials: dm recovered from initial errors up to 9.8 deg / 46 mm; docs/notes/dm.md), so
the defaults are the paper's (1 start, ``3^6``).
Templates of the coarse level can be built offline over the whole motion range
(:class:`TemplateLibrary`, feasible for the real +-10 deg / +-20 mm range: 5^3 9^3 = 91 125
templates, 14.6 MB); finer levels are projected on the fly. The paper's full library at
0.1 mm / 0.1 deg would hold 201^3 401^3 ~ 5.2e14 templates (~ 8e16 bytes) for the real range and
~ 1e19 for the synthetic one: that is why the fine levels are not stored.

**dm+** (ours). DM's answer is capped by the grid (0.1 mm / 0.1 deg) and by the integer-pixel
distance image. ``dm+`` continues from it with the exact distance of every projected model corner
to a detected corner (ideal pixels, one-to-one: Hungarian assignment on the 20 x 20 distances)
and least squares on the six pose parameters (Levenberg-Marquardt, analytic Jacobian),
re-assigning until the assignment is stable: at convergence this is the maximum-likelihood
pose, which reaches the Cramer-Rao bound.
The nearest-corner cost has a degenerate zero: the holder receding to infinity, every model
corner projecting onto one detected corner. The assignment is therefore one-to-one
(``scipy.optimize.linear_sum_assignment``), which excludes it, and the result must stay within
the motion range.

Convention:
    Pose as in :mod:`cutterpose.geometry.pose` (``x_cam = R @ x_holder + t``, ``R = Rz Ry Rx``, mm
    and
    deg). The distance image lives in observed (distorted) pixels like the detected corners;
    dm+ works in ideal pixels (``camera.undistort_px``).

References:
    Seed paper, section 2.3, Figs. 3 and 4. G. Borgefors, "Distance transformations in digital
    images", CVGIP 34 (1986). OpenCV ``cv2.distanceTransform``. H. Kuhn, "The Hungarian method
    for the assignment problem" (1955).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial.distance import cdist
from scipy.spatial.transform import Rotation

from ..errors import DegenerateInputError, InputError
from ..geometry.camera import Camera, PinholeCamera
from ..geometry.holder import Holder
from ..geometry.pose import rotation_from_euler_deg
from ..geometry.working_range import MotionRange, PoseOutOfRangeError, pose_dof
from .estimate import PoseEstimate
from .pnp.base import as_points_px
from .vanishing import check_contour

__all__ = ["DistanceImage", "distance_image", "dm_score", "TemplateLibrary", "distance_match",
           "refine_continuous", "refine_from_close_start", "PAPER_STEPS"]

#: The paper's coarse-to-fine steps (mm and deg).
PAPER_STEPS = (5.0, 1.0, 0.5, 0.2, 0.1)


# ---- distance image -----------------------------------------------------------------------
@dataclass
class DistanceImage:
    """Distance (px) to the nearest detected corner over a region of the observed image.

    Attributes
    ----------
    dist_px : (h, w) float32 distance image.
    origin_px : (u0, v0) of its top-left pixel in the full image.
    """

    dist_px: np.ndarray
    origin_px: tuple[int, int]
    bilinear: bool = False

    def sample(self, uv_px: np.ndarray) -> np.ndarray:
        """Distance at observed pixels ``(..., 2)``, nearest-pixel lookup (paper); outside the
        region, the border value plus the distance to the border; NaN -> a large value."""
        h, w = self.dist_px.shape
        q = np.asarray(uv_px, float) - self.origin_px
        flat = self.dist_px.ravel()
        inside = (np.isfinite(q).all() and q.min() >= 0.0 and q[..., 0].max() <= w - 1
                  and q[..., 1].max() <= h - 1)
        if self.bilinear:
            return self._bilinear(q)
        if inside:                                   # the usual case: a plain lookup
            lin = np.rint(q[..., 1]).astype(np.intp) * w + np.rint(q[..., 0]).astype(np.intp)
            return np.take(flat, lin).astype(float)
        q[~np.isfinite(q)] = 1e6
        qc = np.clip(q, 0.0, (w - 1, h - 1))
        lin = np.rint(qc[..., 1]).astype(np.intp) * w + np.rint(qc[..., 0]).astype(np.intp)
        return np.take(flat, lin) + np.linalg.norm(q - qc, axis=-1)

    def _bilinear(self, q: np.ndarray) -> np.ndarray:
        h, w = self.dist_px.shape
        inside = (np.isfinite(q).all() and q.min() >= 0.0 and q[..., 0].max() < w - 1.001
                  and q[..., 1].max() < h - 1.001)
        if inside:
            qc = q
        else:
            q = q.copy()
            q[~np.isfinite(q)] = 1e6
            qc = np.clip(q, 0.0, (w - 1.001, h - 1.001))
        i0 = qc.astype(np.intp)                       # floor: qc >= 0
        f = qc - i0
        flat = self.dist_px.ravel()
        lin = i0[..., 1] * w + i0[..., 0]
        d00, d01 = np.take(flat, lin), np.take(flat, lin + 1)
        d10, d11 = np.take(flat, lin + w), np.take(flat, lin + w + 1)
        fx, fy = f[..., 0], f[..., 1]
        d0 = d00 + fx * (d01 - d00)
        d = d0 + fy * (d10 + fx * (d11 - d10) - d0)
        return d if inside else d + np.linalg.norm(q - qc, axis=-1)


def distance_image(points_px: np.ndarray, margin_px: float | None = None,
                   mask: int = cv2.DIST_MASK_5, bilinear: bool = False) -> DistanceImage:
    """Distance transform of a binary image holding only the corners (paper Fig. 4).

    Parameters
    ----------
    points_px : (n, 2) observed corner pixels.
    margin_px : margin around the corners' bounding box; default 5 % of its larger side plus
        20 px (the fine levels move corners by a few pixels; a coarse template beyond the
        region is still scored, through the border value plus the distance to the border).
    mask : ``cv2.DIST_MASK_5`` (default; the paper's "approximate distance image", exact to
        2 % and to 0.04 px within 2 px of a corner, 2-3x faster) or ``cv2.DIST_MASK_PRECISE``.
    """
    p = np.asarray(points_px, float)
    lo, hi = p.min(axis=0), p.max(axis=0)
    if margin_px is None:
        margin_px = 0.05 * float(np.max(hi - lo)) + 20.0
    u0, v0 = np.floor(lo - margin_px).astype(int)
    u1, v1 = np.ceil(hi + margin_px).astype(int)
    img = np.full((v1 - v0 + 1, u1 - u0 + 1), 255, np.uint8)
    idx = np.rint(p - [u0, v0]).astype(int)
    img[idx[:, 1], idx[:, 0]] = 0
    dist = cv2.distanceTransform(img, cv2.DIST_L2, mask)
    return DistanceImage(dist, (int(u0), int(v0)), bilinear)


def _euler_columns(dof: np.ndarray) -> np.ndarray:
    """``(k, 3, 3)`` matrices ``[r1 r2 t]`` of poses ``dof (k, 6)``: the first two columns of
    ``R = Rz(gamma) Ry(beta) Rx(alpha)`` (written out: the model is planar, Z = 0) and t."""
    a, b, g = np.radians(dof[:, 0]), np.radians(dof[:, 1]), np.radians(dof[:, 2])
    ca, sa, cb, sb, cg, sg = np.cos(a), np.sin(a), np.cos(b), np.sin(b), np.cos(g), np.sin(g)
    M = np.empty((len(dof), 3, 3))
    M[:, 0, 0], M[:, 1, 0], M[:, 2, 0] = cg * cb, sg * cb, -sb
    M[:, 0, 1], M[:, 1, 1], M[:, 2, 1] = cg * sb * sa - sg * ca, sg * sb * sa + cg * ca, cb * sa
    M[:, :, 2] = dof[:, 3:]
    return M


def _poses(dof: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return rotation_from_euler_deg(dof[..., 0], dof[..., 1], dof[..., 2]), dof[..., 3:]


def project_templates(dof: np.ndarray, camera: Camera, holder: Holder) -> np.ndarray:
    """Templates: ``(k, n, 2)`` observed pixels of the model corners at poses ``dof (k, 6)``.

    The model is planar, so a pose acts on it as the homography ``H = K [r1 r2 t]`` followed by
    the camera's distortion; points behind the camera give NaN.
    """
    dof = np.atleast_2d(np.asarray(dof, float))
    H = camera.K @ _euler_columns(dof)                         # (k, 3, 3)
    q = H @ np.vstack([holder.corners_mm.T, np.ones(holder.n_corners)])   # (k, 3, n)
    w = q[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        w = np.where(w > 0, w, np.nan)
        ideal = np.stack([q[:, 0] / w, q[:, 1] / w], axis=-1)
    if isinstance(camera, PinholeCamera):
        return ideal
    return camera.distort_px(ideal)


def dm_score(dof: np.ndarray, dimg: DistanceImage, camera: Camera, holder: Holder) -> np.ndarray:
    """The paper's distance ``D(p)``: RMS of the distance image at the template points, for
    poses ``dof (k, 6)``."""
    d = dimg.sample(project_templates(dof, camera, holder))
    return np.sqrt(np.mean(d ** 2, axis=-1))


# ---- template library (the coarse level, offline) ----------------------------------------
@dataclass
class TemplateLibrary:
    """Templates on a regular grid over a motion range (the paper's offline library).

    Attributes
    ----------
    dof : (N, 6) grid poses; templates_px : (N, n, 2) float32 observed corner pixels.
    step : grid step (mm and deg).
    """

    dof: np.ndarray
    templates_px: np.ndarray
    step: float

    #: refuse to build more templates than this (the wide synthetic range would need 7.9e8)
    MAX_TEMPLATES = 500_000

    @staticmethod
    def grid_size(motion_range: MotionRange, step: float) -> int:
        n = np.floor(2 * np.asarray(motion_range.half_width_dof) / step + 1e-9).astype(int) + 1
        return int(np.prod(n.astype(float)))

    @classmethod
    def build(cls, camera: Camera, holder: Holder, motion_range: MotionRange,
              step: float = PAPER_STEPS[0]) -> TemplateLibrary:
        """Project the model at every grid pose of the range (offline; seconds)."""
        size = cls.grid_size(motion_range, step)
        if size > cls.MAX_TEMPLATES:
            raise InputError(f"a {step} mm/deg library over this motion range would hold "
                             f"{size:.3g} templates (limit {cls.MAX_TEMPLATES}); use the local "
                             "coarse search instead")
        axes = [np.arange(lo, hi + 1e-9, step) for lo, hi in
                zip(motion_range.lower, motion_range.upper)]
        dof = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 6)
        tpl = np.concatenate([project_templates(c, camera, holder).astype(np.float32)
                              for c in np.array_split(dof, max(1, len(dof) // 20000))])
        return cls(dof, tpl, step)

    def save(self, path) -> None:
        np.savez_compressed(Path(path), dof=self.dof, templates_px=self.templates_px,
                            step=self.step)

    @classmethod
    def load(cls, path) -> TemplateLibrary:
        with np.load(Path(path)) as z:
            return cls(z["dof"], z["templates_px"], float(z["step"]))

    def window(self, center_dof: np.ndarray, radius_steps: float) -> np.ndarray:
        """Indices of the grid poses within ``radius_steps`` steps of a pose, per DOF."""
        return np.flatnonzero(np.all(np.abs(self.dof - center_dof)
                                     <= (radius_steps + 1e-9) * self.step, axis=1))


# ---- search --------------------------------------------------------------------------------
def _offsets(radius: int) -> np.ndarray:
    r = np.arange(-radius, radius + 1, dtype=float)
    g = np.stack(np.meshgrid(*([r] * 6), indexing="ij"), axis=-1).reshape(-1, 6)
    # the centre first, so that ties keep it (argmin returns the first minimum)
    centre = np.flatnonzero(np.all(g == 0, axis=1))[0]
    return np.concatenate([g[centre:centre + 1], np.delete(g, centre, axis=0)])


_OFF1, _OFF2 = _offsets(1), _offsets(2)


class _Scorer:
    """D(p) restricted to the motion range (outside: +inf); counts evaluations. With
    ``truncate_px`` each template point's distance is capped there (partial corner sets)."""

    def __init__(self, dimg, camera, holder, motion_range, truncate_px: float | None = None):
        self.dimg, self.camera, self.holder = dimg, camera, holder
        self.lo, self.hi = motion_range.lower, motion_range.upper
        self.n_eval = 0
        self.truncate_px = truncate_px

    def __call__(self, dof: np.ndarray) -> np.ndarray:
        self.n_eval += len(dof)
        if self.truncate_px is None:
            s = dm_score(dof, self.dimg, self.camera, self.holder)
        else:
            d = self.dimg.sample(project_templates(dof, self.camera, self.holder))
            s = np.sqrt(np.mean(np.minimum(d, self.truncate_px) ** 2, axis=-1))
        inside = np.all((dof >= self.lo - 1e-9) & (dof <= self.hi + 1e-9), axis=1)
        return np.where(inside, s, np.inf)


def _hill_climb(center: np.ndarray, score0: float, step: float, scorer: _Scorer,
                max_iter: int = 50) -> tuple[np.ndarray, float]:
    """3^6 local search at one step size until the centre is the best."""
    for _ in range(max_iter):
        cand = center + step * _OFF1
        s = scorer(cand)
        i = int(np.argmin(s))
        if i == 0 or not s[i] < score0:
            break
        center, score0 = cand[i], float(s[i])
    return center, score0


def _start_dofs(initial, rng: MotionRange, slack: float, n_starts: int) -> np.ndarray:
    """(k, 6) the starts of :func:`distance_match` (``initial``'s candidates, up to
    ``n_starts``) within ``slack`` of the motion range, clipped into it."""
    if isinstance(initial, PoseEstimate):
        if not initial:
            raise InputError(f"the initial pose is a failure: {initial.reason}")
        starts = initial.candidates or [(initial.R_cam_holder, initial.t_cam_holder_mm)]
    else:
        starts = [initial]
    starts = starts[:max(1, n_starts)]
    start_dof = pose_dof(np.array([np.asarray(R, float) for R, _ in starts]),
                         np.array([np.asarray(t, float).reshape(3) for _, t in starts]))
    excess = rng.excess(start_dof)
    if not np.all(np.isfinite(start_dof)):
        raise InputError("the initial pose holds NaN or inf")
    if not np.any(excess <= slack):
        raise PoseOutOfRangeError(
            f"the initial pose lies outside the motion range ({excess.min():.2f} half widths "
            f"beyond it; DOFs {np.round(start_dof[np.argmin(excess)], 2).tolist()})")
    return np.clip(start_dof[excess <= slack], rng.lower, rng.upper)


def _coarse_to_fine(start_dof, scorer, dimg, camera: Camera, holder: Holder, steps,
                    coarse_radius: int, library) -> tuple[np.ndarray, float]:
    """The coarse-to-fine search (module doc): the best pose (dof) and its score (px)."""
    # coarse level: a wide window (or the offline library) around every start, then 3^6
    results = []
    for c in start_dof:
        if library is not None:
            idx = library.window(c, coarse_radius + 0.5)   # the grid nodes of a 3^6 block
            cand = np.concatenate([c[None], library.dof[idx]])
            d = dimg.sample(np.concatenate([project_templates(c[None], camera, holder),
                                            library.templates_px[idx]]))
            s = np.sqrt(np.mean(d.astype(float) ** 2, axis=-1))
            scorer.n_eval += len(cand)
        else:
            cand = c + steps[0] * (_OFF2 if coarse_radius >= 2 else _OFF1)
            s = scorer(cand)
        i = int(np.argmin(s))
        results.append(_hill_climb(cand[i], float(s[i]), steps[0], scorer))
    center, best = min(results, key=lambda r: r[1])
    for step in steps[1:]:
        center, best = _hill_climb(center, best, step, scorer)
    return center, best


def distance_match(points_px, camera: Camera, holder: Holder, initial,
                   motion_range: MotionRange | None = None, refine: bool = False,
                   steps=PAPER_STEPS, coarse_radius: int = 1, n_starts: int = 1,
                   library: TemplateLibrary | None = None, slack: float = 0.5,
                   dt_mask: int = cv2.DIST_MASK_5, bilinear: bool = True,
                   truncate_mm: float = 10.0, partial: bool | None = None) -> PoseEstimate:
    """Distance matching from an initial pose (module doc); ``refine=True`` gives dm+.

    Parameters
    ----------
    points_px : (20, 2) observed corners in contour order (unknown start and direction; the
        order is not used here); or any other number (>= 4) of corners: a *partial* set, some
        of the holder's corners missing and/or spurious ones added (field images: corners
        under slurry, points on a lump). Then the initial pose may be None, each template
        point's distance is capped at ``truncate_mm`` (in px at the range's centre depth: a
        missing corner costs a constant, it does not pull the pose) and dm+ pairs only model
        and detected corners closer than that (rectangular one-to-one assignment). ``partial``
        says which (None: a partial set if ``initial`` is None or the count is not 20; a set
        of 20 with some missing and as many spurious needs ``partial=True``).
    camera, holder : camera model and holder geometry.
    initial : a :class:`PoseEstimate` (its ``candidates`` are all used as starts, best first,
        up to ``n_starts``) or a pair ``(R, t_mm)``; None: the centre of the motion range,
        the first level scanning a 5^6 window (``coarse_radius`` 2).
    motion_range : the known range (default: the synthetic protocol's); the search stays in it.
    refine : continue with the continuous one-to-one least-squares refinement (dm+).
    steps : coarse-to-fine steps (mm and deg), the paper's by default.
    coarse_radius : the first level scans a ``(2 r + 1)^6`` window (r = 1 is the paper's 3^6).
    n_starts : number of initial candidates searched at the coarse level.
    library : optional offline templates of the coarse level (:class:`TemplateLibrary`).
    slack : an initial pose may lie outside the range by this fraction of the half widths
        (it is then clipped into the range); beyond, :class:`PoseOutOfRangeError`.
    dt_mask : ``cv2.distanceTransform`` mask (see :func:`distance_image`).
    bilinear : sample the distance image bilinearly at the sub-pixel template points (default)
        rather than at the nearest pixel (module doc, "Score").

    Raises
    ------
    InputError, DegenerateInputError
        Bad corners (see :func:`~cutterpose.solvers.vanishing.check_contour`).
    PoseOutOfRangeError
        Every initial pose lies outside the motion range.
    """
    t0 = time.perf_counter()
    rng = motion_range or MotionRange()
    x = as_points_px(points_px)
    if partial is None:
        partial = initial is None or len(x) != holder.n_corners
    x = _check_partial(x, holder) if partial else check_contour(x, holder)
    if initial is None:
        c = np.asarray(rng.center_dof, float)
        initial = _poses(c[None])
        initial = (initial[0][0], initial[1][0])
        coarse_radius = max(coarse_radius, 2)
    truncate_px = (truncate_mm * camera.focal_px / float(rng.center_dof[5])
                   if partial else None)
    ideal = camera.undistort_px(x)
    if not np.all(np.isfinite(ideal)):
        raise InputError("points_px lie outside the camera's valid distortion domain")
    start_dof = _start_dofs(initial, rng, slack, n_starts)
    dimg = distance_image(x, mask=dt_mask, bilinear=bilinear)
    scorer = _Scorer(dimg, camera, holder, rng, truncate_px)
    center, best = _coarse_to_fine(start_dof, scorer, dimg, camera, holder, steps,
                                   coarse_radius, library)
    R, t = _poses(center)
    info = {"dm_score_px": best, "n_templates": scorer.n_eval, "n_starts": len(start_dof),
            "dm_dof": center.tolist()}
    est = PoseEstimate(method="dm", R_cam_holder=R, t_cam_holder_mm=np.array(t, float),
                       residual_px=best, info=info)
    if refine:
        est = refine_continuous(est, ideal, camera, holder, rng, slack=slack,
                                gate_px=truncate_px)
    est.time_ms = (time.perf_counter() - t0) * 1e3
    return est


# ---- dm+: continuous, correspondence-free refinement ---------------------------------------
def _project_ideal(R, t, P, K):
    X = P @ R.T + t
    return (X @ K.T)[:, :2] / X[:, 2:3], X[:, 2]


def _lm_pose(R, t, P, K, target, max_iter: int = 100):
    """Levenberg-Marquardt on the pixel reprojection error with fixed pairs.

    Residuals ``r = pi(R P + t) - target`` (ideal px); the rotation is updated on the left,
    ``R <- exp([w]x) R``, and re-linearised at every step, so the analytic Jacobian is exact:
    ``d pi / d X = (K_{0:2} - pi e3^T) / Z``, ``dX / dw = -[R P]x``, ``dX / dt = I``.
    Returns ``(R, t, rms_px)`` with the RMS per point.
    """
    n = len(P)

    def resid(R, t):
        X = P @ R.T + t
        q = X @ K.T
        uv = q[:, :2] / q[:, 2:3]
        return X, uv, (uv - target).ravel()

    X, uv, r = resid(R, t)
    cost = r @ r
    lam = 1e-3
    for _ in range(max_iter):
        Z = X[:, 2]
        # d uv / d X, (n, 2, 3)
        A = (K[None, :2, :] - uv[:, :, None] * np.array([0.0, 0.0, 1.0])) / Z[:, None, None]
        RP = X - t
        skew = np.zeros((n, 3, 3))
        skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = RP[:, 2], -RP[:, 1], RP[:, 0]
        skew[:, 1, 0], skew[:, 2, 0], skew[:, 2, 1] = -RP[:, 2], RP[:, 1], -RP[:, 0]
        # skew @ w = w x RP = -[RP]x w: the change of X under R <- exp([w]x) R
        J = np.concatenate([A @ skew, A], axis=2).reshape(2 * n, 6)
        g = J.T @ r
        H = J.T @ J
        while True:
            delta = -np.linalg.solve(H + lam * np.diag(np.diag(H)), g)
            R_new = Rotation.from_rotvec(delta[:3]).as_matrix() @ R
            t_new = t + delta[3:]
            X_new, uv_new, r_new = resid(R_new, t_new)
            c_new = r_new @ r_new
            if c_new <= cost or lam > 1e12:
                break
            lam *= 10.0
        if c_new > cost:
            break
        done = cost - c_new <= 1e-15 * max(cost, 1e-30) or np.abs(delta).max() < 1e-13
        R, t, X, uv, r, cost = R_new, t_new, X_new, uv_new, r_new, c_new
        lam = max(lam / 10.0, 1e-9)
        if done:
            break
    return R, t, float(np.sqrt(cost / n))


def refine_continuous(est: PoseEstimate, ideal_px: np.ndarray, camera: Camera, holder: Holder,
                      motion_range: MotionRange, max_rounds: int = 10,
                      slack: float = 0.1, gate_px: float | None = None) -> PoseEstimate:
    """dm+ (module doc): one-to-one nearest-corner assignment + least squares, repeated until
    the assignment is stable. Returns a failure if the result leaves the motion range.

    ``gate_px`` (partial corner sets): the assignment is rectangular on distances capped at
    the gate, and only pairs closer than the gate enter the least squares."""
    K = camera.K
    P = holder.points_holder_mm
    R, t = np.asarray(est.R_cam_holder, float), np.asarray(est.t_cam_holder_mm, float)
    assign = None
    rounds = 0
    rms = np.nan
    for _ in range(max_rounds):
        rounds += 1
        uv, z = _project_ideal(R, t, P, K)
        if np.any(z <= 0):
            break
        d2 = cdist(uv, ideal_px, "sqeuclidean")
        if gate_px is None:
            _, col = linear_sum_assignment(d2)
            rows = np.arange(len(P))
        else:
            rows, col = linear_sum_assignment(np.minimum(d2, gate_px ** 2))
            near = d2[rows, col] < gate_px ** 2
            rows, col = rows[near], col[near]
            if len(rows) < 4:
                break
        pairs = np.column_stack([rows, col])
        if assign is not None and np.array_equal(pairs, assign):
            break
        assign = pairs

        R, t, rms = _lm_pose(R, t, P[rows], K, ideal_px[col])
    info = dict(est.info, dm_plus_rounds=rounds)
    pairs = None if assign is None else (assign[:, 1].tolist() if gate_px is None
                                         else assign.tolist())
    dof = pose_dof(R, t)
    if not np.all(np.isfinite(dof)) or motion_range.excess(dof) > slack:
        return PoseEstimate.failure("dm+", "the continuous refinement left the motion range",
                                    info=info, assignment=pairs)
    return PoseEstimate(method="dm+", R_cam_holder=R, t_cam_holder_mm=t, residual_px=rms,
                        info=info, assignment=pairs)


def refine_from_close_start(points_px, camera: Camera, holder: Holder, initial,
                            motion_range: MotionRange | None = None, slack: float = 0.5,
                            truncate_mm: float = 10.0, partial: bool | None = None,
                            max_rms_px: float = 1.5) -> PoseEstimate:
    """dm+ without the grid search (issue 13): the continuous one-to-one refinement
    (:func:`refine_continuous`) straight from a start that is already close, e.g. the pose of
    the field chain's outline homography (within ~0.5 deg and a few mm: far less than half the
    corner spacing, so the first assignment is already the final one).

    DM's coarse-to-fine search only brings the start into the basin of the refinement; from
    such a start it adds nothing: both end at the same least-squares fixpoint (same assignment,
    same cost). Whether the start was close enough is checked, not assumed: every corner
    (every seen corner of a partial set) must be assigned one-to-one within the gate and the
    RMS residual be at most ``max_rms_px``; otherwise the estimate is a failure whose reason
    says so, and the caller runs the full ``dm+``.

    Parameters as :func:`distance_match` (``initial``: ``(R, t_mm)``).
    """
    t0 = time.perf_counter()
    rng = motion_range or MotionRange()
    x = as_points_px(points_px)
    if partial is None:
        partial = len(x) != holder.n_corners
    x = _check_partial(x, holder) if partial else check_contour(x, holder)
    R0, t0_mm = np.asarray(initial[0], float), np.asarray(initial[1], float).reshape(3)
    dof0 = pose_dof(R0, t0_mm)
    if not np.all(np.isfinite(dof0)) or rng.excess(dof0) > slack:
        return PoseEstimate.failure("dm+", "the close start lies outside the motion range")
    ideal = camera.undistort_px(x)
    if not np.all(np.isfinite(ideal)):
        raise InputError("points_px lie outside the camera's valid distortion domain")
    gate = truncate_mm * camera.focal_px / float(rng.center_dof[5]) if partial else None
    start = PoseEstimate(method="dm+", R_cam_holder=R0, t_cam_holder_mm=t0_mm,
                         info={"start": "close", "start_dof": dof0.tolist()})
    est = refine_continuous(start, ideal, camera, holder, rng, slack=slack, gate_px=gate)
    pairs = est.assignment
    n_pairs = 0 if pairs is None else len(pairs)
    if est and (n_pairs != len(x) or not est.residual_px <= max_rms_px):
        est = PoseEstimate.failure("dm+", f"the close start did not converge ({n_pairs} of "
                                   f"{len(x)} corners paired, RMS {est.residual_px:.2f} px)",
                                   info=est.info, assignment=pairs)
    est.time_ms = (time.perf_counter() - t0) * 1e3
    return est


def _check_partial(x: np.ndarray, holder: Holder) -> np.ndarray:
    """A partial corner set: at least 4 finite corners, not all collinear."""
    if not isinstance(holder, Holder):
        raise InputError("the correspondence-free methods need a Holder (its contour), got "
                         f"{type(holder).__name__}")
    if len(x) < 4:
        raise DegenerateInputError(f"need at least 4 corners of the holder, got {len(x)}")
    sv = np.linalg.svd(x - x.mean(axis=0), compute_uv=False)
    if sv[0] <= 0 or sv[1] / sv[0] < 1e-6:
        raise DegenerateInputError("all corners are collinear (or coincide): the holder's "
                                   "pose is not determined")
    return x
