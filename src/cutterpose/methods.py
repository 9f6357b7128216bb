"""The registry of pose methods: name -> class (:class:`~cutterpose.solvers.method.PoseMethod`).

A method is a class (its ``estimate``, ``budget`` and the rest: :mod:`cutterpose.solvers.method`)
and one line in :data:`REGISTRY`, ``"name": "module:Class"``. Classes are imported only when
asked for, so that ``import cutterpose`` stays light and worker processes resolve methods by
name. ``<name>+lm`` is any correspondence method followed by Levenberg-Marquardt on the pixel
reprojection error (:class:`cutterpose.solvers.pnp.refine.LMRefined`).

A method with ``needs_correspondences = False`` (``initial``, ``dm``, ``dm+`` ...) receives the
corners in contour order in ``solve`` but with an unknown start and direction, and must not rely
on their order.

>>> from cutterpose.methods import get_method
>>> m = get_method("dm+b")
>>> m.name, m.refines_design_edge, m.needs_corners
('dm+b', True, False)
>>> get_method("epnp+lm").description
'EPnP (Lepetit et al. 2009) + LM refinement'
"""

from __future__ import annotations

import importlib

from .errors import InputError
from .solvers.method import FunctionMethod, PoseMethod

__all__ = ["Method", "PoseMethod", "FunctionMethod", "REGISTRY", "get_method", "available_methods",
           "describe_methods", "parse_methods"]

#: a method made from a solve function: ``Method(name, solve, needs_correspondences=True,
#: description="")`` (:class:`~cutterpose.solvers.method.FunctionMethod`)
Method = FunctionMethod

#: name -> "module:Class", imported when asked for
REGISTRY: dict[str, str] = {
    "opencv-sqpnp": "cutterpose.solvers.pnp.opencv_ref:OpenCVSQPnP",
    "opencv-ippe-lm": "cutterpose.solvers.pnp.opencv_ref:OpenCVIPPELM",
    "dlt": "cutterpose.solvers.pnp.dlt:Dlt",
    "epnp": "cutterpose.solvers.pnp.epnp:EPnP",
    "rpnp": "cutterpose.solvers.pnp.rpnp:RPnP",
    "aspnp": "cutterpose.solvers.pnp.aspnp:ASPnP",
    "opnp": "cutterpose.solvers.pnp.opnp:OPnP",
    "initial": "cutterpose.solvers.vanishing:Initial",
    "initial-paper": "cutterpose.solvers.vanishing:InitialPaper",
    "dm": "cutterpose.solvers.dm:Dm",
    "dm-paper": "cutterpose.solvers.dm:DmPaper",
    "dm+": "cutterpose.solvers.dm:DmPlus",
    "dm+r": "cutterpose.solvers.radius_budget:EdgeRadius",
    "dm+b": "cutterpose.solvers.edge_band:EdgeBand",
}


def _load(name: str) -> type[PoseMethod]:
    mod, _, cls = REGISTRY[name].partition(":")
    return getattr(importlib.import_module(mod), cls)


def available_methods() -> list[str]:
    """Names of the registered methods whose module is importable."""
    out = []
    for name in REGISTRY:
        try:
            _load(name)
        except (ImportError, AttributeError):
            continue
        out.append(name)
    return out


def describe_methods() -> dict[str, str]:
    """name -> one-line description of every registered method (``(not available)`` when its
    module cannot be imported in this build)."""
    out = {}
    for name in REGISTRY:
        try:
            out[name] = _load(name).description
        except (ImportError, AttributeError):
            out[name] = "(not available)"
    return out


def get_method(name: str | PoseMethod) -> PoseMethod:
    """The method registered as ``name`` (``<name>+lm`` adds LM refinement to a correspondence
    method); a :class:`PoseMethod` passes through."""
    if isinstance(name, PoseMethod):
        return name
    if name.endswith("+lm"):
        base = get_method(name[:-3])
        if not base.needs_correspondences:
            raise InputError(f"'+lm' needs a correspondence method; {base.name} has none")
        from .solvers.pnp.refine import LMRefined

        return LMRefined(base)
    if name not in REGISTRY:
        raise InputError(f"unknown method {name!r}; choose from {', '.join(REGISTRY)} "
                         "(or <pnp-method>+lm)")
    try:
        cls = _load(name)
    except (ImportError, AttributeError) as e:
        raise InputError(f"method {name!r} is not available in this build ({e})") from None
    return cls()


def parse_methods(spec: str) -> list[PoseMethod]:
    """``"a,b,c"`` -> methods; an unknown name fails before any work starts."""
    names = [s.strip() for s in spec.split(",") if s.strip()]
    if not names:
        raise InputError("no method given")
    return [get_method(n) for n in names]
