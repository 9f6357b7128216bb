"""The edge-look calibration in the cell, start to end: the reference images at known poses,
the look fitted to them, the design-edge offsets it still leaves, and the check at the known
poses (:func:`calibrate_in_cell`). ``cutterpose calibrate-edge-look`` and any other front end
only call these; the steps themselves are :mod:`cutterpose.calibration.edge_look`'s.
"""

from __future__ import annotations

from pathlib import Path

from ..errors import InputError
from ..geometry.camera import Camera
from ..geometry.holder import Holder, default_holder
from . import edge_look as el
from .edge_look import (
    EdgeLookCalibration,
    ReferenceImage,
    load_reference_images,
    load_reference_set,
)

__all__ = ["reference_images", "calibrate_in_cell", "EDGE_SHAPE_CHOICES"]

#: the reference holder's break as the operator gives it ("truth": each rendered image's own)
EDGE_SHAPE_CHOICES = ("unknown", "round", "chamfer", "truth")


def reference_images(sources, poses=None, camera: Camera | None = None,
                     holder: Holder | None = None, edge_shape: str = "unknown",
                     limit: int | None = None) -> list[ReferenceImage]:
    """The reference images: rendered sets (folders with ``truth.json``; several are pooled)
    when ``poses`` is None, else image files with their known poses ``T_cam_holder`` (one
    :class:`~cutterpose.geometry.pose.Pose` per image, in order). ``edge_shape``: the
    reference holder's break, ``round`` or ``chamfer`` for every image, ``unknown`` (chosen per
    image by cost) or ``truth`` (a rendered set's own, per image). ``limit``: the first N
    images of each set."""
    if edge_shape not in EDGE_SHAPE_CHOICES:
        raise InputError(f"the edge shape must be round, chamfer, unknown or truth, got "
                         f"{edge_shape!r}")
    shape = edge_shape if edge_shape in ("round", "chamfer") else None
    if poses is None:
        missing = [s for s in sources if not (Path(s) / "truth.json").is_file()]
        if missing:
            raise InputError(f"{missing[0]}: not a rendered set (no truth.json); give rendered "
                             "sets, or images and their known poses (--poses)")
        refs = [r for s in sources
                for r in load_reference_set(s, limit=limit, use_shape=edge_shape == "truth")]
        if shape is not None:
            for r in refs:
                r.shape = shape
        return refs
    if edge_shape == "truth":
        raise InputError("the edge shape 'truth' needs a rendered set")
    if camera is None:
        raise InputError("reference images with poses need the camera model")
    images = list(sources)[:limit] if limit else list(sources)
    return load_reference_images(images, poses[:limit] if limit else poses, camera,
                                 holder or default_holder(), shape)


def calibrate_in_cell(refs: list[ReferenceImage], offsets: bool = True, workers: int = 1,
                      progress=None, tick=None) -> EdgeLookCalibration:
    """The look fitted on ``refs`` (:func:`~cutterpose.calibration.edge_look.
    calibrate_edge_look`), then, with ``offsets``, the design-edge offset per shape it still
    leaves (:func:`~cutterpose.calibration.edge_look.calibrate_offsets`), and the check: the
    design-edge shift at the known poses with the generic and the calibrated looks, in
    ``report["shift_at_truth"]`` (:func:`~cutterpose.calibration.edge_look.shift_at_truth`).
    ``progress(text)`` and ``tick(round, n, n_max)`` report on the way; ``workers`` processes
    evaluate the look's cost (the result does not change)."""
    say = progress or (lambda text: None)
    say(f"{len(refs)} reference images; fitting the look with the design edge at the known "
        "poses")
    # the steps are looked up on their module at call time (one seam for tests to stub)
    cal = el.calibrate_edge_look(refs, progress=progress, tick=tick, workers=workers)
    if offsets:
        say("the design-edge offset per shape at the known poses")
        cal = el.calibrate_offsets(refs, cal)
    say("checking: the design-edge shift at the known poses, generic and calibrated looks")
    cal.report["shift_at_truth"] = {"generic": el.shift_at_truth(refs),
                                    "calibrated": el.shift_at_truth(refs, cal.band_looks())}
    return cal
