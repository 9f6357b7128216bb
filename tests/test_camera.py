import json

import cv2
import numpy as np
import pytest

from cutterpose.errors import CameraFileError
from cutterpose.geometry.camera import (
    DivisionCamera,
    OpenCVCamera,
    PinholeCamera,
    camera_from_dict,
)
from cutterpose.geometry.camera_files import load_camera, save_camera


def _grid(cam, step=16):
    w, h = cam.image_size_px
    u, v = np.meshgrid(np.arange(0, w, step, dtype=float), np.arange(0, h, step, dtype=float))
    # include the exact image corners
    g = np.stack([u.ravel(), v.ravel()], -1)
    return np.vstack([g, [[0, 0], [w - 1, 0], [0, h - 1], [w - 1, h - 1]]])


@pytest.fixture
def cam_cv():
    K = np.array([[2400.0, 0.0, 2050.0], [0, 2410.0, 1500.0], [0, 0, 1]])
    return OpenCVCamera(K, [-0.12, 0.08, 4e-4, -3e-4, -0.02], (4112, 3008))


def test_division_round_trip_whole_image(cam_t1):
    g = _grid(cam_t1)
    assert np.abs(cam_t1.distort_px(cam_t1.undistort_px(g)) - g).max() < 1e-9
    ideal = cam_t1.undistort_px(g)
    assert np.abs(cam_t1.undistort_px(cam_t1.distort_px(ideal)) - ideal).max() < 1e-9


def test_division_model_matches_halcon_formula(cam_t1):
    # u_u = u_d / (1 + kappa r_d^2) in metric image-plane coordinates
    px = np.array([[100.0, 200.0], [4000.0, 2900.0]])
    sx, sy = cam_t1.pixel_size_m
    cx, cy = cam_t1.principal_point_px
    xd, yd = (px[:, 0] - cx) * sx, (px[:, 1] - cy) * sy
    f = 1 + cam_t1.kappa_per_m2 * (xd**2 + yd**2)
    expect = np.stack([xd / f / sx + cx, yd / f / sy + cy], -1)
    assert np.allclose(cam_t1.undistort_px(px), expect, atol=1e-12)
    # kappa < 0 is barrel distortion: undistorted points lie further from the centre
    assert np.all(np.linalg.norm(cam_t1.undistort_px(px) - [cx, cy], axis=1)
                  > np.linalg.norm(px - [cx, cy], axis=1))


def test_opencv_round_trip_whole_image(cam_cv):
    g = _grid(cam_cv)
    ideal = cam_cv.undistort_px(g)
    assert np.abs(cam_cv.distort_px(ideal) - g).max() < 1e-9
    assert np.abs(cam_cv.undistort_px(cam_cv.distort_px(ideal)) - ideal).max() < 1e-9


@pytest.mark.parametrize("which", ["pinhole", "opencv"])
def test_projection_equals_cv2(which, cam_syn, cam_cv, rng):
    cam = cam_syn if which == "pinhole" else cam_cv
    X = rng.uniform([-300, -200, 400], [300, 200, 900], (200, 3))
    dist = np.zeros(5) if which == "pinhole" else cam.dist_coeffs
    ref, _ = cv2.projectPoints(X, np.zeros(3), np.zeros(3), cam.K, dist)
    assert np.abs(cam.project(X) - ref.reshape(-1, 2)).max() < 1e-8


def test_rays_and_normalisation(cam_t1, rng):
    X = rng.uniform([-300, -200, 400], [300, 200, 900], (50, 3))
    px = cam_t1.project(X)
    rays = cam_t1.pixel_to_ray(px)
    assert np.allclose(rays, X / np.linalg.norm(X, axis=1, keepdims=True), atol=1e-12)
    assert np.allclose(cam_t1.normalize_px(px), X[:, :2] / X[:, 2:], atol=1e-12)


def test_points_behind_camera_project_to_nan(cam_syn):
    assert np.all(np.isnan(cam_syn.project([[0.0, 0.0, -5.0]])))


@pytest.mark.parametrize("cam_name", ["cam_syn", "cam_t1", "cam_cv"])
def test_json_round_trip(cam_name, request, tmp_path):
    cam = request.getfixturevalue(cam_name)
    save_camera(cam, tmp_path / "c.json")
    back = load_camera(tmp_path / "c.json")
    assert type(back) is type(cam)
    g = _grid(cam, 256)
    assert np.allclose(back.undistort_px(g), cam.undistort_px(g), atol=1e-9)


@pytest.mark.parametrize("cam_name", ["cam_syn", "cam_cv"])
def test_opencv_yaml_round_trip(cam_name, request, tmp_path):
    cam = request.getfixturevalue(cam_name)
    save_camera(cam, tmp_path / "c.yml")
    text = (tmp_path / "c.yml").read_text()
    for key in ("camera_matrix", "distortion_coefficients", "image_width", "image_height"):
        assert key in text
    back = load_camera(tmp_path / "c.yml")
    assert back.image_size_px == cam.image_size_px
    assert np.allclose(back.K, cam.K)
    g = _grid(cam, 256)
    assert np.allclose(back.undistort_px(g), cam.undistort_px(g), atol=1e-9)


def test_division_to_opencv_yaml_is_refused(cam_t1, tmp_path):
    with pytest.raises(CameraFileError, match="division"):
        save_camera(cam_t1, tmp_path / "c.yml")


