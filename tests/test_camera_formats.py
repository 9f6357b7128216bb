"""HALCON and ROS camera files, model conversion, and `cutterpose camera convert` (issue 6)."""

from __future__ import annotations

import numpy as np
import pytest
from typer.testing import CliRunner

from cutterpose.cli import app
from cutterpose.errors import CameraFileError
from cutterpose.geometry.camera import (
    DivisionCamera,
    OpenCVCamera,
    PinholeCamera,
    default_camera,
)
from cutterpose.geometry.camera_files import (
    convert_camera,
    detect_format,
    load_camera,
    read_halcon,
    save_camera,
    to_division,
    to_opencv,
)

# the example of HALCON's read_cam_par reference page (division model), with its comment,
# tab/space layout and parameter order
HALCON_DOC_EXAMPLE = """# INTERNAL CAMERA PARAMETERS

ParGroup: Camera: Parameter;
  "Internal camera parameters";

Focus:foc:      0.00806039;
  DOUBLE:0.0:;
  "Focal length of the lens [meter]";

Kappa:kappa:    -2253.5;
  DOUBLE::;
  "Radial distortion coefficient [1/(meter*meter)]";

Sx:sx:  1.0629e-05;
  DOUBLE:0.0:;
  "Width of a cell on the sensor [meter]";

Sy:sy:  1.1e-05;
  DOUBLE:0.0:;
  "Height of a cell on the sensor [meter]";

Cx:cx:  378.236;
  DOUBLE:0.0:;
  "X-coordinate of the image center [pixel]";

Cy:cy:  297.587;
  DOUBLE:0.0:;
  "Y-coordinate of the image center [pixel]";

ImageWidth:imgw:    768;
  INT:1:32767;
  "Width of the images [pixel]";

ImageHeight:imgh:   576;
  INT:1:32767;
  "Height of the images [pixel]";
"""

ROS_EXAMPLE = """image_width: 640
image_height: 480
camera_name: narrow_stereo
camera_matrix:
  rows: 3
  cols: 3
  data: [430.2, 0, 306.7, 0, 430.9, 260.4, 0, 0, 1]
distortion_model: plumb_bob
distortion_coefficients:
  rows: 1
  cols: 5
  data: [-0.337, 0.092, 0.0011, -0.0006, 0]
rectification_matrix:
  rows: 3
  cols: 3
  data: [1, 0, 0, 0, 1, 0, 0, 0, 1]
projection_matrix:
  rows: 3
  cols: 4
  data: [430.2, 0, 306.7, 0, 0, 430.9, 260.4, 0, 0, 0, 1, 0]
"""


def test_read_halcon_documentation_example(tmp_path):
    p = tmp_path / "campar.dat"
    p.write_text(HALCON_DOC_EXAMPLE)
    cam = load_camera(p)
    assert isinstance(cam, DivisionCamera)
    assert cam.focal_length_m == 0.00806039 and cam.kappa_per_m2 == -2253.5
    assert cam.pixel_size_m == (1.0629e-05, 1.1e-05)
    assert cam.principal_point_px == (378.236, 297.587) and cam.image_size_px == (768, 576)


def test_halcon_round_trip_is_exact(tmp_path):
    cam = default_camera("table1")
    save_camera(cam, tmp_path / "t1.dat")
    text = (tmp_path / "t1.dat").read_text()
    assert "ParGroup: Camera: Parameter;" in text and "Kappa:kappa:" in text
    back = load_camera(tmp_path / "t1.dat")
    assert back.to_dict() | {"name": ""} == cam.to_dict() | {"name": ""}
    # content sniffing: a HALCON file without its usual suffix
    (tmp_path / "campar.txt").write_text(text)
    assert load_camera(tmp_path / "campar.txt").kappa_per_m2 == cam.kappa_per_m2


@pytest.mark.parametrize("edit, msg", [
    (lambda t: t.replace("Kappa:kappa:    -2253.5;", ""), "missing HALCON parameter 'Kappa'"),
    (lambda t: t.replace("378.236", "abc"), "'Cx' is not a number"),
    (lambda t: t.replace("Kappa:kappa:    -2253.5", "Poly1:poly1: 0"), "'Poly2'"),
    (lambda t: t.replace("Focus:foc:      0.00806039", "Focus:foc: 0"), "telecentric"),
    (lambda t: t.replace("ParGroup: Camera: Parameter", "ParGroup: Foo: Bar"), "not a HALCON"),
])
def test_halcon_errors_name_the_parameter(tmp_path, edit, msg):
    p = tmp_path / "bad.dat"
    p.write_text(edit(HALCON_DOC_EXAMPLE))
    with pytest.raises(CameraFileError, match=msg):
        read_halcon(p)


