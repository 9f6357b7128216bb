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


_LM_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 100, 1e-14)


def ippe_lm_candidates(P: np.ndarray, m: np.ndarray) -> list[Candidate]:
    if not is_planar(P):
        # IPPE is planar only; fall back to SQPnP for a non-planar set.
        cands = sqpnp_candidates(P, m)
        init = cands
    else:
        obj, img = _to_cv(P, m)
        n, rvecs, tvecs, errs = cv2.solvePnPGeneric(obj, img, np.eye(3), None,
                                                    flags=cv2.SOLVEPNP_IPPE)
        init = [(cv2.Rodrigues(r)[0], t.ravel()) for r, t in zip(rvecs, tvecs)]
    out = []
    obj, img = _to_cv(P, m)
    for R, t in init:
        rvec = cv2.Rodrigues(R)[0]
        tvec = t.reshape(3, 1).copy()
        # LM works on normalised coordinates here: the criterion is tight enough for that scale.
        rvec, tvec = cv2.solvePnPRefineLM(obj, img, np.eye(3), None, rvec, tvec,
                                          criteria=_LM_CRITERIA)
        out.append((cv2.Rodrigues(rvec)[0], tvec.ravel()))
    return out


solve_sqpnp = make_solver("opencv-sqpnp", sqpnp_candidates, min_points=3)
solve_ippe_lm = make_solver("opencv-ippe-lm", ippe_lm_candidates, min_points=4)
