"""Tests of the realistic renderer (render.py) and of `cutterpose render` / `render-set`."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from cutterpose.cli import app
from cutterpose.errors import InputError
from cutterpose.geometry.camera import DivisionCamera, default_camera
from cutterpose.geometry.holder import default_holder
from cutterpose.geometry.pose import Pose
from cutterpose.render.analytic import (
    PRESETS,
    add_sensor_noise,
    defocus,
    preset,
    render_holder,
)
from cutterpose.render.sets import render_set


def small_camera(scale: int = 4) -> DivisionCamera:
    """The Table 1 camera with ``scale`` x larger pixels: the same field of view and
    distortion on a (4112 / scale) x (3008 / scale) sensor."""
    c = default_camera("table1")
    sx, sy = c.pixel_size_m
    cx, cy = c.principal_point_px
    return DivisionCamera(c.focal_length_m, c.kappa_per_m2, (sx * scale, sy * scale),
                          ((cx + 0.5) / scale - 0.5, (cy + 0.5) / scale - 0.5),
                          (c.image_size_px[0] // scale, c.image_size_px[1] // scale))


CAM = small_camera()
HOLDER = default_holder()
#: no texture, blur or noise: the image is the antialiased geometry
CLEAN = preset("easy").with_(texture=0.0, machining_marks=0.0, scratches=0, corrosion=0.0,
                             defocus_sigma_px=0.0, electrons_per_dn=0.0, read_noise_dn=0.0)
TILTED = Pose.from_euler(6.0, -8.0, 4.0, 12.0, -9.0, 615.0)


def _bilinear(img, u, v):
    u0, v0 = int(np.floor(u)), int(np.floor(v))
    a, b = u - u0, v - v0
    p = img[v0:v0 + 2, u0:u0 + 2].astype(float)
    return (p[0, 0] * (1 - a) * (1 - b) + p[0, 1] * a * (1 - b) + p[1, 0] * (1 - a) * b
            + p[1, 1] * a * b)


def _inside_pocket(xy):
    c = HOLDER.corners_mm.astype(np.float32)
    return cv2.pointPolygonTest(c, (float(xy[0]), float(xy[1])), False) > 0


@pytest.mark.parametrize("settings", ["easy", "hard"])
def test_corners_sit_on_the_image_edges(settings):
    """Around every true corner: bright on the top-face side, dark in the pocket."""
    r = render_holder(TILTED, CAM, settings=settings, seed=1)
    img = cv2.medianBlur(r.image, 5)  # the paper's preprocessing, against noise and scratches
    np.testing.assert_allclose(r.corners_px, CAM.project(TILTED.apply(HOLDER.points_holder_mm)))
    bright, dark = [], []
    for i, (X, Y) in enumerate(HOLDER.corners_mm):
        if i in r.occluded_corners:
            continue
        for dx, dy in [(1, 1), (1, -1), (-1, 1), (-1, -1)]:
            p = np.array([X + 5.0 * dx, Y + 5.0 * dy])  # ~2 px from the corner
            u, v = CAM.project(TILTED.apply([p[0], p[1], 0.0]))
            g = _bilinear(img, u, v)
            (dark if _inside_pocket(p) else bright).append(g)
    assert len(bright) and len(dark)
    if settings == "easy":
        assert min(bright) > 70 and max(dark) < 70  # the paper's threshold separates them
    else:  # worn edges and dim light: still separable on the whole
        assert np.median(bright) > np.median(dark) + 40


@pytest.mark.parametrize("camera", [CAM, CAM.to_pinhole()], ids=["division", "pinhole"])
def test_edge_position_matches_projection(camera):
    """The antialiased step across the inner contour crosses half height at the projected edge
    (sub-pixel), for both lens models: the distortion is in the rays."""
    r = render_holder(TILTED, camera, settings=CLEAN, seed=0)
    img = r.image.astype(float)
    errs = []
    for k in (0, 4, 10):  # three edges along X: y = -90, y = -30 (right lobe), y = 90
        (x0, y0), (x1, y1) = HOLDER.edges[k]
        xm = 0.5 * (x0 + x1)
        pts = TILTED.apply([[xm, y0, 0.0], [xm + 2.0, y0, 0.0]])
        (um, vm), (u2, v2) = camera.project(pts)
        u = round(um)
        v_edge = vm + (v2 - vm) / (u2 - um) * (u - um)  # the edge's row at column u
        col = img[int(v_edge) - 4:int(v_edge) + 6, u]
        top_above = _inside_pocket((xm, y0 + 1.0))  # pocket at +Y: top face is above
        hi = col[0] if top_above else col[-1]
        lo = col[-1] if top_above else col[0]
        # the straddling pixel's coverage by the top face gives the edge position
        j = int(np.argmin(np.abs(np.arange(len(col)) + int(v_edge) - 4 - v_edge)))
        cov = (col[j] - lo) / (hi - lo)
        vpix = int(v_edge) - 4 + j
        est = vpix - 0.5 + cov if top_above else vpix + 0.5 - cov
        errs.append(est - v_edge)
    assert np.max(np.abs(errs)) < 0.08, errs


def test_division_and_pinhole_differ():
    a = render_holder(TILTED, CAM, settings=CLEAN)
    b = render_holder(TILTED, CAM.to_pinhole(), settings=CLEAN)
    d = np.linalg.norm(a.corners_px - b.corners_px, axis=1)
    assert d.max() > 0.1  # kappa < 0: barrel, ~0.5 px at the holder's ends at this size
    assert np.mean(a.image != b.image) > 0.005


def test_seeded_and_sizes():
    a = render_holder(TILTED, CAM, settings="worn", seed=5)
    b = render_holder(TILTED, CAM, settings="worn", seed=5)
    c = render_holder(TILTED, CAM, settings="worn", seed=6)
    assert a.image.dtype == np.uint8 and a.image.shape == (CAM.image_size_px[1],
                                                           CAM.image_size_px[0])
    assert a.corners_px.shape == (20, 2)
    np.testing.assert_array_equal(a.image, b.image)
    assert np.mean(a.image != c.image) > 0.3
    assert a.pose is TILTED


def test_presets_change_the_image():
    def top_face_mean(r):
        # a patch of top face between the pocket and the outer rectangle, at X = 0
        u, v = CAM.project(TILTED.apply([0.0, -110.0, 0.0]))
        return float(r.image[int(v) - 3:int(v) + 4, int(u) - 20:int(u) + 21].mean())

    easy = render_holder(TILTED, CAM, settings="easy", seed=2)
    dim = render_holder(TILTED, CAM, settings="dim", seed=2)
    assert top_face_mean(dim) < 0.7 * top_face_mean(easy)
    occ = render_holder(TILTED, CAM, settings="occluded", seed=2)
    assert len(occ.occluded_corners) == 1
    u, v = occ.corners_px[occ.occluded_corners[0]]
    win = np.s_[int(v) - 6:int(v) + 7, int(u) - 6:int(u) + 7]
    assert occ.image[win].astype(float).mean() != pytest.approx(
        easy.image[win].astype(float).mean(), abs=3)
    assert set(PRESETS) >= {"easy", "dim", "worn", "occluded", "hard"}
    with pytest.raises(InputError):
        preset("nope")


def test_pocket_depth_changes_only_the_pocket():
    a = render_holder(TILTED, CAM, settings=CLEAN.with_(pocket_depth_mm=80.0))
    b = render_holder(TILTED, CAM, settings=CLEAN.with_(pocket_depth_mm=20.0))
    diff = a.image != b.image
    assert diff.mean() > 0.002
    # every changed pixel views the pocket: its ray meets Z = 0 inside the inner contour
    vv, uu = np.nonzero(diff)
    m = CAM.normalize_px(np.column_stack([uu, vv]).astype(float))
    o = -TILTED.R.T @ TILTED.t_mm
    d = np.column_stack([m, np.ones(len(m))]) @ TILTED.R
    s = -o[2] / d[:, 2]
    xy = o[:2] + s[:, None] * d[:, :2]
    c = HOLDER.corners_mm.astype(np.float32)
    dist = np.array([cv2.pointPolygonTest(c, (float(x), float(y)), True) for x, y in xy])
    assert np.all(dist > -0.5)  # inside, or within a pixel (antialiasing) of the contour


def test_edge_wear_darkens_only_a_band_along_the_contour():
    pose = Pose.from_euler(0.0, 0.0, 0.0, 0.0, 0.0, 600.0)
    a = render_holder(pose, CAM, settings=CLEAN).image.astype(float)
    b = render_holder(pose, CAM, settings=CLEAN.with_(edge_wear_mm=4.0)).image.astype(float)

    def row_mean(img, y_mm):  # along the long edge y = -90 of the pocket, X in [-100, 100]
        p = CAM.project(pose.apply([[x, y_mm, 0.0] for x in np.linspace(-100, 100, 50)]))
        return np.mean([_bilinear(img, u, v) for u, v in p])

    assert row_mean(b, -91.5) < 0.85 * row_mean(a, -91.5)  # 1.5 mm from the contour: worn
    assert row_mean(b, -115.0) == pytest.approx(row_mean(a, -115.0), abs=0.5)  # 25 mm: not


def test_camera_behind_the_holder_is_refused():
    with pytest.raises(InputError):
        render_holder(Pose.from_euler(180.0, 0, 0, 0, 0, 600), CAM)


def test_noise_and_blur_helpers():
    rng = np.random.default_rng(0)
    flat = np.full((200, 200), 100.0, np.float32)
    s = preset("easy").with_(electrons_per_dn=4.0, read_noise_dn=2.0)
    noisy = add_sensor_noise(flat, s, rng).astype(float)
    # variance = signal / k + read^2 = 25 + 4
    assert noisy.std() == pytest.approx(np.sqrt(100 / 4 + 4), rel=0.05)
    assert noisy.mean() == pytest.approx(100, abs=0.3)
    step = np.zeros((50, 50), np.float32)
    step[:, 25:] = 200
    for kernel in ("gaussian", "disk"):
        b = defocus(step, 2.0, kernel)
        assert 0 < b[25, 24] < 200 and b[25, 0] == pytest.approx(0, abs=1e-3)
        assert b[25, 49] == pytest.approx(200, abs=1e-3)


def test_render_set_writes_the_protocol_format(tmp_path):
    path = render_set(3, 7, tmp_path, CAM)
    doc = json.loads(path.read_text())
    assert doc["camera"] == CAM.to_dict()
    assert len(doc["images"]) == 3
    for e in doc["images"]:
        img = cv2.imread(str(tmp_path / e["file"]), cv2.IMREAD_UNCHANGED)
        assert img.shape == (CAM.image_size_px[1], CAM.image_size_px[0]) and img.dtype == np.uint8
        pose = Pose(np.array(e["R_cam_holder"]), np.array(e["t_cam_holder_mm"]))
        assert np.all(np.abs(pose.euler_deg) <= 10) and np.all(
            np.abs(pose.t_mm - [0, 0, 600]) <= 20)
        np.testing.assert_allclose(e["corners_px"],
                                   CAM.project(pose.apply(HOLDER.points_holder_mm)), atol=1e-9)
        assert e["difficulty"] in PRESETS
    # the set does not depend on the number of worker processes
    path2 = render_set(3, 7, tmp_path / "par", CAM, workers=2)
    assert json.loads(path2.read_text())["images"] == doc["images"]
    for e in doc["images"]:
        np.testing.assert_array_equal(cv2.imread(str(tmp_path / e["file"])),
                                      cv2.imread(str(tmp_path / "par" / e["file"])))


def test_render_set_over_a_distance_range(tmp_path):
    """``distance_mm``: depths drawn in (near, far) with the same angles and sideways shifts as
    the default set of the seed, the light auto-exposed: the face's grey level stays near the
    600 mm set's (without it, (600 / 900)^2 = 0.44 of it at 900 mm)."""
    near = json.loads(render_set(2, 5, tmp_path / "near", CAM, mix=(("easy", 1.0),))
                      .read_text())["images"]
    far = json.loads(render_set(2, 5, tmp_path / "far", CAM, mix=(("easy", 1.0),),
                                distance_mm=(850.0, 900.0)).read_text())
    assert far["distance_mm"] == [850.0, 900.0]
    for a, b in zip(near, far["images"]):
        pa = Pose(np.array(a["R_cam_holder"]), np.array(a["t_cam_holder_mm"]))
        pb = Pose(np.array(b["R_cam_holder"]), np.array(b["t_cam_holder_mm"]))
        assert 850.0 <= pb.t_mm[2] <= 900.0
        np.testing.assert_allclose(pb.euler_deg, pa.euler_deg)
        np.testing.assert_allclose(pb.t_mm[:2], pa.t_mm[:2])

        def face_grey(e, folder):
            img = cv2.imread(str(tmp_path / folder / e["file"]), cv2.IMREAD_GRAYSCALE)
            c = np.array(e["corners_px"])
            lo, hi = c.min(axis=0).astype(int), c.max(axis=0).astype(int)
            return float(np.median(img[lo[1]:hi[1], lo[0]:hi[0]]))

        ratio = face_grey(b, "far") / face_grey(a, "near")
        assert 0.75 < ratio < 1.33, ratio


