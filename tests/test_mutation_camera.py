"""The pinhole camera's back-projection against ``K^-1`` by hand (issue 33: the mutation run
found ``(v + cy) / fy``, a dropped skew and a swapped axis unnoticed)."""

from __future__ import annotations

import numpy as np
import pytest

from cutterpose.errors import CameraFileError, InputError
from cutterpose.geometry.camera import PinholeCamera


def test_pinhole_normalize_is_k_inverse_and_project_its_inverse():
    cam = PinholeCamera(1200.0, 1100.0, 640.0, 480.0, (1280, 960), skew=3.5, name="bench")
    K = np.array([[1200.0, 3.5, 640.0], [0.0, 1100.0, 480.0], [0.0, 0.0, 1.0]])
    np.testing.assert_array_equal(cam.K, K)
    px = np.array([[10.0, 20.0], [900.0, 700.0], [640.0, 480.0], [1279.0, 3.0]])
    m = np.linalg.solve(K, np.column_stack([px, np.ones(len(px))]).T).T
    np.testing.assert_allclose(cam.normalize_px(px), m[:, :2], rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(cam.normalize_px(px[1]), m[1, :2], rtol=1e-12)
    X = np.column_stack([m[:, :2], np.ones(len(px))]) * 700.0
    np.testing.assert_allclose(cam.project(X), px, atol=1e-9)
    d = cam.to_dict()
    assert d["name"] == "bench" and d["model"] == "pinhole" and d["distortion"] is None
    assert d["camera_matrix"] == K.tolist() and d["image_size_px"] == [1280, 960]
    back = PinholeCamera.from_matrix(K.tolist(), (1280, 960), name="bench")
    assert back == cam and back.name == "bench"
    with pytest.raises(InputError, match="K must be 3x3"):
        PinholeCamera.from_matrix(np.eye(2), (1280, 960))


@pytest.mark.parametrize("field, value", [("fx", 0.0), ("fy", -1.0), ("cx", np.nan),
                                          ("cy", np.inf), ("skew", np.nan)])
def test_pinhole_refuses_bad_values_naming_them(field, value):
    kw = dict(fx=1200.0, fy=1100.0, cx=640.0, cy=480.0, image_size_px=(1280, 960))
    kw[field] = value
    with pytest.raises(CameraFileError, match=f"^pinhole camera: field .{field}. must be"):
        PinholeCamera(**kw)
