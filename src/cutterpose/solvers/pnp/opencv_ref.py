"""Reference solvers from OpenCV, used to prove the experiment harness.

* ``opencv-sqpnp``: ``cv2.solvePnP(..., SOLVEPNP_SQPNP)`` (Terzakis & Lourakis, ECCV 2020), a
  globally optimal solver of a squared object-space error.
* ``opencv-ippe-lm``: ``cv2.solvePnPGeneric(..., SOLVEPNP_IPPE)`` (Collins & Bartoli, IJCV 2014)
  returns the two planar solutions; the one with the smaller reprojection error is refined by
  ``cv2.solvePnPRefineLM``: the maximum-likelihood pose under Gaussian pixel noise.

Both receive ideal (undistorted) pixels and the camera's ``K``, so they work through any camera
model.
"""

from __future__ import annotations

import cv2
import numpy as np

from ..method import CorrespondenceMethod
from .base import Candidate, is_planar, make_solver


def _to_cv(P, m):
    return (np.ascontiguousarray(P, dtype=np.float64).reshape(-1, 1, 3),
            np.ascontiguousarray(m, dtype=np.float64).reshape(-1, 1, 2))


def sqpnp_candidates(P: np.ndarray, m: np.ndarray) -> list[Candidate]:
    obj, img = _to_cv(P, m)
    ok, rvec, tvec = cv2.solvePnP(obj, img, np.eye(3), None, flags=cv2.SOLVEPNP_SQPNP)
    if not ok:
        return []
    return [(cv2.Rodrigues(rvec)[0], tvec.ravel())]


_LM_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 200, 1e-15)
# The LM runs on normalised coordinates scaled by this focal length, so that its stopping rule
# (OpenCV's default epsilon is FLT_EPSILON, an absolute change) sees pixel-sized residuals: on
# raw normalised coordinates (errors ~1e-4) it stopped up to 0.3 mm short of the optimum.
_F_SCALE = 2500.0


def ippe_lm_candidates(P: np.ndarray, m: np.ndarray) -> list[Candidate]:
    obj, img = _to_cv(P, m)
    if not is_planar(P):
        # IPPE is planar only; start from SQPnP for a non-planar set.
        init = sqpnp_candidates(P, m)
    else:
        n, rvecs, tvecs, errs = cv2.solvePnPGeneric(obj, img, np.eye(3), None,
                                                    flags=cv2.SOLVEPNP_IPPE)
        init = [(cv2.Rodrigues(r)[0], t.ravel()) for r, t in zip(rvecs, tvecs)]
    K = np.diag([_F_SCALE, _F_SCALE, 1.0])
    img_px = img * _F_SCALE
    out = []
    for R, t in init:
        rvec = cv2.Rodrigues(R)[0]
        tvec = t.reshape(3, 1).copy()
        rvec, tvec = cv2.solvePnPRefineLM(obj, img_px, K, None, rvec, tvec,
                                          criteria=_LM_CRITERIA)
        out.append((cv2.Rodrigues(rvec)[0], tvec.ravel()))
    return out


solve_sqpnp = make_solver("opencv-sqpnp", sqpnp_candidates, min_points=3)
solve_ippe_lm = make_solver("opencv-ippe-lm", ippe_lm_candidates, min_points=4)


class OpenCVSQPnP(CorrespondenceMethod):
    name = "opencv-sqpnp"
    description = "OpenCV SQPnP (reference)"
    solve = staticmethod(solve_sqpnp)


class OpenCVIPPELM(CorrespondenceMethod):
    name = "opencv-ippe-lm"
    description = "OpenCV IPPE + solvePnPRefineLM: the ML reference"
    solve = staticmethod(solve_ippe_lm)
