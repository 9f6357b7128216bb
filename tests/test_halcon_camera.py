"""HALCON's camera models (area_scan_division, area_scan_polynomial) and their .dat files."""

from __future__ import annotations

import numpy as np
import pytest

from cutterpose.errors import CameraFileError
from cutterpose.geometry.camera import DivisionCamera, PolynomialCamera, camera_from_dict
from cutterpose.geometry.camera_files import (
    convert_camera,
    load_camera,
    read_halcon,
    save_camera,
    to_opencv,
    write_ros,
)

# pixel pitch 10 um, principal point (100, 50), f = 10 mm: every number below is checkable by hand
SX = 1e-5
F = 0.01


def _poly(**kw):
    c = dict(focal_length_m=F, k1_per_m2=1000.0, k2_per_m4=0.0, k3_per_m6=0.0, p1_per_m=2.0,
             p2_per_m=-3.0, pixel_size_m=(SX, SX), principal_point_px=(100.0, 50.0),
             image_size_px=(640, 480))
    c.update(kw)
    return PolynomialCamera(**c)


def test_polynomial_model_by_hand():
    """HALCON: u_u = u + u(K1 r^2 + ...) + 2 P1 u v + P2 (r^2 + 2u^2) (and v alike), from
    distorted to undistorted metric coordinates. Pixel (300, 150): u = 2 mm, v = 1 mm,
    r^2 = 5e-6 m^2, K1 r^2 = 0.005;
    u_u = 0.002 + 0.00001 + 2*2*0.002*0.001 - 3*(5e-6 + 8e-6) = 0.001979 -> column 297.9;
    v_u = 0.001 + 0.000005 + 2*(5e-6 + 2e-6) + 2*(-3)*0.002*0.001 = 0.001007 -> row 150.7."""
    cam = _poly()
    ideal = cam.undistort_px([300.0, 150.0])
    np.testing.assert_allclose(ideal, [297.9, 150.7], atol=1e-9)
    # projection of the camera-frame point on that ray gives the observed pixel back
    X = np.array([0.001979, 0.001007, F]) * 50.0
    np.testing.assert_allclose(cam.project(X), [300.0, 150.0], atol=1e-9)
    # a K2, K3 term by hand: r^4 = 2.5e-11, r^6 = 1.25e-16
    cam2 = _poly(k1_per_m2=0.0, k2_per_m4=4e8, k3_per_m6=8e13, p1_per_m=0.0, p2_per_m=0.0)
    s = 1 + 4e8 * 2.5e-11 + 8e13 * 1.25e-16  # = 1.02
    np.testing.assert_allclose(cam2.undistort_px([300.0, 150.0]),
                               [100 + 200 * s, 50 + 100 * s], atol=1e-9)


def test_division_model_by_hand():
    """HALCON: u_u = u / (1 + kappa r^2). kappa = -1000 / m^2 at r^2 = 5e-6: 1 + kappa r^2 =
    0.995, so (300, 150) -> (100 + 200/0.995, 50 + 100/0.995)."""
    cam = DivisionCamera(F, -1000.0, (SX, SX), (100.0, 50.0), (640, 480))
    np.testing.assert_allclose(cam.undistort_px([300.0, 150.0]),
                               [100 + 200 / 0.995, 50 + 100 / 0.995], atol=1e-9)
    X = np.array([200 / 0.995 * SX, 100 / 0.995 * SX, F])
    np.testing.assert_allclose(cam.project(X), [300.0, 150.0], atol=1e-9)


def test_polynomial_round_trip_over_the_image():
    cam = PolynomialCamera(0.012, -900.0, 3e6, -2e10, 0.4, -0.3, (3.45e-6, 3.46e-6),
                           (1010.0, 760.0), (2048, 1536))
    g = np.random.default_rng(1).uniform([0, 0], [2047, 1535], (500, 2))
    np.testing.assert_allclose(cam.distort_px(cam.undistort_px(g)), g, atol=1e-9)
    np.testing.assert_allclose(cam.undistort_px(cam.distort_px(g)), g, atol=1e-9)
    rays = cam.pixel_to_ray(g)
    np.testing.assert_allclose(cam.project(rays * 500.0), g, atol=1e-9)


def test_polynomial_json_round_trip():
    cam = _poly(name="c")
    back = camera_from_dict(cam.to_dict())
    assert isinstance(back, PolynomialCamera)
    assert back.to_dict() == cam.to_dict()
    with pytest.raises(CameraFileError, match="p2_per_m"):
        d = cam.to_dict()
        del d["p2_per_m"]
        camera_from_dict(d)


# a polynomial-model file in the layout of HALCON's write_cam_par (Poly1..Poly5)
HALCON_POLY = """# INTERNAL CAMERA PARAMETERS

ParGroup: Camera: Parameter;
  "Internal camera parameters";

Focus:foc:      0.0121;
  DOUBLE:0.0:;
  "Focal length of the lens [meter]";

Poly1:poly1:   -812.5;
  DOUBLE::;
  "1st polynomial distortion coefficient";

Poly2:poly2:   2.5e+06;
  DOUBLE::;
  "2nd polynomial distortion coefficient";

Poly3:poly3:   -1.5e+10;
  DOUBLE::;
  "3rd polynomial distortion coefficient";

Poly4:poly4:   0.21;
  DOUBLE::;
  "4th polynomial distortion coefficient";

Poly5:poly5:   -0.17;
  DOUBLE::;
  "5th polynomial distortion coefficient";

Sx:sx:   3.45e-06;
  DOUBLE:0.0:;
  "Width of a cell on the sensor";

Sy:sy:   3.45e-06;
  DOUBLE:0.0:;
  "Height of a cell on the sensor";

Cx:cx:   1012.5;
  DOUBLE::;
  "X-coordinate of the image center";

Cy:cy:   771.25;
  DOUBLE::;
  "Y-coordinate of the image center";

ImageWidth:imgw:  2048;
  INT:1:32768;
  "Width of the images";

ImageHeight:imgh:  1536;
  INT:1:32768;
  "Height of the images";"""


