"""HALCON plate description files, the hexagonal plate's detector and calibration on renders."""

from __future__ import annotations

from importlib import resources

import numpy as np
import pytest

from cutterpose.calibration.halcon_plate import (
    FINDER_HOLES,
    HalconCaltab,
    HalconPlate,
    HexagonalPlate,
    caltab_description,
    hexagonal_description,
    load_halcon_plate,
    read_plate_description,
    write_plate_description,
)
from cutterpose.calibration.plate import CirclePlate, render_plate, sample_plate_poses
from cutterpose.calibration.view_refine import calibrate_views
from cutterpose.errors import InputError, ModelFileError
from cutterpose.geometry.camera import PolynomialCamera
from cutterpose.geometry.pose import Pose

DATA = resources.files("cutterpose.data")

# a gen_caltab-style file written here by hand (30 mm plate: marks 3.75 mm apart, radius
# 0.9375 mm, frame 15 mm from the centre and 0.9375 mm wide, triangle legs 3.75 mm), with the
# per-row comments and the key order of HALCON's files
CALTAB_30MM = """# Plate Description Version 2
# Description of the standard calibration plate
# used for the camera calibration
#
# 7 rows x 7 columns
# Distance between mark centers [meter]: 0.00375

# Number of marks in y-dimension (rows)
r 7

# Number of marks per row (columns)
c 7

# offset of coordinate system in z-dimension [meter] (optional):
z 0

# Rectangular border (rim and black frame) of calibration plate
#   rim of the calibration plate (min x, max y, max x, min y) [meter]:
o -0.015375 0.015375 0.015375 -0.015375
#   outer border of the black frame (min x, max y, max x, min y) [meter]:
i -0.015 0.015 0.015 -0.015
#   triangular corner mark given by two corner points (x,y, x,y) [meter]
#   (optional):
t -0.015 -0.01125 -0.01125 -0.015

#   width of the black frame [meter]:
w 0.0009375

# calibration marks:  x y radius [meter]
""" + "\n".join(
    f"# calibration marks at y = {y:.6f} m\n" + "\n".join(
        f"{x:.6f} {y:.6f} 0.0009375" for x in np.arange(-3, 4) * 0.00375)
    for y in np.arange(-3, 4) * 0.00375) + "\n"


def test_read_caltab_descr(tmp_path):
    p = tmp_path / "caltab_30mm.descr"
    p.write_text(CALTAB_30MM)
    plate = load_halcon_plate(p)
    assert isinstance(plate, HalconCaltab)
    cp = plate.plate
    assert (cp.rows, cp.cols) == (7, 7)
    assert cp.spacing_mm == pytest.approx(3.75) and cp.diameter_mm == pytest.approx(1.875)
    # frame: outer border 15 mm = 4 spacings, 0.9375 mm wide; triangle legs inside the frame
    # (3.75 - 2 * 0.9375) mm = 0.5 spacings
    assert cp.frame_outer == pytest.approx(4.0) and cp.frame_inner == pytest.approx(3.75)
    assert cp.mark_leg == pytest.approx(0.5)
    np.testing.assert_allclose(plate.points_target_mm[0], [-11.25, -11.25, 0.0])


def test_shipped_descriptions_round_trip(tmp_path):
    caltab = load_halcon_plate(DATA / "caltab_7x7_30mm.descr")
    assert caltab.plate == CirclePlate()  # the project's caltab:7x7:30 plate
    hexp = load_halcon_plate(DATA / "hexplate_15x17_2.5mm.cpd")
    assert isinstance(hexp, HexagonalPlate) and hexp.n_points == 255
    assert len(hexp.finders) == 5 and hexp.spacing_mm == pytest.approx(5.0)
    for plate in (caltab, hexp):
        out = tmp_path / ("x" + (".descr" if plate is caltab else ".cpd"))
        write_plate_description(plate.description, out)
        back = read_plate_description(out)
        np.testing.assert_allclose(back.marks_mm, plate.description.marks_mm, atol=1e-9)
        np.testing.assert_allclose(back.hole_radius_mm, plate.description.hole_radius_mm)
        assert back.polarity == plate.description.polarity
    assert caltab_description().n_marks == 49


@pytest.mark.parametrize("edit, msg", [
    (lambda t: t.replace("r 7", "r 6"), "r x c = 6 x 7"),
    (lambda t: t.replace("0.003750 0.011250 0.0009375", "0.003750 abc 0.0009375"), "line"),
    (lambda t: t.replace("t -0.015 -0.01125 -0.01125 -0.015", ""), "triangular"),
    (lambda t: "# nothing\n", "no calibration marks"),
])
def test_descr_errors(tmp_path, edit, msg):
    p = tmp_path / "bad.descr"
    p.write_text(edit(CALTAB_30MM))
    with pytest.raises(ModelFileError, match=msg):
        load_halcon_plate(p)


