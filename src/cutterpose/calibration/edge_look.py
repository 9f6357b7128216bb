"""Calibrating the edge look in the cell: the band model's photometry fitted on a reference
holder at known poses (issue 10; ``dm+b``'s remaining bias, docs/notes/edge_band.md).

``dm+b`` (:mod:`cutterpose.solvers.edge_band`) fits, per edge segment, the edge model's profile
(:mod:`cutterpose.image.edge_model`: Lambert + a Blinn-Phong lobe under the light at the lens)
to the measured profile across the broken pocket edge and takes where the model puts the
*design* edge. A fillet has no crease: where the design edge lies inside its band comes from the
shading law alone, and a generic look puts it a fraction of a pixel off (on the path-traced
``new`` holders +0.2 px outwards at the true pose, the Z bias of -0.15 mm). A look chosen by
cost alone is not located right (docs/notes/edge_band.md, "Tried and dropped").

A cell can calibrate it: at a known pose the design edge's image is known, so the look must
reproduce the measured profiles with the design-edge shift at 0. This module fits the look's
continuous parameters to that:

* **Reference profiles** (:func:`reference_image`): each image's band is sampled at its known
  pose exactly as ``dm+b``'s last pass samples it (:func:`~cutterpose.image.edge_band.sample_band`,
  4 segments per edge, 12 normals each).
* **The fit** (:func:`calibrate_edge_look`): parameters ``theta`` = (log specular weight, log
  shininess, wall albedo, pocket level), all relative to the face albedo (the profile's gain
  and offset are free per segment, so only ratios are seen). For every segment the residual is
  ``r_s = sqrt(C_s(theta) / c_i)``, ``C_s`` the least-squares cost of ``y ~ a + b m(w)`` with the
  shift fixed at 0 and the radius profiled out (minimum over the fine scan's radii, refined by a
  parabola: variable projection, Golub and Pereyra 2003), ``c_i`` the image's median segment
  cost at the start (every image weighs alike). ``sum rho(r_s^2)`` with soft-L1 ``rho`` (slurry,
  a chip, the cutter's silhouette) is minimised by Powell's derivative-free search (each
  segment's residual jumps where its best radius moves to the next grid node; the sum is smooth
  enough for line searches, not for a Gauss-Newton Jacobian). Each image's
  shape (fillet or chamfer) and blur (``dm+b``'s three) are chosen by the trimmed cost, as
  ``dm+b`` chooses them, and held during a round; rounds repeat until they no longer change.
* **Uncertainty**: the cluster-robust ("sandwich") covariance with images as clusters (Liang and
  Zeger 1986): ``H^-1 (sum_i g_i g_i^T) H^-1``, ``H`` the Gauss-Newton Hessian, ``g_i`` image
  ``i``'s score. It knows that segments of one image share its light, steel and defocus (times
  the number of images: the spread of one image's own look, reported). Looks at +-1 sd along
  its main axes (:meth:`EdgeLookCalibration.variants`) can enter the budget, but do not by
  default (below).
* **Offset** (:func:`calibrate_offsets`): the look is fitted to the profiles' shape; where a
  look of this family puts the design edge can still be off by a few hundredths of a mm (on the
  path-traced ``new`` set: chamfers 0.04 mm, fillets 0.005 mm). At each known pose ``dm+b``'s
  fit with the calibrated look gives the design-edge points, the pose is fitted to them from the
  true pose, and per shape a uniform outward offset and the depth below the face at which the
  located edge behaves (a parallax of ``depth x tan(theta)``, ``theta`` the view's lean across
  the edge: a tilt error growing with the tilt; kept where it predicts left-out images better)
  are fitted to the pose errors. ``dm+b`` adds the offset to every fitted shift of that shape.
  The offsets' scatter over the reference images is how far one image's design edge may still
  be off: the budget's edge-model term with a calibration (the pose change for a uniform shift
  by it), with the offset's and depth's joint covariance; there it replaces the generic model
  floor, within the depths of the reference poses (``distance_range_mm``) and the radii of the
  reference breaks (``radius_range_mm``) only. It is measured, where the variants only
  propagate the parameters' uncertainty through a model that does not fit: on three worn images
  the variants (worn calibration) made the edge-model term 0.66-0.78 mm at 3 sigma, the
  measured scatter 0.39-0.52 mm.
* **Check** (:func:`shift_at_truth`): at the known poses, ``dm+b``'s profile fit with the shift
  free, for the generic looks and the calibrated one: the mean design-edge shift per image is
  the bias the look leaves.

Convention:
    Poses ``x_cam = R_cam_holder x_holder + t_cam_holder_mm`` (mm); shifts in px along each
    segment's outward image normal (away from the pocket), and in mm as the shift over the
    segment's ``a_s`` (px per mm outwards in the face plane). Greys of :class:`EdgeLook` are
    relative to the light (the face albedo is held at its default 0.78).

References:
    Liang, K.-Y. and Zeger, S. L., "Longitudinal data analysis using generalized linear
    models", Biometrika 73(1), 1986 (the cluster-robust covariance); Golub, G. and Pereyra, V.,
    "Separable nonlinear least squares: the variable projection method and its applications",
    Inverse Problems 19(2), 2003; Powell, M. J. D., "An efficient method for finding the
    minimum of a function of several variables without calculating derivatives", The Computer
    Journal 7(2), 1964; Triggs et al., "Bundle adjustment - a modern synthesis"
    (2000), section 6 (robust costs); the seed paper's follow-up (Sensors 2023, 23(3), 1536).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np
from scipy.optimize import minimize

from ..errors import EdgeLookFileError, InputError
from ..geometry.camera import Camera
from ..geometry.holder import Holder
from ..geometry.jsonfile import is_finite_number
from ..geometry.pose import Pose
from ..image import edge_model as em
from ..image.edge_band import (
    BLURS_PX,
    CAL_RADII_MM,
    BandLooks,
    BandProfiles,
    DesignEdgeOffsets,
    fit_band,
    profile_costs,
    sample_band,
    view_lean,
)
from ..image_set import load_image_set
from ..solvers.edge_band import POSITIONS_PER_SEGMENT, SEGMENTS_PER_EDGE, design_pose

__all__ = ["ReferenceImage", "EdgeLookCalibration", "reference_image", "load_reference_set",
           "load_reference_images", "calibrate_edge_look", "calibrate_offsets",
           "shift_at_truth", "save_edge_look",
           "load_edge_look", "PARAM_NAMES", "FORMAT"]

FORMAT = "cutterpose-edge-look"
#: version 2 adds the design edge's depth (``design_edge_depth_mm``); a version-1 file reads
#: as depth 0
VERSION = 2
READS_VERSIONS = (1, 2)
#: the largest calibrated depth of the design edge (mm) a file may give
MAX_DEPTH_MM = 3.0
#: the fitted parameters, in the fit's coordinates (log for the lobe's weight and exponent)
PARAM_NAMES = ("log_specular", "log_shininess", "wall_albedo", "pocket_level")
_LOWER = np.array([math.log(0.01), math.log(2.0), 0.0, 0.0])
_UPPER = np.array([math.log(20.0), math.log(1000.0), 2.0, 2.0])
#: soft-L1 scale of the normalised residuals: a segment whose cost is beyond ~4x the image's
#: median is down-weighted
F_SCALE = 2.0
#: the uniform outward offset (mm) of the design-edge points by which the offset calibration
#: differentiates the pose (it is linear in it)
OFFSET_STEP_MM = 0.02
#: the fewest reference images of a shape for its offset, and for its depth (the offset's change
#: with the view's lean across the edge, :func:`calibrate_offsets`)
MIN_OFFSET_IMAGES = 3
MIN_DEPTH_IMAGES = 8
#: the depth step (mm) by which the offset calibration differentiates the pose
DEPTH_STEP_MM = 0.1
#: the lever (mm) at which the offset calibration weighs a rotation error against a translation
#: error (a grasp point ~100 mm from the holder's origin)
OFFSET_LEVER_MM = 100.0
#: the largest normalised residual of a segment (a look that cannot fit it at all)
MAX_RESIDUAL = 10 * F_SCALE
#: rounds of (shape and blur per image, then the fit); stops early when they hold
ROUNDS = 3
#: the budget's variants: +-1 sd along this many main axes of the calibration's covariance
N_VARIANT_AXES = 2
#: the steps of the central differences of the covariance (fit coordinates): the profiled cost
#: is rough on small scales (each segment's best radius jumps between grid nodes, float32
#: profiles), so the steps are a few hundredths, where its curvature dominates
JAC_STEP = np.array([0.03, 0.03, 0.02, 0.02])
#: Powell's evaluations per round at most
MAX_EVALS = 500


@dataclass
class ReferenceImage:
    """One image of the reference holder at its known pose (module doc)."""

    name: str
    profiles: BandProfiles
    camera: Camera
    holder: Holder
    R_cam_holder: np.ndarray
    t_cam_holder_mm: np.ndarray
    #: the break's shape when known (the reference holder's drawing), else None: by cost
    shape: str | None = None

    def view(self, look: em.EdgeLook) -> em.EdgeView:
        return em.edge_views(self.R_cam_holder, self.t_cam_holder_mm, self.camera.K,
                             self.holder, look)


def reference_image(image, camera: Camera, holder: Holder, R_cam_holder, t_cam_holder_mm,
                    name: str = "", shape: str | None = None) -> ReferenceImage:
    """Sample the band of ``image`` at the known pose as ``dm+b``'s last pass does."""
    img = np.asarray(image)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    if shape not in (None, "round", "chamfer"):
        raise InputError(f"reference shape must be 'round', 'chamfer' or None, got {shape!r}")
    R = np.asarray(R_cam_holder, float).reshape(3, 3)
    t = np.asarray(t_cam_holder_mm, float).reshape(3)
    bp = sample_band(img, camera, holder, R, t, n_seg=SEGMENTS_PER_EDGE,
                     positions=POSITIONS_PER_SEGMENT)
    return ReferenceImage(name, bp, camera, holder, R, t, shape)


