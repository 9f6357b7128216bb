"""The verdict: when a measured pose is refused, and why (:class:`QualityLimits`,
:class:`Quality`, :func:`verdict`).

Every pose method gives an estimate and its error budget (:mod:`cutterpose.budget`); the verdict
judges them the same way for every method, in this order: the residuals the method fitted
(RMS and worst, ideal px), the working range (paper section 3.2: +-10 deg and +-20 mm about the
nominal pose, with a tolerance), the planar two-fold ambiguity, the per-DOF std, and the error
budget against the robot's tolerance (1 mm at the grasp point, 0.3 deg, 3 sigma). A method may
add its own check afterwards (:meth:`cutterpose.solvers.method.PoseMethod.review`).

This module sits below the solvers and imports none of them (``tests/test_layout.py``).

Convention:
    DOFs as in :mod:`cutterpose.geometry.pose` (alpha, beta, gamma [deg], X, Y, Z [mm]);
    residuals in ideal pixels.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass

import numpy as np

from .budget import ErrorBudget, Tolerance
from .errors import InputError
from .geometry.pose import Pose

__all__ = ["QualityLimits", "Quality", "verdict", "DOF_NAMES", "EDGE_SHAPES", "EDGE_SHAPE_FITS",
           "UNKNOWN_EDGE_BREAK_MM", "NOMINAL_DISTANCE_MM"]

#: the paper's measuring station: the camera 600 mm from the holder's top face
NOMINAL_DISTANCE_MM = 600.0
#: the pocket edge's break shapes a holder's drawing may give (QualityLimits.edge_shape)
EDGE_SHAPES = ("round", "chamfer", "unknown")
#: the shapes the band / radius fit tries for each of them
EDGE_SHAPE_FITS = {"unknown": ("round", "chamfer"), "round": ("round",), "chamfer": ("chamfer",)}
#: the pocket edge's largest break (mm) the corner methods' verdict assumes when the holder's is
#: not given (``QualityLimits.edge_break_mm = None``): a new holder's machined edge break is
#: 0.5-1.5 mm (issue 10), and a worn one's more (the darkening indicator's ``wear`` part)
UNKNOWN_EDGE_BREAK_MM = 1.5

DOF_NAMES = ("alpha_deg", "beta_deg", "gamma_deg", "X_mm", "Y_mm", "Z_mm")


@dataclass(frozen=True)
class QualityLimits:
    """When :func:`cutterpose.pipeline.measure` refuses a pose.

    The working range is the real rig's (paper section 3.2): +-10 deg and +-20 mm around the
    nominal pose, accepted with a tolerance.
    """

    max_rms_px: float = 1.5            #: RMS corner residual (ideal px)
    max_corner_residual_px: float = 4.0
    max_ambiguity_ratio: float = 0.8   #: best / second-best candidate error
    range_center_dof: tuple = (0.0, 0.0, 0.0, 0.0, 0.0, NOMINAL_DISTANCE_MM)
    range_half_width_dof: tuple = (10.0, 10.0, 10.0, 20.0, 20.0, 20.0)
    range_tolerance_dof: tuple = (2.0, 2.0, 2.0, 5.0, 5.0, 5.0)
    max_std_dof: tuple = (0.5, 0.5, 0.5, 2.0, 2.0, 2.0)
    #: unused since the error budget (kept for callers that set it)
    max_edge_bias_dof: tuple = (0.2, 0.2, 0.2, 0.5, 0.5, 0.5)
    #: the error budget's tolerance (3 sigma: 1 mm at the grasp point, 0.3 deg)
    tolerance: Tolerance = Tolerance()
    #: the point (holder frame, mm) whose position the budget checks: the origin, the centre of
    #: the pocket's top plane (a holder file's grasp frame may be given instead)
    grasp_point_mm: tuple = (0.0, 0.0, 0.0)
    #: the pocket edge's break as the holder's drawing gives it: "round" or "chamfer" (only that
    #: shape is fitted), or "unknown" (default: both; ``dm+b`` tells them apart from the band's
    #: profile; ``dm+r``, from the corners alone, cannot, and its budget then carries a
    #: chamfer's unseen depth, refusing nearly every pose: docs/RESULTS.md section 11)
    edge_shape: str = "unknown"
    #: the largest break (mm, fillet radius or chamfer leg) the pocket edge may have, for the
    #: methods that see only the edge's image, not the design edge (``dm``, ``dm+``, PnP): their
    #: budget carries the pose shift of the seen edge lying anywhere between the design edge and
    #: this far outside it (:func:`cutterpose.solvers.corner_budget.edge_break_effect`).
    #: ``None``: not known, 1.5 mm (:data:`UNKNOWN_EDGE_BREAK_MM`); ``0``: a sharp edge (a lab
    #: holder, the analytic renderer's default). ``dm+b`` and ``dm+r`` measure the break and
    #: ignore it.
    edge_break_mm: float | None = None

    def __post_init__(self):
        if self.edge_shape not in EDGE_SHAPES:
            raise InputError(f"edge_shape must be one of {', '.join(EDGE_SHAPES)}, got "
                             f"{self.edge_shape!r}")
        b = self.edge_break_mm
        if b is not None and (isinstance(b, bool) or not isinstance(b, numbers.Real)
                              or not 0 <= b < math.inf):
            raise InputError(f"edge_break_mm must be a finite number >= 0 or None, got {b!r}")

    @property
    def assumed_edge_break_mm(self) -> float:
        """The break the corner methods' budget carries (:attr:`edge_break_mm` or, not given,
        :data:`UNKNOWN_EDGE_BREAK_MM`)."""
        return UNKNOWN_EDGE_BREAK_MM if self.edge_break_mm is None else float(self.edge_break_mm)

    @property
    def edge_shape_fits(self) -> tuple:
        """The break shapes a band or radius fit tries (:data:`EDGE_SHAPE_FITS`)."""
        return EDGE_SHAPE_FITS[self.edge_shape]


@dataclass
class Quality:
    """The verdict: ``ok`` or the reason for refusing."""

    ok: bool
    reason: str = ""
    rms_px: float = math.nan
    ambiguity_ratio: float = math.nan
    #: (6,) pose shift if every edge moved inwards by its possible wear offset (deg, mm)
    edge_bias_dof: np.ndarray | None = None
    edge_offset_px: float = math.nan   #: median possible outward offset of the edges
    note: str = ""                     #: a warning that does not refuse the pose
    budget: ErrorBudget | None = None  #: the error budget (None without a pose)

    def to_dict(self) -> dict:
        return {"ok": self.ok, "reason": self.reason, "rms_residual_px": _f(self.rms_px),
                "ambiguity_ratio": _f(self.ambiguity_ratio), "note": self.note,
                "edge_offset_px": _f(self.edge_offset_px),
                "edge_bias": None if self.edge_bias_dof is None else
                {k: _f(v) for k, v in zip(DOF_NAMES, self.edge_bias_dof)},
                "budget": None if self.budget is None else self.budget.to_dict()}


def _f(x):
    return None if x is None or not math.isfinite(float(x)) else float(x)


def _bias_text(bias) -> str:
    return ", ".join(f"{n} {b:.2f} {'deg' if k < 3 else 'mm'}"
                     for k, (n, b) in enumerate(zip(DOF_NAMES, bias)))


def _range_reason(dof: np.ndarray, limits: QualityLimits) -> str:
    """Why ``dof`` lies outside the working range (with its tolerance), or ''."""
    lo = np.subtract(limits.range_center_dof, limits.range_half_width_dof)
    hi = np.add(limits.range_center_dof, limits.range_half_width_dof)
    tol = np.asarray(limits.range_tolerance_dof)
    out = (dof < lo - tol) | (dof > hi + tol)
    if not out.any():
        return ""
    names = [f"{DOF_NAMES[k]}={dof[k]:.1f}" for k in np.nonzero(out)[0]]
    return f"pose outside the working range: {', '.join(names)}"


def verdict(estimate, budget: ErrorBudget | None, limits: QualityLimits,
            ambiguity: float = math.nan, edge_bias_dof=None,
            edge_offset_px: float = math.nan) -> Quality:
    """The verdict on a method's ``estimate`` (:class:`~cutterpose.solvers.estimate.PoseEstimate`)
    with its ``budget`` (the method's :meth:`~cutterpose.solvers.method.PoseMethod.budget`:
    its std, its residuals ``budget.residuals_px`` and its 3-sigma figures): refused, with the
    reason, on the first limit it breaks (module doc). ``ambiguity``: best over second-best
    candidate error; ``edge_bias_dof``, ``edge_offset_px``: the edges' possible wear (a note,
    :func:`cutterpose.solvers.corner_budget.edge_wear_effect`)."""
    amb, bias, offset_px = ambiguity, edge_bias_dof, edge_offset_px
    if estimate is None or not estimate or budget is None:
        why = ("not solved" if estimate is None else estimate.reason) or "no error budget"
        return Quality(False, f"no pose: {why}", ambiguity_ratio=amb)
    r = budget.residuals_px
    std = budget.std_dof
    rms = float(np.sqrt(np.mean(np.sum(r ** 2, axis=1))))
    q = Quality(True, "", rms, amb, bias, offset_px, budget=budget)
    if bias is not None and np.all(np.isfinite(bias)) and offset_px > 0.1:
        q.note = (f"edges worn: contour position uncertain by ~{offset_px:.1f} px, pose may be "
                  f"biased by {_bias_text(bias)} (in the error budget)")
    dof = Pose(estimate.R_cam_holder, estimate.t_cam_holder_mm).dof
    worst = float(np.sqrt(np.sum(r ** 2, axis=1)).max())
    if rms > limits.max_rms_px:
        q.ok, q.reason = False, (f"corner residual RMS {rms:.2f} px > {limits.max_rms_px} px: "
                                 "the corners do not fit the holder model")
    elif worst > limits.max_corner_residual_px:
        q.ok, q.reason = False, (f"a corner is {worst:.2f} px off the model (> "
                                 f"{limits.max_corner_residual_px} px)")
    elif why := _range_reason(dof, limits):
        q.ok, q.reason = False, why
    elif math.isfinite(amb) and amb > limits.max_ambiguity_ratio:
        q.ok, q.reason = False, (f"planar ambiguity: a second pose fits almost as well (ratio "
                                 f"{amb:.2f} > {limits.max_ambiguity_ratio})")
    elif not np.all(np.isfinite(std)) or np.any(std > np.asarray(limits.max_std_dof)):
        q.ok, q.reason = False, f"pose too uncertain: std {np.round(std, 3).tolist()}"
    elif why := budget.exceeds(limits.tolerance):
        q.ok, q.reason = False, why
    return q
