"""Image sets with known poses: a folder of images and ``truth.json`` (PROTOCOL.md, exchange
formats), as ``cutterpose render-set`` writes them; read by the image experiment and by the edge
look's calibration on a reference holder.

Convention:
    Each entry's pose is ``T_cam_holder``: ``R_cam_holder`` (3 x 3) and ``t_cam_holder_mm``
    (mm), ``x_cam = R x_holder + t`` (:mod:`cutterpose.geometry.pose`).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .errors import InputError
from .geometry.camera import camera_from_dict
from .geometry.holder import default_holder, holder_from_dict

__all__ = ["load_image_set"]


def load_image_set(folder) -> tuple:
    """Read ``truth.json`` of an image set: (camera, holder, entries)."""
    folder = Path(folder)
    path = folder / "truth.json"
    if not path.is_file():
        raise InputError(f"{folder}: no truth.json (an image set is a folder of images and "
                         "truth.json, see PROTOCOL.md)")
    try:
        doc = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise InputError(f"{path}: not valid JSON ({e})") from None
    if not isinstance(doc, dict) or "camera" not in doc or "images" not in doc:
        raise InputError(f"{path}: needs fields 'camera' and 'images'")
    if not isinstance(doc["images"], list):
        raise InputError(f"{path}: field 'images' must be a list")
    camera = camera_from_dict(doc["camera"], where=f"{path}:camera")
    holder = holder_from_dict(doc["holder"], where=f"{path}:holder") if "holder" in doc \
        else default_holder()
    for i, e in enumerate(doc["images"]):
        if not isinstance(e, dict):
            raise InputError(f"{path}: image {i} must be an object")
        for k in ("file", "R_cam_holder", "t_cam_holder_mm"):
            if k not in e:
                raise InputError(f"{path}: image {i} lacks field '{k}'")
        if not isinstance(e["file"], str):
            raise InputError(f"{path}: image {i}: 'file' must be a file name")
        for k, shape in (("R_cam_holder", (3, 3)), ("t_cam_holder_mm", (3,))):
            try:
                a = np.asarray(e[k], float)
            except (TypeError, ValueError, OverflowError):
                a = None
            if a is None or a.shape != shape or not np.all(np.isfinite(a)):
                raise InputError(f"{path}: image {i}: '{k}' must be {shape[0]}"
                                 f"{' x 3' if len(shape) == 2 else ''} finite numbers")
    return camera, holder, doc["images"]
