"""Region of interest (paper section 2.1, step 1): the holder's face template at the nominal
pose matched on the reduced image by normalised correlation.

Convention:
    ROI ``(u0, v0, u1, v1)`` in full-image pixels, ``u1, v1`` exclusive.
"""

from __future__ import annotations

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