def test_read_halcon_polynomial_file(tmp_path):
    p = tmp_path / "cam.dat"
    p.write_text(HALCON_POLY)
    cam = load_camera(p)
    assert isinstance(cam, PolynomialCamera)
    assert (cam.focal_length_m, cam.k1_per_m2, cam.k2_per_m4, cam.k3_per_m6, cam.p1_per_m,
            cam.p2_per_m) == (0.0121, -812.5, 2.5e6, -1.5e10, 0.21, -0.17)
    assert cam.principal_point_px == (1012.5, 771.25) and cam.image_size_px == (2048, 1536)
    # newer parameter names and a Model statement read the same
    q = tmp_path / "cam_k.dat"
    text = HALCON_POLY
    for old, new in (("Poly1:poly1", "K1:k1"), ("Poly2:poly2", "K2:k2"), ("Poly3:poly3", "K3:k3"),
                     ("Poly4:poly4", "P1:p1"), ("Poly5:poly5", "P2:p2")):
        text = text.replace(old, new)
    text = text.replace('"Internal camera parameters";', '"Internal camera parameters";\n\n'
                        "Model:model:   'area_scan_polynomial';\n  STRING;\n  \"Model\";")
    q.write_text(text)
    assert read_halcon(q).to_dict() | {"name": ""} == cam.to_dict() | {"name": ""}


@pytest.mark.parametrize("cam", [
    _poly(name="p"),
    DivisionCamera(0.0081, -2253.5, (1.0629e-5, 1.1e-5), (378.236, 297.587), (768, 576), "d"),
])
def test_halcon_write_read_round_trip(tmp_path, cam):
    p = tmp_path / f"{cam.name}.dat"
    save_camera(cam, p)
    back = read_halcon(p)
    assert type(back) is type(cam)
    assert back.to_dict() == cam.to_dict()
    assert "Poly1:poly1:" in p.read_text() or "Kappa:kappa:" in p.read_text()


def test_halcon_polynomial_errors(tmp_path):
    p = tmp_path / "bad.dat"
    p.write_text(HALCON_POLY.replace("Poly3:poly3:   -1.5e+10;", ""))
    with pytest.raises(CameraFileError, match="Poly3"):
        read_halcon(p)
    p.write_text(HALCON_POLY.replace("Poly4:poly4:   0.21", "Poly4:poly4:   abc"))
    with pytest.raises(CameraFileError, match="Poly4"):
        read_halcon(p)


def test_polynomial_conversions(tmp_path):
    cam = PolynomialCamera(0.0121, -812.5, 2.5e6, 0.0, 0.21, -0.17, (3.45e-6, 3.45e-6),
                           (1012.5, 771.25), (2048, 1536))
    assert convert_camera(cam, "halcon").exact
    # another pixel height: the same camera (exact), expressed in other metric units
    conv = convert_camera(cam, "halcon", pixel_height_m=5e-6)
    assert conv.exact and isinstance(conv.camera, PolynomialCamera)
    assert conv.camera.pixel_size_m[1] == 5e-6
    g = np.random.default_rng(2).uniform([0, 0], [2047, 1535], (200, 2))
    np.testing.assert_allclose(conv.camera.pixel_to_ray(g), cam.pixel_to_ray(g), atol=1e-12)
    conv = to_opencv(cam)
    assert not conv.exact and conv.max_error_px < 0.5
    with pytest.raises(CameraFileError, match="polynomial"):
        write_ros(cam, tmp_path / "x.ros.yaml")


def test_opencv_to_halcon_polynomial(tmp_path):
    """An OpenCV camera with tangential terms: the polynomial model follows it closely, the
    division model (no decentering) cannot; the CLI writes either on request."""
    from typer.testing import CliRunner

    from cutterpose.cli import app
    from cutterpose.geometry.camera import OpenCVCamera
    from cutterpose.geometry.camera_files import to_division, to_polynomial

    K = np.array([[1400.0, 0, 650.0], [0, 1400.0, 470.0], [0, 0, 1]])
    cv = OpenCVCamera(K, np.array([-0.2, 0.08, 0.001, -0.0008, 0.0]), (1280, 960))
    poly = to_polynomial(cv, 4.8e-6)
    div = to_division(cv, 4.8e-6)
    assert isinstance(poly.camera, PolynomialCamera) and not poly.exact
    assert poly.max_error_px < 0.5 < 1.0 < div.max_error_px  # 0.22 and 2.1 px
    src = tmp_path / "cv.json"
    save_camera(cv, src)
    out = CliRunner().invoke(app, ["camera", "convert", str(src), str(tmp_path / "p.dat"),
                                   "--halcon-model", "polynomial", "--pixel-height-um", "4.8"])
    assert out.exit_code == 0, out.output
    assert "APPROXIMATE" in out.output and "polynomial" in out.output
    assert isinstance(read_halcon(tmp_path / "p.dat"), PolynomialCamera)