def test_ros_camera_info_read_write(tmp_path):
    p = tmp_path / "left.yaml"
    p.write_text(ROS_EXAMPLE)
    assert detect_format(p) == "ros"
    cam = load_camera(p)
    assert isinstance(cam, OpenCVCamera) and cam.name == "narrow_stereo"
    assert np.allclose(cam.dist_coeffs, [-0.337, 0.092, 0.0011, -0.0006, 0])
    save_camera(cam, tmp_path / "out.ros.yaml")
    back = load_camera(tmp_path / "out.ros.yaml")
    assert np.allclose(back.K, cam.K) and np.allclose(back.dist_coeffs, cam.dist_coeffs)
    # OpenCV FileStorage YAML with the same suffix is still read as OpenCV
    save_camera(cam, tmp_path / "cv.yaml")
    assert detect_format(tmp_path / "cv.yaml") == "opencv"
    assert np.allclose(load_camera(tmp_path / "cv.yaml").dist_coeffs, cam.dist_coeffs)


def test_ros_refuses_the_division_model(tmp_path):
    with pytest.raises(CameraFileError, match="division"):
        save_camera(default_camera("table1"), tmp_path / "x.ros.yaml")


def test_division_to_opencv_is_close_but_approximate():
    cam = default_camera("table1")
    conv = to_opencv(cam)
    assert not conv.exact and 0 < conv.max_error_px < 0.01
    # both cameras image the same rays at the same pixels, corners included
    w, h = cam.image_size_px
    px = np.array([[0, 0], [w - 1, h - 1], [w / 2, h / 3], [10, h - 10]], float)
    rays = cam.pixel_to_ray(px)
    assert np.abs(conv.camera.project(rays) - px).max() <= conv.max_error_px + 1e-9


def test_opencv_to_division_reports_its_worst_error():
    cv = OpenCVCamera(np.array([[2400, 0, 2050], [0, 2405, 1500], [0, 0, 1.0]]),
                      np.array([-0.05, 0.02, 0.0, 0.0, 0.0]), (4112, 3008))
    conv = to_division(cv)
    assert isinstance(conv.camera, DivisionCamera) and not conv.exact
    # a k2 term the division model lacks: a real, measured, non-zero error
    assert 0.01 < conv.max_error_px < 20
    assert conv.rms_error_px < conv.max_error_px


def test_pinhole_conversions_are_exact():
    pin = PinholeCamera(2000.0, 2010.0, 640.0, 480.0, (1280, 960))
    d = to_division(pin, 5e-6)
    assert d.exact and d.camera.kappa_per_m2 == 0
    assert np.allclose(d.camera.K, pin.K)
    assert convert_camera(pin, "ros").exact


def test_cli_convert_says_when_approximate(tmp_path):
    runner = CliRunner()
    src = tmp_path / "t1.json"
    save_camera(default_camera("table1"), src)
    r = runner.invoke(app, ["camera", "convert", str(src), str(tmp_path / "t1.ros.yaml")])
    assert r.exit_code == 0, r.output
    assert "APPROXIMATE" in r.output and "worst pixel error" in r.output
    r = runner.invoke(app, ["camera", "convert", str(src), str(tmp_path / "t1.dat")])
    assert r.exit_code == 0 and "exact" in r.output
    r = runner.invoke(app, ["camera", "convert", str(tmp_path / "t1.dat"),
                            str(tmp_path / "back.json")])
    assert r.exit_code == 0 and "exact" in r.output
    assert load_camera(tmp_path / "back.json").kappa_per_m2 == -308.215
    r = runner.invoke(app, ["camera", "convert", str(tmp_path / "t1.ros.yaml"),
                            str(tmp_path / "x.out"), "--to", "halcon"])
    assert r.exit_code == 0 and "APPROXIMATE" in r.output
    assert isinstance(read_halcon(tmp_path / "x.out"), DivisionCamera)
    r = runner.invoke(app, ["camera", "convert", str(tmp_path / "missing.dat"),
                            str(tmp_path / "y.json")])
    assert r.exit_code == 2 and "not found" in r.output
