"""The registry of pose methods, by name.

Every method has the common signature ``solve(points_px, camera, model) -> PoseEstimate``. A
method with ``needs_correspondences = False`` (the paper's ``initial``, ``dm`` and ``dm+``)
receives the detected corners in contour order but with an unknown start and direction, and must
not rely on their order.

``<name>+lm`` is any correspondence method followed by Levenberg-Marquardt on the pixel
reprojection error (:mod:`cutterpose.solvers.pnp.refine`).

Entries are imported lazily so that ``import cutterpose`` stays light and worker processes resolve
methods by name.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass

from .errors import InputError

__all__ = ["Method", "get_method", "available_methods", "parse_methods"]


@dataclass(frozen=True)
class Method:
    """A pose method: ``solve(points_px, camera, model) -> PoseEstimate``.

    ``searches_range``: correspondence-free and searching a motion range (``dm``, ``dm+``,
    ``dm-paper``); its ``solve`` also takes the keywords ``motion_range`` (the rig's working
    range), ``start`` (a close ``(R, t_mm)`` or None), ``partial`` (some corners missing or
    spurious) and ``close_start_rms_px``. ``base`` and ``refine``: a method that refines the
    pose of ``base`` with more than the corners (the edge model, the image):
    ``refine(start, features, camera, model, shapes) -> PoseEstimate`` (``dm+r``, ``dm+b``;
    their ``solve`` on corners alone is the registered fallback). ``takes_edge_look``: its
    ``refine`` also takes ``edge_look=`` (a look calibrated in the cell: ``dm+b``).
    ``start_from_outline``: on the field chain its refinement starts from the pose of the
    pocket outline's homography instead of ``base``'s pose from the corners (``dm+b``: the band
    needs a start within a few pixels, which the outline fit gives, and no corners), so
    :func:`cutterpose.pipeline.measure` skips the line fits and corners for it.
    """

    name: str
    solve: Callable
    needs_correspondences: bool = True
    description: str = ""
    searches_range: bool = False
    base: str | None = None
    refine: Callable | None = None
    takes_edge_look: bool = False
    start_from_outline: bool = False


# name -> (module, attribute, needs_correspondences, description)
_ENTRIES: dict[str, tuple[str, str, bool, str]] = {
    "opencv-sqpnp": ("cutterpose.solvers.pnp.opencv_ref", "solve_sqpnp", True,
                     "OpenCV SQPnP (reference)"),
    "opencv-ippe-lm": ("cutterpose.solvers.pnp.opencv_ref", "solve_ippe_lm", True,
                       "OpenCV IPPE + solvePnPRefineLM: the ML reference"),
    "dlt": ("cutterpose.solvers.pnp.dlt", "solve", True, "DLT (homography for planar points)"),
    "epnp": ("cutterpose.solvers.pnp.epnp", "solve", True, "EPnP (Lepetit et al. 2009)"),
    "rpnp": ("cutterpose.solvers.pnp.rpnp", "solve", True, "RPnP (Li et al. 2012)"),
    "aspnp": ("cutterpose.solvers.pnp.aspnp", "solve", True, "ASPnP (Zheng et al. 2013)"),
    "opnp": ("cutterpose.solvers.pnp.opnp", "solve", True, "OPnP (Zheng et al. 2013)"),
    "initial": ("cutterpose.solvers.vanishing", "solve", False,
                "initial pose from vanishing points and contour area (paper 2.2)"),
    "initial-paper": ("cutterpose.solvers.vanishing", "solve_paper", False,
                      "initial pose, the paper's image-plane vanishing-point median"),
    "dm": ("cutterpose.solvers.matching", "solve_dm", False, "distance matching (paper 2.3)"),
    "dm-paper": ("cutterpose.solvers.matching", "solve_dm_paper", False,
                 "the paper as written: its initial pose (2.2) + distance matching (2.3)"),
    "dm+": ("cutterpose.solvers.matching", "solve_dm_plus", False,
            "distance matching + continuous correspondence-free refinement"),
    "dm+r": ("cutterpose.solvers.edge_radius", "solve", False,
             "dm+ + the radius of the broken pocket edge: the design edge's pose"),
    "dm+b": ("cutterpose.solvers.edge_band", "solve", False,
             "the band across every edge fitted with the edge model from the outline's pose "
             "(dm+'s on the paper's chain): the design edge's pose (needs the image)"),
}

#: how the pipeline runs a method beyond ``solve`` (:class:`Method`): range search, or the
#: refinement ``(module, attribute)`` of a base method's pose
_PIPELINE: dict[str, dict] = {
    "dm": {"searches_range": True},
    "dm+": {"searches_range": True},
    "dm-paper": {"searches_range": True},
    "dm+r": {"base": "dm+", "refine": ("cutterpose.solvers.edge_radius", "refine_features")},
    "dm+b": {"base": "dm+", "refine": ("cutterpose.solvers.edge_band", "refine_features"),
             "takes_edge_look": True, "start_from_outline": True},
}


def available_methods() -> list[str]:
    """Names of the registered methods whose module is importable."""
    out = []
    for name, (mod, attr, _, _) in _ENTRIES.items():
        try:
            getattr(importlib.import_module(mod), attr)
        except (ImportError, AttributeError):
            continue
        out.append(name)
    return out


def get_method(name: str) -> Method:
    """Resolve a method by name (``<name>+lm`` adds LM refinement to a correspondence method)."""
    if name.endswith("+lm"):
        base = get_method(name[:-3])
        if not base.needs_correspondences:
            raise InputError(f"'+lm' needs a correspondence method; {base.name} has none")
        refine = importlib.import_module("cutterpose.solvers.pnp.refine")
        return Method(name, refine.with_refinement(base.solve, name), True,
                      base.description + " + LM refinement")
    if name not in _ENTRIES:
        raise InputError(f"unknown method {name!r}; choose from {', '.join(_ENTRIES)} "
                         "(or <pnp-method>+lm)")
    mod, attr, corr, desc = _ENTRIES[name]
    extra = dict(_PIPELINE.get(name, {}))
    try:
        fn = getattr(importlib.import_module(mod), attr)
        if "refine" in extra:
            extra["refine"] = getattr(importlib.import_module(extra["refine"][0]),
                                      extra["refine"][1])
    except (ImportError, AttributeError) as e:
        raise InputError(f"method {name!r} is not available in this build ({e})") from None
    return Method(name, fn, corr, desc, **extra)


def parse_methods(spec: str) -> list[Method]:
    """``"a,b,c"`` -> methods; an unknown name fails before any work starts."""
    names = [s.strip() for s in spec.split(",") if s.strip()]
    if not names:
        raise InputError("no method given")
    return [get_method(n) for n in names]