def test_hexagonal_lattice_and_finders():
    d = hexagonal_description(9, 11, 0.004, [2, 6], [3, 7])
    plate = HexagonalPlate(d)
    assert plate.spacing_mm == pytest.approx(8.0)  # 2 D between neighbours
    inner = np.all(plate.neighbours >= 0, axis=1)
    # every inner mark has six neighbours 2 D away
    d6 = np.linalg.norm(plate.marks_mm[plate.neighbours[inner]]
                        - plate.marks_mm[inner][:, None], axis=-1)
    np.testing.assert_allclose(d6, 8.0, atol=1e-9)
    assert [f[0] for f in plate.finders] == [2 * 11 + 3, 6 * 11 + 7]
    for (centre, ring), f in zip(FINDER_HOLES, plate.finders):
        assert f[2][0] == centre and set(np.nonzero(f[2][1:])[0]) == set(ring)
    with pytest.raises(InputError, match="overlaps"):
        hexagonal_description(9, 11, 0.004, [2, 3], [3, 4])
    with pytest.raises(InputError, match="leaves the plate"):
        hexagonal_description(9, 11, 0.004, [0], [3])


CAM = PolynomialCamera(0.008, -900.0, 3e6, 0.0, 0.3, -0.2, (4.8e-6, 4.8e-6), (322.0, 236.0),
                       (640, 480))


@pytest.fixture(scope="module")
def hexplate():
    return HalconPlate.from_file(DATA / "hexplate_15x17_2.5mm.cpd")


@pytest.mark.parametrize("blur, found, tol_px", [("easy", 1.0, 0.1), ("blurred", 1.0, 0.3)])
def test_detect_full_view(hexplate, blur, found, tol_px):
    from cutterpose.render.analytic import preset

    # "blurred": a 2.5 px defocus disk fills the 6 px holes in a threshold (they only dim
    # their marks), yet every finder pattern is found
    pose = sample_plate_poses(CAM, 1, hexplate, distance_mm=(300, 350), seed=3)[0]
    det = hexplate.detect(render_plate(CAM, pose, hexplate, settings=preset(blur)))
    assert det and len(det.ids) >= found * hexplate.n_points and det.info["finders"] == 5
    truth = CAM.project(pose.apply(hexplate.points_target_mm[det.ids]))
    assert np.max(np.linalg.norm(det.points_px - truth, axis=1)) < tol_px


def test_detect_partial_view_gives_ids(hexplate):
    # the plate's left half is outside the image: only finders on the right are whole
    pose = Pose(np.eye(3), np.array([-30.0, 0.0, 230.0]), "cam", "target")
    img = render_plate(CAM, pose, hexplate)
    det = hexplate.detect(img)
    assert det, det.reason
    assert 40 < len(det.ids) < hexplate.n_points
    truth = CAM.project(pose.apply(hexplate.points_target_mm[det.ids]))
    assert np.max(np.linalg.norm(det.points_px - truth, axis=1)) < 0.15
    assert np.all(CAM.in_image(truth))


def test_detect_failures_say_why(hexplate):
    assert "round marks" in hexplate.detect(np.full((240, 320), 128, np.uint8)).reason
    # marks without any whole finder pattern: a crop of a plate's corner region
    pose = Pose(np.eye(3), np.array([0.0, 0.0, 300.0]), "cam", "target")
    img = render_plate(CAM, pose, hexplate)
    det = hexplate.detect(img[:150, :200])
    assert not det and "finder pattern" in det.reason


def test_polynomial_calibration_on_renders(hexplate):
    poses = sample_plate_poses(CAM, 4, hexplate, distance_mm=(270, 380), seed=5)
    ids, pts = [], []
    for pose in poses:
        det = hexplate.detect(render_plate(CAM, pose, hexplate))
        assert det, det.reason
        ids.append(det.ids)
        pts.append(det.points_px)
    res = calibrate_views(hexplate, ids, pts, CAM.image_size_px, model="polynomial",
                          pixel_height_m=4.8e-6, bias_rounds=0)
    cam = res.camera
    assert isinstance(cam, PolynomialCamera)
    assert abs(cam.focal_length_m / CAM.focal_length_m - 1) < 0.005
    assert np.max(np.abs(np.subtract(cam.principal_point_px, CAM.principal_point_px))) < 2.0
    assert res.rms_px < 0.1
    assert set(res.std) >= {"focal_length_m", "k1_per_m2", "p2_per_m", "cx_px"}
    assert all(np.isfinite(v) and v > 0 for v in res.std.values())