def _read_grey(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise InputError(f"{path}: not a readable image")
    return img


def load_reference_set(folder, limit: int | None = None, use_shape: bool = False
                       ) -> list[ReferenceImage]:
    """The reference images of a rendered set (a folder with ``truth.json``,
    :func:`cutterpose.image_set.load_image_set`): the known pose of each image, and with
    ``use_shape`` its break's shape (``edge_profile``)."""
    camera, holder, entries = load_image_set(folder)
    out = []
    for e in entries[:limit]:
        shape = e.get("edge_profile") if use_shape else None
        out.append(reference_image(_read_grey(Path(folder) / e["file"]), camera, holder,
                                   e["R_cam_holder"], e["t_cam_holder_mm"], e["file"],
                                   shape if shape in ("round", "chamfer") else None))
    if not out:
        raise InputError(f"{folder}: no images in truth.json")
    return out


def load_reference_images(images, poses, camera: Camera, holder: Holder,
                          shape: str | None = None) -> list[ReferenceImage]:
    """Reference images from files and their known poses ``T_cam_holder`` (a list of
    :class:`~cutterpose.geometry.pose.Pose`, e.g. from
    :func:`cutterpose.robot.poses.read_poses`), one per image in order."""
    images = list(images)
    if len(images) != len(poses):
        raise InputError(f"{len(images)} images but {len(poses)} poses: one pose per image")
    if not images:
        raise InputError("no reference images")
    return [reference_image(_read_grey(Path(p)), camera, holder, ps.R, ps.t_mm, Path(p).name,
                            shape) for p, ps in zip(images, poses)]


def _look_of(x, base: em.EdgeLook) -> em.EdgeLook:
    return replace(base, specular=float(math.exp(x[0])), shininess=float(math.exp(x[1])),
                   wall_albedo=float(x[2]), pocket_level=float(x[3]))


def _params_of(look: em.EdgeLook) -> np.ndarray:
    return np.array([math.log(max(look.specular, 1e-3)), math.log(max(look.shininess, 1.0)),
                     look.wall_albedo, look.pocket_level])


def _profiled(cost: np.ndarray, radii: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Minimum over the radius axis of ``cost`` (S, M) refined by the parabola through the grid
    minimum and its neighbours (the grid's steps differ): value and radius (S,)."""
    S, M = cost.shape
    ar = np.arange(S)
    j = np.argmin(cost, axis=1)
    c0 = cost[ar, j]
    jj = np.clip(j, 1, M - 2)
    x0, x1, x2 = radii[jj - 1], radii[jj], radii[jj + 1]
    y0, y1, y2 = cost[ar, jj - 1], cost[ar, jj], cost[ar, jj + 1]
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        d01, d12 = (y1 - y0) / (x1 - x0), (y2 - y1) / (x2 - x1)
        a = (d12 - d01) / (x2 - x0)
        b = d01 - a * (x0 + x1)
        xm = -b / (2 * a)
        ym = y1 - a * (xm - x1) ** 2
    ok = (j == jj) & np.isfinite(ym) & (a > 0) & (xm >= x0) & (xm <= x2)
    return np.where(ok, np.minimum(ym, c0), c0), np.where(ok, xm, radii[j])


def _shift0_costs(ref: ReferenceImage, view: em.EdgeView, look: em.EdgeLook, blurs,
                  radii=CAL_RADII_MM) -> tuple[np.ndarray, np.ndarray]:
    """(B, S) profiled costs at shift 0 and the radii (mm) for ``look`` at each blur."""
    looks = [replace(look, blur_sigma_px=float(b), profile_sigma_px=0.0) for b in blurs]
    cost = profile_costs(ref.profiles, view, looks, radii, (0.0,))[0][..., 0]
    out = [_profiled(np.where(np.isfinite(c), c, 1e300), radii) for c in cost]
    c = np.array([o[0] for o in out])
    c[c >= 1e299] = np.inf          # no radius with a positive gain (see _residuals)
    c[:, ~ref.profiles.valid] = np.inf
    return c, np.array([o[1] for o in out])


def _trimmed(c: np.ndarray, valid: np.ndarray) -> float:
    """The best 75 % of the sampled segments' costs (``dm+b``'s look choice); a segment the
    look cannot fit counts as infinite, not as missing."""
    c = np.sort(c[valid])
    return float(c[: max(1, int(math.ceil(0.75 * len(c))))].sum()) if len(c) else math.inf


def _choose(ref: ReferenceImage, view, x, base, blurs, shapes
            ) -> tuple[tuple[str, float, np.ndarray], float]:
    """The shape and blur of the lowest trimmed cost at shift 0, with the radii the fit then
    needs (the grid up to 1 mm beyond the 90th percentile of the radii found: a poor start look
    sends a few segments to the grid's end, and the model's cost grows with its radii):
    ((shape, blur, radii), cost)."""
    best, cost = ("round", float(blurs[0]), CAL_RADII_MM), math.inf
    for s in ([ref.shape] if ref.shape else shapes):
        c, r = _shift0_costs(ref, view, replace(_look_of(x, base), shape=s), blurs)
        for b, cb, rb in zip(blurs, c, r):
            t = _trimmed(cb, ref.profiles.valid)
            if t < cost:
                fin = rb[np.isfinite(cb)]
                top = float(np.percentile(fin, 90)) if len(fin) else CAL_RADII_MM[-1]
                best = (s, float(b), CAL_RADII_MM[CAL_RADII_MM <= max(top + 1.0, 0.5)])
                cost = t
    return best, cost


@dataclass(frozen=True)
class EdgeLookCalibration:
    """A look calibrated on a reference holder (module doc; saved by :func:`save_edge_look`).

    ``look``: the calibrated photometry (shape and blur are fitted per image); ``x``: its
    parameters in the fit's coordinates (:data:`PARAM_NAMES`); ``cov_mean``: their
    cluster-robust covariance; ``cov_image``: one image's spread (``n_images`` times it);
    ``blurs_px``: the blurs ``dm+b`` chooses among; ``report``: the fit's and the check's
    figures (JSON-able).
    """

    look: em.EdgeLook
    x: tuple[float, ...]
    cov_mean: tuple[tuple[float, ...], ...]
    cov_image: tuple[tuple[float, ...], ...]
    blurs_px: tuple[float, ...] = BLURS_PX
    report: dict = field(default_factory=dict, compare=False, hash=False)
    #: where the look still puts the design edge at the known poses (:func:`calibrate_offsets`)
    offsets: DesignEdgeOffsets = DesignEdgeOffsets()

    def sd(self, per_image: bool = False) -> dict:
        """1-sigma of each fitted parameter in its natural unit (delta method through the log
        of the lobe's weight and exponent)."""
        cov = np.asarray(self.cov_image if per_image else self.cov_mean)
        sd = np.sqrt(np.clip(np.diag(cov), 0, None))
        return {"specular": self.look.specular * sd[0], "shininess": self.look.shininess * sd[1],
                "wall_albedo": sd[2], "pocket_level": sd[3]}

    def variants(self, n_axes: int = N_VARIANT_AXES) -> tuple[em.EdgeLook, ...]:
        """The calibrated look moved by +-1 sd along the ``n_axes`` main axes of the
        calibration's covariance (``cov_mean``; inside the fit's bounds)."""
        cov = np.asarray(self.cov_mean, float)
        if not np.all(np.isfinite(cov)):
            return ()
        val, vec = np.linalg.eigh(cov)
        out = []
        for k in np.argsort(val)[::-1][:n_axes]:
            if val[k] <= 0:
                continue
            d = math.sqrt(val[k]) * vec[:, k]
            for sgn in (1.0, -1.0):
                out.append(_look_of(np.clip(np.asarray(self.x) + sgn * d, _LOWER, _UPPER),
                                    self.look))
        return tuple(out)

    def band_looks(self, variant_axes: int = 0) -> BandLooks:
        """What ``dm+b`` fits (:class:`~cutterpose.image.edge_band.BandLooks`): the look, its
        offsets and their scatter; with ``variant_axes`` > 0 also :meth:`variants` for the
        budget (not by default: the offsets' measured scatter stands for what the look leaves,
        module doc)."""
        return BandLooks(self.look, self.variants(variant_axes) if variant_axes else (),
                         tuple(self.blurs_px), self.offsets)

    def to_dict(self) -> dict:
        lk = self.look
        return {"format": FORMAT, "version": VERSION,
                "look": {"face_albedo": lk.face_albedo, "specular": lk.specular,
                         "shininess": lk.shininess, "wall_albedo": lk.wall_albedo,
                         "pocket_level": lk.pocket_level, "ring_radius_mm": lk.ring_radius_mm,
                         "blur_sigma_px": lk.blur_sigma_px},
                "blurs_px": list(self.blurs_px),
                "parameters": list(PARAM_NAMES), "x": list(self.x),
                "cov_mean": [list(r) for r in self.cov_mean],
                "cov_image": [list(r) for r in self.cov_image],
                "sd": self.sd(), "sd_per_image": self.sd(per_image=True),
                **_offsets_dict(self.offsets),
                "report": self.report}


class _Workers:
    """Worker processes that each hold the reference images (sent once), and evaluate the
    residuals of a share of them for a look: a cost evaluation of 30 images takes ~1 s, its
    messages (the 4 parameters in, the residuals out) a millisecond."""

    def __init__(self, refs, views, base, workers: int):
        from ..parallel import JobRunner

        self.n = len(refs)
        self.chunks = [c for c in np.array_split(np.arange(self.n), workers) if len(c)]
        self.runner = JobRunner(len(self.chunks), initializer=_worker_init,
                                initargs=(refs, views, base)).__enter__()

    def residuals(self, x, choice, scale) -> np.ndarray:
        jobs = [(c, np.asarray(x, float), [choice[i] for i in c], [scale[i] for i in c])
                for c in self.chunks]
        return np.concatenate(self.runner.map(_worker_residuals, jobs))

    def close(self) -> None:
        self.runner.__exit__(None, None, None)


_WORKER: dict = {}


def _worker_init(refs, views, base) -> None:
    _WORKER.update(refs=refs, views=views, base=base)


def _worker_residuals(job) -> np.ndarray:
    idx, x, choice, scale = job
    w = _WORKER
    return _residuals(x, [w["refs"][i] for i in idx], [w["views"][i] for i in idx], choice,
                      scale, w["base"])


def _residuals(x, refs, views, choice, scale, base, workers: _Workers | None = None):
    """Each segment's ``sqrt(C_s / c_i)`` (module doc), at most :data:`MAX_RESIDUAL`; a sampled
    segment the look cannot fit at all (no radius with a positive gain) counts as that maximum,
    so that a look gains nothing by losing segments; unsampled segments are 0. ``workers``:
    evaluated in those processes (the same numbers)."""
    if workers is not None:
        return workers.residuals(x, choice, scale)
    out = []
    for ref, view, (shape, blur, radii), c0 in zip(refs, views, choice, scale):
        c, _ = _shift0_costs(ref, view, replace(_look_of(x, base), shape=shape), (blur,),
                             radii)
        c = c[0]
        with np.errstate(invalid="ignore"):
            r = np.sqrt(np.clip(c, 0, None) / c0)
        r = np.where(np.isfinite(r), np.minimum(r, MAX_RESIDUAL), MAX_RESIDUAL)
        out.append(np.where(ref.profiles.valid, r, 0.0))
    return np.concatenate(out)


def _objective(x, refs, views, choice, scale, base, workers=None) -> float:
    """``sum rho(r_s^2)``, soft-L1 of scale :data:`F_SCALE` (module doc)."""
    f = _residuals(np.clip(x, _LOWER, _UPPER), refs, views, choice, scale, base, workers)
    return float(np.sum(2 * F_SCALE ** 2 * (np.sqrt(1 + (f / F_SCALE) ** 2) - 1)))


def _fit(x, refs, views, choice, scale, base, tick=None, workers=None):
    """Powell's derivative-free search inside the bounds: each segment's residual jumps where its
    best radius moves to the next grid node, which stalls a Gauss-Newton step (its Jacobian is
    of those jumps); the sum over hundreds of segments is smooth enough for line searches.
    ``tick(n)``: called after the ``n``-th evaluation (of at most :data:`MAX_EVALS`)."""
    count = [0]

    def objective(xx):
        f = _objective(xx, refs, views, choice, scale, base, workers)
        count[0] += 1
        if tick is not None:
            tick(count[0])
        return f

    return minimize(objective, x, method="Powell", bounds=list(zip(_LOWER, _UPPER)),
                    options={"xtol": 1e-2, "ftol": 1e-4, "maxfev": MAX_EVALS})


def _jacobian(x, refs, views, choice, scale, base, workers=None):
    """Central differences of the residuals at :data:`JAC_STEP` (one-sided at a bound)."""
    J = np.empty((sum(len(r.profiles.edge) for r in refs), len(x)))
    for k in range(len(x)):
        lo, hi = x.copy(), x.copy()
        lo[k] = max(x[k] - JAC_STEP[k], _LOWER[k])
        hi[k] = min(x[k] + JAC_STEP[k], _UPPER[k])
        J[:, k] = ((_residuals(hi, refs, views, choice, scale, base, workers)
                    - _residuals(lo, refs, views, choice, scale, base, workers))
                   / (hi[k] - lo[k]))
    return J


def _image_index(refs) -> np.ndarray:
    return np.concatenate([np.full(len(r.profiles.edge), i) for i, r in enumerate(refs)])


def _cluster_covariance(J, f, idx, n_img):
    """(cov of the mean, cov of one image) of the soft-L1 fit from the raw residuals ``f`` and
    their Jacobian ``J`` (module doc)."""
    z = (f / F_SCALE) ** 2
    w = 1.0 / np.sqrt(1.0 + z)                         # rho'(z): the IRLS weight
    H = J.T @ (w[:, None] * J)
    g = np.zeros((n_img, J.shape[1]))
    np.add.at(g, idx, (w * f)[:, None] * J)
    try:
        Hi = np.linalg.inv(H)
    except np.linalg.LinAlgError:
        P = J.shape[1]
        return np.full((P, P), np.inf), np.full((P, P), np.inf)
    meat = g.T @ g * (n_img / max(n_img - 1, 1))
    cov = Hi @ meat @ Hi
    cov = 0.5 * (cov + cov.T)
    return cov, n_img * cov


def calibrate_edge_look(refs: list[ReferenceImage], start: em.EdgeLook | None = None,
                        blurs=BLURS_PX, shapes=("round", "chamfer"), rounds: int = ROUNDS,
                        progress=None, tick=None, workers: int = 1) -> EdgeLookCalibration:
    """Fit the look to the reference profiles with the design-edge shift at 0 (module doc).

    Parameters
    ----------
    refs : reference images (:func:`reference_image`, :func:`load_reference_set`).
    start : the look to start from (default: ``dm+b``'s nominal look); its face albedo, light
        and everything but the fitted parameters are kept.
    blurs, shapes : what is chosen per image (``dm+b``'s).
    progress : callable(str) for a line per round.
    tick : callable(round, evaluations, max_evaluations) after every evaluation of the cost
        (a progress bar: a round takes ~250 evaluations, ~1 s each on 30 images).
    workers : processes that evaluate the cost (each holds the reference images; the result
        is the same as with one).

    Returns
    -------
    EdgeLookCalibration : without the check (:func:`shift_at_truth` adds it).
    """
    if not refs:
        raise InputError("calibrate_edge_look: no reference images")
    n_ok = sum(int(r.profiles.valid.sum()) for r in refs)
    if n_ok < 6 * len(PARAM_NAMES):
        raise InputError(f"calibrate_edge_look: the band was measured on {n_ok} segments only "
                         "(wrong poses, or the edges not in the images)")
    base = replace(start or em.EdgeLook(), shape="round", blur_sigma_px=0.9,
                   profile_sigma_px=0.0)
    x = np.clip(_params_of(base), _LOWER, _UPPER)
    views = [r.view(base) for r in refs]
    choice, scale, start_cost = [], [], []
    for ref, view in zip(refs, views):
        ch, t = _choose(ref, view, x, base, blurs, shapes)
        choice.append(ch)
        c, _ = _shift0_costs(ref, view, replace(_look_of(x, base), shape=ch[0]), (ch[1],),
                             ch[2])
        fin = c[0][np.isfinite(c[0])]
        scale.append(max(float(np.median(fin)) if len(fin) else 1.0, 1e-9))
        start_cost.append(t)
    pool = _Workers(refs, views, base, workers) if workers > 1 and len(refs) > 1 else None
    try:
        return _calibrate(refs, views, base, x, choice, scale, start_cost, n_ok, blurs, shapes,
                          rounds, progress, tick, pool)
    finally:
        if pool is not None:
            pool.close()


def _calibrate(refs, views, base, x, choice, scale, start_cost, n_ok, blurs, shapes, rounds,
               progress, tick, pool) -> EdgeLookCalibration:
    """The rounds of :func:`calibrate_edge_look` from its start (``pool``: a
    :class:`_Workers` or None)."""
    sol = None

    def ticker(k):
        return None if tick is None else (lambda n: tick(k, n, MAX_EVALS))

    for k in range(max(1, rounds)):
        sol = _fit(x, refs, views, choice, scale, base, ticker(k + 1), pool)
        x = np.clip(sol.x, _LOWER, _UPPER)
        new = [_choose(r, v, x, base, blurs, shapes)[0] for r, v in zip(refs, views)]
        changed = sum(a[:2] != b[:2] for a, b in zip(new, choice))
        if progress:
            progress(f"round {k + 1}: cost {sol.fun:.1f} after {sol.nfev} evaluations, "
                     f"{changed} images changed shape or blur")
        if not changed:
            break
        choice = new
        sol = None
    if sol is None:     # the last round changed the choice: fit once more with it held
        sol = _fit(x, refs, views, choice, scale, base, ticker(max(1, rounds) + 1), pool)
        x = np.clip(sol.x, _LOWER, _UPPER)
    idx = _image_index(refs)
    J = _jacobian(x, refs, views, choice, scale, base, pool)
    f = _residuals(x, refs, views, choice, scale, base, pool)
    cov_mean, cov_image = _cluster_covariance(J, f, idx, len(refs))
    look = _look_of(x, base)
    end_cost = []
    for ref, view, (s, b, _) in zip(refs, views, choice):
        c, _ = _shift0_costs(ref, view, replace(look, shape=s), (b,))
        end_cost.append(_trimmed(c[0], ref.profiles.valid))
    report = {"images": len(refs), "segments": n_ok,
              "cost_ratio_to_start": float(np.sum(end_cost) / np.sum(start_cost)),
              "per_image": [{"image": r.name, "shape": s, "blur_px": b,
                             "cost_ratio_to_start": float(e / t) if t > 0 else None}
                            for r, (s, b, _), e, t in zip(refs, choice, end_cost,
                                                          start_cost)],
              "optimizer": {"method": "Powell", "success": bool(sol.success),
                            "evaluations_last_round": int(sol.nfev)}}
    return EdgeLookCalibration(look, tuple(float(v) for v in x),
                               tuple(tuple(float(v) for v in r) for r in cov_mean),
                               tuple(tuple(float(v) for v in r) for r in cov_image),
                               tuple(float(b) for b in blurs), report)


def _pose_error_at_truth(ref: ReferenceImage, f, offset_mm: float = 0.0):
    """(6,) error of the pose fitted (as ``dm+b`` fits it, from the true pose) to the fit's
    design-edge points moved outwards by ``offset_mm``; None with fewer than 6 points."""
    dof = Pose(ref.R_cam_holder, ref.t_cam_holder_mm).dof
    e = design_pose(f, f.best.moved(offset_mm, ref.profiles.px_per_mm), ref.camera.K, dof) - dof
    return e if np.all(np.isfinite(e)) else None


def calibrate_offsets(refs: list[ReferenceImage], cal: EdgeLookCalibration,
                      shapes=("round", "chamfer")) -> EdgeLookCalibration:
    """The design-edge offset per shape that the calibrated look still leaves (module doc):
    ``dm+b``'s profile fit at each known pose with the look (shape chosen by cost, as at run
    time) and its pose fitted from the true pose to the design-edge points.

    The offset of a segment is ``delta - d tan(theta)`` (mm outwards;
    :func:`~cutterpose.image.edge_band.view_lean`): ``delta`` uniform, ``d`` the depth below the
    face at which the located edge behaves (a point ``d`` below the face images ``d tan(theta)``
    outwards of the design edge: a parallax that changes sign across the view, i.e. a tilt
    error proportional to the tilt; on the path-traced ``new`` holders the look puts the edge
    ~0.45 mm down a chamfer and ~0.25 mm down a fillet). Both are fitted, per shape, to the
    pose errors at the known poses, linear in them: ``min sum_i |W (e_i + g_i delta + h_i
    d)|^2`` with ``W`` the rotations at a :data:`OFFSET_LEVER_MM` lever (mm) and the
    translations in mm (a uniform offset is what the pose cannot tell from depth: it moves Z).
    The depth is kept only when it predicts the images better in leave-one-out (the weighted
    pose error of each image under the fit to the others) and the shape has
    :data:`MIN_DEPTH_IMAGES` images or more; otherwise ``d = 0``. Their covariance is
    cluster-robust over the images. A shape seen on fewer than :data:`MIN_OFFSET_IMAGES`
    reference images (by its fit: a worn fillet may pass for a chamfer) keeps no offset.

    The offsets' scatter (the budget's edge-model term): the standard deviation over the
    images of the uniform offset that zeroes each one's Z error with ``d`` applied.
    """
    looks = replace(cal.band_looks(), offsets=DesignEdgeOffsets())
    per: dict = {}
    radii: dict = {}
    z = [float(r.t_cam_holder_mm[2]) for r in refs]
    for ref in refs:
        f = fit_band(ref.profiles, ref.camera, ref.holder, ref.R_cam_holder,
                     ref.t_cam_holder_mm, shapes, looks=looks)
        e0 = _pose_error_at_truth(ref, f)
        if e0 is None:
            continue
        lean = view_lean(ref.view(cal.look), ref.profiles.edge, ref.profiles.frac)
        e1 = _pose_error_at_truth(ref, f, OFFSET_STEP_MM)
        e2 = _pose_error_at_truth(ref, f, -DEPTH_STEP_MM * lean)
        if e1 is None or e2 is None:
            continue
        per.setdefault(f.best.look.shape, []).append(
            (e0, (e1 - e0) / OFFSET_STEP_MM, (e2 - e0) / DEPTH_STEP_MM))
        if np.isfinite(f.radius_median_mm):
            radii.setdefault(f.best.look.shape, []).append(f.radius_median_mm)
    off, scatter, depth, cov_od, rep = [], [], [], [], {}
    for shape, rows in sorted(per.items()):
        n = len(rows)
        if n < MIN_OFFSET_IMAGES:
            rep[shape] = {"images": n, "offset_mm": None,
                          "note": f"fewer than {MIN_OFFSET_IMAGES} images: no offset"}
            continue
        e = np.array([r[0] for r in rows])                          # (n, 6)
        A = np.stack([np.array([r[1] for r in rows]), np.array([r[2] for r in rows])],
                     axis=-1)                                       # (n, 6, 2)
        # the depth only where it predicts images it was not fitted on better
        cv = {k: _loo_error(e, A[..., :k]) for k in ((1, 2) if n >= MIN_DEPTH_IMAGES else (1,))}
        k = min(cv, key=cv.get)
        p, cov = _offset_fit(e, A[..., :k])
        delta, d = float(p[0]), float(p[1]) if k > 1 else 0.0
        each = -(e[:, 5] + A[:, 5, 1] * d) / A[:, 5, 0]
        spread = float(np.std(each, ddof=1))
        off.append((shape, delta))
        scatter.append((shape, spread))
        c2 = np.zeros((2, 2))
        c2[:k, :k] = cov
        cov_od.append((shape, tuple(tuple(float(v) for v in r) for r in c2)))
        if k > 1:
            depth.append((shape, d))
        after = e + A[..., :k] @ p
        sds = np.sqrt(np.clip(np.diag(c2), 0.0, None))
        rep[shape] = {"images": n, "offset_mm": delta, "sd_mm": float(sds[0]),
                      "depth_mm": d if k > 1 else None,
                      "depth_sd_mm": float(sds[1]) if k > 1 else None,
                      "loo_error": {("uniform" if j == 1 else "uniform+depth"): float(v)
                                    for j, v in cv.items()},
                      "scatter_mm": spread,
                      "z_error_at_truth_mm": float(np.mean(e[:, 5])),
                      "pose_error_sd_before": [float(v) for v in e.std(axis=0, ddof=1)],
                      "pose_error_sd_after": [float(v) for v in after.std(axis=0, ddof=1)],
                      "per_image_offset_mm": [float(v) for v in each]}
    report = dict(cal.report)
    report["design_edge_offset"] = rep
    return replace(cal, report=report, offsets=DesignEdgeOffsets(
        tuple(off), tuple(scatter), tuple(depth), tuple(cov_od),
        (float(min(z)), float(max(z))) if off else None,
        tuple((k, (min(radii[k]), max(radii[k]))) for k, _ in off if k in radii)))


def _offset_weights() -> np.ndarray:
    """The pose error's weights: rotations (deg) at :data:`OFFSET_LEVER_MM`, translations mm."""
    return np.r_[np.full(3, OFFSET_LEVER_MM * math.pi / 180.0), np.ones(3)]


def _offset_fit(e: np.ndarray, A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Offset coefficients ``p`` minimising ``sum_i |W (e_i + A_i p)|^2`` (e (n, 6), A (n, 6,
    k)) and their cluster-robust covariance over the images (k, k)."""
    w = _offset_weights()
    n = len(e)
    Aw, ew = w[None, :, None] * A, w[None, :] * e
    H = np.einsum("nkp,nkq->pq", Aw, Aw)
    p = np.linalg.solve(H, -np.einsum("nkp,nk->p", Aw, ew))
    g = np.einsum("nkp,nk->np", Aw, ew + Aw @ p)
    Hi = np.linalg.inv(H)
    return p, Hi @ (g.T @ g) @ Hi * (n / max(n - 1, 1))


def _loo_error(e: np.ndarray, A: np.ndarray) -> float:
    """Mean weighted squared pose error of each image under the offsets fitted on the others
    (leave-one-out)."""
    w = _offset_weights()
    out = []
    for i in range(len(e)):
        keep = np.arange(len(e)) != i
        p, _ = _offset_fit(e[keep], A[keep])
        out.append(float(np.sum((w * (e[i] + A[i] @ p)) ** 2)))
    return float(np.mean(out))


def shift_at_truth(refs: list[ReferenceImage], looks: BandLooks | None = None,
                   shapes=("round", "chamfer")) -> dict:
    """``dm+b``'s profile fit at the known poses with the shift free: per image the mean
    design-edge shift (px and mm) over the segments it uses and the Z error of the pose fitted
    to its design-edge points from the true pose; over all images the mean and sd of those
    (``looks`` None: the generic looks)."""
    per, seg_px, seg_mm = [], [], []
    for ref in refs:
        f = fit_band(ref.profiles, ref.camera, ref.holder, ref.R_cam_holder,
                     ref.t_cam_holder_mm, shapes, looks=looks)
        v = ref.profiles.valid & np.isfinite(f.best.shift_var_px2)
        s = f.best.shift_px[v]
        mm = s / ref.profiles.px_per_mm[v]
        seg_px.append(s)
        seg_mm.append(mm)
        e = _pose_error_at_truth(ref, f)
        per.append({"image": ref.name, "shape": f.best.look.shape,
                    "blur_px": f.best.look.blur_sigma_px, "segments": int(v.sum()),
                    "mean_px": float(s.mean()) if len(s) else None,
                    "mean_mm": float(mm.mean()) if len(s) else None,
                    "z_error_mm": None if e is None else float(e[5])})
    z = np.array([p["z_error_mm"] for p in per if p["z_error_mm"] is not None])
    means = np.array([p["mean_px"] for p in per if p["mean_px"] is not None])
    means_mm = np.array([p["mean_mm"] for p in per if p["mean_mm"] is not None])
    a, b = np.concatenate(seg_px), np.concatenate(seg_mm)
    return {"mean_px": float(means.mean()), "sd_of_image_means_px": float(means.std(ddof=1))
            if len(means) > 1 else 0.0, "mean_mm": float(means_mm.mean()),
            "sd_of_image_means_mm": float(means_mm.std(ddof=1)) if len(means_mm) > 1 else 0.0,
            "segment_sd_px": float(a.std()), "segment_median_px": float(np.median(a)),
            "segment_mean_mm": float(b.mean()),
            "z_error_mean_mm": float(z.mean()) if len(z) else None,
            "z_error_sd_mm": float(z.std(ddof=1)) if len(z) > 1 else None, "per_image": per}


def save_edge_look(cal: EdgeLookCalibration, path) -> None:
    """Write the calibration as JSON (``cutterpose calibrate-edge-look --out``)."""
    Path(path).write_text(json.dumps(cal.to_dict(), indent=2) + "\n")


def _number(d: dict, key: str, where: str) -> float:
    v = d.get(key)
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not is_finite_number(v):
        raise EdgeLookFileError(f"{where}: '{key}' must be a finite number, got {v!r}")
    return float(v)


def _matrix(d: dict, key: str, n: int, where: str) -> tuple:
    m = d.get(key)
    try:
        a = np.asarray(m, float)
    except (TypeError, ValueError, OverflowError):
        a = None
    if a is None or a.shape != (n, n) or not np.all(np.isfinite(a)):
        raise EdgeLookFileError(f"{where}: '{key}' must be a finite {n} x {n} matrix")
    if not np.allclose(a, a.T, rtol=1e-6, atol=1e-12) or np.linalg.eigvalsh(a).min() < -1e-9:
        raise EdgeLookFileError(f"{where}: '{key}' must be symmetric positive semi-definite")
    return tuple(tuple(float(v) for v in r) for r in a)


def edge_look_from_dict(d, where: str = "edge look") -> EdgeLookCalibration:
    """Validate and read :meth:`EdgeLookCalibration.to_dict` (raises
    :class:`~cutterpose.errors.EdgeLookFileError` naming the field)."""
    if not isinstance(d, dict) or d.get("format") != FORMAT:
        raise EdgeLookFileError(f"{where}: not an edge look file ('format' must be "
                                f"{FORMAT!r}; write one with `cutterpose calibrate-edge-look`)")
    if d.get("version") not in READS_VERSIONS:
        raise EdgeLookFileError(f"{where}: version {d.get('version')!r} is not supported "
                                f"(this build reads versions {list(READS_VERSIONS)})")
    lk = d.get("look")
    if not isinstance(lk, dict):
        raise EdgeLookFileError(f"{where}: 'look' must be an object")
    vals = {k: _number(lk, k, f"{where}: look") for k in
            ("face_albedo", "specular", "shininess", "wall_albedo", "pocket_level",
             "ring_radius_mm", "blur_sigma_px")}
    try:
        look = em.EdgeLook(shape="round", profile_sigma_px=0.0, **vals)
    except InputError as e:
        raise EdgeLookFileError(f"{where}: look: {e}") from None
    if look.face_albedo <= 0 or look.shininess < 1:
        raise EdgeLookFileError(f"{where}: look: face_albedo must be > 0 and shininess >= 1")
    if d.get("parameters") != list(PARAM_NAMES):
        raise EdgeLookFileError(f"{where}: 'parameters' must be {list(PARAM_NAMES)}")
    x = d.get("x")
    if (not isinstance(x, list) or len(x) != len(PARAM_NAMES)
            or not all(isinstance(v, (int, float)) and is_finite_number(v) for v in x)):
        raise EdgeLookFileError(f"{where}: 'x' must be {len(PARAM_NAMES)} finite numbers")
    blurs = d.get("blurs_px")
    if (not isinstance(blurs, list) or not blurs or not all(
            isinstance(b, (int, float)) and math.isfinite(b) and 0 < b <= 5 for b in blurs)):
        raise EdgeLookFileError(f"{where}: 'blurs_px' must be a list of blurs in (0, 5] px")
    n = len(PARAM_NAMES)
    return EdgeLookCalibration(look, tuple(float(v) for v in x),
                               _matrix(d, "cov_mean", n, where),
                               _matrix(d, "cov_image", n, where),
                               tuple(float(b) for b in blurs),
                               d.get("report") if isinstance(d.get("report"), dict) else {},
                               _offsets_from_dict(d, where))


def _offsets_dict(o: DesignEdgeOffsets) -> dict:
    """The file's keys of :class:`DesignEdgeOffsets` (the sds derived from the covariance, for
    the reader)."""
    sd = {k: o.sd(k) for k, _ in o.cov_mm2}
    return {"design_edge_offset_mm": dict(o.offset_mm),
            "design_edge_offset_sd_mm": {k: v[0] for k, v in sd.items()},
            "design_edge_offset_scatter_mm": dict(o.scatter_mm),
            "design_edge_depth_mm": dict(o.depth_mm),
            "design_edge_depth_sd_mm": {k: sd[k][1] for k, _ in o.depth_mm if k in sd},
            "design_edge_offset_depth_cov_mm2": {k: [list(r) for r in v] for k, v in o.cov_mm2},
            "distance_range_mm": list(o.distance_range_mm) if o.distance_range_mm else None,
            "radius_range_mm": {k: list(v) for k, v in o.radius_range_mm}}


def _offsets_from_dict(d: dict, where: str) -> DesignEdgeOffsets:
    """:class:`DesignEdgeOffsets` from a file. Without the joint covariance (version 1) it is
    the offsets' and depths' sds, uncorrelated (the budget then is what version 1's was: a
    uniform shift by the offset's sd adds to the scatter's in quadrature)."""
    cov = _offset_covariances(d, where)
    if not cov:
        sd_o = dict(_offsets(d, "design_edge_offset_sd_mm", where))
        sd_d = dict(_offsets(d, "design_edge_depth_sd_mm", where, MAX_DEPTH_MM))
        cov = tuple((k, ((sd_o.get(k, 0.0) ** 2, 0.0), (0.0, sd_d.get(k, 0.0) ** 2)))
                    for k in sorted(set(sd_o) | set(sd_d)))
    return DesignEdgeOffsets(_offsets(d, "design_edge_offset_mm", where),
                             _offsets(d, "design_edge_offset_scatter_mm", where),
                             _offsets(d, "design_edge_depth_mm", where, MAX_DEPTH_MM), cov,
                             _distance_range(d, where), _radius_ranges(d, where))


def _radius_ranges(d: dict, where: str) -> tuple:
    """The optional ``{shape: [smallest, largest]}`` median radii of the reference breaks."""
    o = d.get("radius_range_mm", {})
    ok = isinstance(o, dict) and all(
        k in ("round", "chamfer") and isinstance(v, list) and len(v) == 2
        and all(isinstance(x, (int, float)) and not isinstance(x, bool) and is_finite_number(x)
                and x >= 0 for x in v) and v[0] <= v[1] for k, v in o.items())
    if not ok:
        raise EdgeLookFileError(f"{where}: 'radius_range_mm' must map 'round' / 'chamfer' to "
                                "[smallest, largest] radii in mm")
    return tuple((k, (float(v[0]), float(v[1]))) for k, v in sorted(o.items()))


def _offset_covariances(d: dict, where: str) -> tuple:
    """The optional ``{shape: 2 x 2}`` covariance of (offset, depth) in mm^2."""
    key = "design_edge_offset_depth_cov_mm2"
    o = d.get(key, {})
    if not isinstance(o, dict) or not all(k in ("round", "chamfer") for k in o):
        raise EdgeLookFileError(f"{where}: '{key}' must map 'round' / 'chamfer' to 2 x 2 "
                                "matrices")
    return tuple((k, _matrix(o, k, 2, f"{where}: {key}")) for k in sorted(o))


def _distance_range(d: dict, where: str) -> tuple[float, float] | None:
    """The optional ``distance_range_mm``: ``[near, far]``, positive and ordered."""
    v = d.get("distance_range_mm")
    if v is None:
        return None
    if (not isinstance(v, list) or len(v) != 2
            or not all(isinstance(x, (int, float)) and not isinstance(x, bool)
                       and is_finite_number(x) and x > 0 for x in v) or v[0] > v[1]):
        raise EdgeLookFileError(f"{where}: 'distance_range_mm' must be [near, far] in mm, "
                                f"0 < near <= far, got {v!r}")
    return float(v[0]), float(v[1])


def _offsets(d: dict, key: str, where: str, bound_mm: float = 1.0) -> tuple:
    """An optional ``{shape: mm}`` object (a calibrated offset is a fraction of a mm, a depth
    a few tenths)."""
    o = d.get(key, {})
    if not isinstance(o, dict) or not all(
            k in ("round", "chamfer") and isinstance(v, (int, float))
            and not isinstance(v, bool) and is_finite_number(v) and abs(v) <= bound_mm
            for k, v in o.items()):
        raise EdgeLookFileError(f"{where}: '{key}' must map 'round' / 'chamfer' to finite "
                                f"values within +-{bound_mm:g} mm")
    return tuple((k, float(v)) for k, v in sorted(o.items()))


def load_edge_look(path) -> EdgeLookCalibration:
    """Read an edge look file (:func:`save_edge_look`).

    Raises
    ------
    EdgeLookFileError
        Missing or unreadable file, not JSON, or a malformed field (the message names it).
    """
    p = Path(path)
    if not p.is_file():
        raise EdgeLookFileError(f"{p}: edge look file not found")
    try:
        d = json.loads(p.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise EdgeLookFileError(f"{p}: not valid JSON ({e})") from None
    return edge_look_from_dict(d, str(p))