def test_cli_render_set_distance_option(tmp_path):
    res = CliRunner().invoke(app, ["render-set", "--count", "1", "--distance-mm", "900:600",
                                   "--out", str(tmp_path / "x")])
    assert res.exit_code == 2 and "--distance-mm" in res.output


def test_cli_render_and_render_set(tmp_path):
    cam_file = tmp_path / "cam.json"
    cam_file.write_text(json.dumps(CAM.to_dict()))
    out = tmp_path / "one.png"
    res = CliRunner().invoke(app, ["render", "--pose", "1,2,3,4,5,606", "--out", str(out),
                                   "--camera", str(cam_file), "--preset", "dim", "--seed", "3"])
    assert res.exit_code == 0, res.output
    assert str(out) in res.output
    truth = json.loads(out.with_suffix(".truth.json").read_text())
    assert truth["images"][0]["t_cam_holder_mm"] == [4.0, 5.0, 606.0]
    assert cv2.imread(str(out), cv2.IMREAD_UNCHANGED).shape == (752, 1028)
    res = CliRunner().invoke(app, ["render", "--pose", "1,2", "--out", str(out)])
    assert res.exit_code == 2 and "six" in res.output
    res = CliRunner().invoke(app, ["render-set", "--count", "2", "--seed", "1", "--out",
                                   str(tmp_path / "set"), "--camera", str(cam_file)])
    assert res.exit_code == 0, res.output
    assert len(json.loads((tmp_path / "set" / "truth.json").read_text())["images"]) == 2


def test_cli_render_set_views_needs_pbr(tmp_path):
    res = CliRunner().invoke(app, ["render-set", "--count", "2", "--views", "2",
                                   "--out", str(tmp_path / "x")])
    assert res.exit_code == 2 and "--views" in res.output and "pbr" in res.output
    assert not (tmp_path / "x" / "truth.json").exists()