def test_target_interface(tmp_path):
    from cutterpose.calibration.targets import target_from_spec

    hexp = target_from_spec(str(DATA / "hexplate_15x17_2.5mm.cpd"))
    caltab = target_from_spec(str(DATA / "caltab_7x7_30mm.descr"))
    assert isinstance(hexp, HalconPlate) and hexp.hexagonal and hexp.n_points == 255
    assert isinstance(caltab, HalconPlate) and not caltab.hexagonal
    assert hexp.rotation_symmetry_deg == 0 and caltab.rotation_symmetry_deg == 0
    # the caltab from its .descr is detected by the caltab detector, all 49 points in order
    cam = CAM
    # the sampler keeps the triangular mark in view too (HalconPlate.mark_vertices_mm)
    poses = sample_plate_poses(cam, 6, caltab, distance_mm=(800, 900), seed=2)
    tri = np.c_[caltab.mark_vertices_mm, np.zeros(3)]
    assert all(np.all(cam.in_image(cam.project(p.apply(tri)))) for p in poses)
    pose = poses[0]
    det = caltab.detect(render_plate(cam, pose, caltab))
    assert det and np.array_equal(det.ids, np.arange(49))
    truth = cam.project(pose.apply(caltab.points_target_mm))
    assert np.max(np.linalg.norm(det.points_px - truth, axis=1)) < 0.3
    assert HalconPlate.from_dict(hexp.to_dict()).n_points == 255
    with pytest.raises(ModelFileError, match="file"):
        HalconPlate.from_dict({"kind": "halcon"})
    # a target file naming the description beside it (as render-plate writes target.yaml)
    from cutterpose.calibration.targets import load_target, save_target

    (tmp_path / "plate.cpd").write_text((DATA / "hexplate_15x17_2.5mm.cpd").read_text())
    (tmp_path / "target.yaml").write_text("kind: halcon\nfile: plate.cpd\n")
    assert load_target(tmp_path / "target.yaml").n_points == 255
    save_target(hexp, tmp_path / "again.yaml")
    assert load_target(tmp_path / "again.yaml").hexagonal
    with pytest.raises(ModelFileError, match="not found"):
        HalconPlate.from_dict({"kind": "halcon", "file": "nowhere.cpd"})


def test_calibrate_polynomial_model_on_the_caltab():
    """``intrinsics.calibrate(model="polynomial")``: the caltab plate's complete views."""
    from cutterpose.calibration.intrinsics import calibrate

    plate = CirclePlate()
    poses = sample_plate_poses(CAM, 6, plate, distance_mm=(800, 1000), seed=4)
    pts = np.stack([CAM.project(p.apply(plate.points_mm)) for p in poses])
    pts += np.random.default_rng(0).normal(0, 0.02, pts.shape)
    res = calibrate(pts, plate, CAM.image_size_px, model="polynomial", pixel_height_m=4.8e-6,
                    bias_rounds=0)
    assert isinstance(res.camera, PolynomialCamera)
    assert abs(res.camera.focal_length_m / CAM.focal_length_m - 1) < 0.005
    assert res.rms_px < 0.03 and len(res.per_image_rms_px) == 6
    with pytest.raises(InputError, match="polynomial"):
        calibrate(pts, plate, CAM.image_size_px, model="fisheye")


def test_dark_on_light_plate(tmp_path):
    """The other polarity (HALCON's ``*_dark_on_light`` plates): dark marks, light holes."""
    d = hexagonal_description(9, 11, 0.004, [2, 6], [3, 7], polarity="dark_on_light")
    path = tmp_path / "dark.cpd"
    write_plate_description(d, path)
    plate = HalconPlate.from_file(path)
    assert plate.geometry.polarity == "dark_on_light"
    pose = sample_plate_poses(CAM, 1, plate, distance_mm=(300, 350), seed=1)[0]
    img = render_plate(CAM, pose, plate)
    det = plate.detect(img)
    assert det and len(det.ids) == 99 and det.info["finders"] == 2
    truth = CAM.project(pose.apply(plate.points_target_mm[det.ids]))
    assert np.max(np.linalg.norm(det.points_px - truth, axis=1)) < 0.1
    # the light-on-dark description of the same layout does not match the image
    d.polarity = "light_on_dark"
    assert not HalconPlate(HexagonalPlate(d)).detect(img)


def test_detect_clutter_uneven_light_jpeg(hexplate):
    """Round clutter (discs and rings: rings look like holed marks) around and on the plate,
    light falling to 40 % across the image, a strong tilt, JPEG at quality 70: the plate is
    found with its true indexing, marks cut by clutter are left out."""
    import cv2

    rng = np.random.default_rng(3)
    pose = sample_plate_poses(CAM, 1, hexplate, distance_mm=(300, 340), seed=7,
                              tilt_deg=(45, 55))[0]
    img = render_plate(CAM, pose, hexplate, background=170.0).astype(float)
    h, w = img.shape
    for _ in range(30):
        c = (int(rng.uniform(0, w)), int(rng.uniform(0, h)))
        cv2.circle(img, c, int(rng.uniform(3, 12)), float(rng.choice([240.0, 20.0])),
                   -1 if rng.random() < 0.6 else 2)
    yy, xx = np.mgrid[0:h, 0:w]
    img = np.clip(img * (0.4 + 0.7 * xx / w), 0, 255).astype(np.uint8)
    img = cv2.imdecode(cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 70])[1], 0)
    det = hexplate.detect(img)
    assert det, det.reason
    truth = CAM.project(pose.apply(hexplate.points_target_mm[det.ids]))
    err = np.linalg.norm(det.points_px - truth, axis=1)
    assert len(det.ids) > 200 and np.median(err) < 0.1 and err.max() < 1.0