#: SHA-256 of the contract's files (shared/spec) as the package bundles them: a clone without
#: shared/ beside it (CI's) still checks the bundled copies against the contract; a new spec
#: is taken in by copying its files to src/cutterpose/data and updating these on purpose
SPEC_SHA256 = {
    "PROTOCOL.md": "e6073efceee3f00027e1bdc4f042e53c36927ce4c44be2c361cb8176c42326e2",
    "camera_synthetic.json": "19b390d15b6d9a4677f56159d6267094cdf53218b174740285c3fccab6b0aab4",
    "camera_table1.json": "fc7f60fe82f6230f9e0540671b58030676c33bda8f94ec26eb2bb6ed2d781cfd",
    "holder.json": "cd64adbc3fa1a7b141562c8ca5a342ac59e717c4fb7f42dc030975d801f21d26",
}


def _live_spec_dirs() -> list:
    """The contract's folders reachable from here: ``$CUTTERPOSE_SPEC_DIR``, ``shared/spec``
    beside the checkout (the integration checkout's, CI's copy) and ``/work/shared/spec``."""
    import os
    from pathlib import Path

    repo = Path(__file__).resolve().parents[1]
    cands = [Path(os.environ["CUTTERPOSE_SPEC_DIR"])] if os.environ.get("CUTTERPOSE_SPEC_DIR") \
        else []
    cands += [repo.parent / "shared" / "spec", Path("/work/shared/spec")]
    return [c for c in dict.fromkeys(cands) if (c / "PROTOCOL.md").is_file()]


def test_spec_files_are_bundled_unchanged():
    """The bundled copies are byte for byte the contract's files: against the recorded hashes
    always, and against every live copy of the contract this machine has."""
    import hashlib
    from importlib import resources

    for name, sha in SPEC_SHA256.items():
        bundled = resources.files("cutterpose.data").joinpath(name).read_bytes()
        assert hashlib.sha256(bundled).hexdigest() == sha, f"bundled {name} differs from the spec"
        for spec in _live_spec_dirs():
            live = (spec / name).read_bytes()
            assert live == bundled, f"{spec / name} differs from the bundled copy"


def test_spec_check_sees_the_live_contract_where_there_is_one():
    """Where the contract is on this machine the live comparison above is not silently empty."""
    from pathlib import Path

    if Path("/work/shared/spec/PROTOCOL.md").is_file():
        assert Path("/work/shared/spec") in _live_spec_dirs()
    assert all((d / n).is_file() for d in _live_spec_dirs() for n in SPEC_SHA256)


BASE = {"model": "division", "image_size_px": [4112, 3008], "focal_length_m": 0.0085,
        "kappa_per_m2": -300.0, "pixel_size_m": [3.45e-6, 3.45e-6],
        "principal_point_px": [2056.0, 1504.0]}


@pytest.mark.parametrize("field", ["model", "image_size_px", "focal_length_m", "kappa_per_m2",
                                   "pixel_size_m", "principal_point_px"])
def test_missing_field_is_named(field):
    d = dict(BASE)
    del d[field]
    with pytest.raises(CameraFileError, match=field):
        camera_from_dict(d)


@pytest.mark.parametrize("field,value", [
    ("focal_length_m", "8.5mm"), ("focal_length_m", float("nan")), ("focal_length_m", -1.0),
    ("kappa_per_m2", None), ("pixel_size_m", [3e-6]), ("pixel_size_m", [3e-6, 0.0]),
    ("principal_point_px", [float("nan"), 1.0]), ("image_size_px", [4112.5, 3008]),
    ("image_size_px", "big"), ("model", "fisheye"),
])
def test_bad_value_is_named(field, value):
    d = dict(BASE)
    d[field] = value
    with pytest.raises(CameraFileError, match=field if field != "model" else "model"):
        camera_from_dict(d)


def test_bad_files(tmp_path):
    with pytest.raises(CameraFileError, match="not found"):
        load_camera(tmp_path / "nope.json")
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(CameraFileError, match="JSON"):
        load_camera(tmp_path / "bad.json")
    (tmp_path / "k.json").write_text(json.dumps({"model": "opencv", "image_size_px": [10, 10],
                                                 "camera_matrix": [[1, 0], [0, 1]],
                                                 "distortion_coefficients": [0, 0, 0, 0]}))
    with pytest.raises(CameraFileError, match="camera_matrix"):
        load_camera(tmp_path / "k.json")
    (tmp_path / "y.yml").write_text("%YAML:1.0\n---\nimage_width: 100\nimage_height: 80\n")
    with pytest.raises(CameraFileError, match="camera_matrix"):
        load_camera(tmp_path / "y.yml")


def test_opencv_model_refuses_skew():
    K = np.array([[2400.0, 0.3, 2050.0], [0, 2410.0, 1500.0], [0, 0, 1]])
    with pytest.raises(CameraFileError, match="skew"):
        OpenCVCamera(K, [0, 0, 0, 0], (4112, 3008))


def test_pinhole_from_spec_values(cam_syn):
    assert isinstance(cam_syn, PinholeCamera)
    assert cam_syn.K[0, 0] == pytest.approx(0.0085 / 3.45e-6)
    assert isinstance(camera_from_dict(BASE), DivisionCamera)
