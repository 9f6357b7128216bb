"""Calibration targets: specs, files, symmetry, detection on real photographs (issue 29).

Real images: tests/data/real/ (rct_10x10 from ROS-Industrial robot_cal_tools, Apache-2.0;
visp_grid36 from ViSP's data set, GPL-2; see their SOURCE.md).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from cutterpose.calibration.targets import (
    TargetDetection,
    load_target,
    save_target,
    symmetry_permutations,
    target_from_spec,
)
from cutterpose.errors import InputError, ModelFileError

REAL = Path(__file__).parent / "data" / "real"
RCT = sorted((REAL / "rct_10x10" / "images").glob("*.png"), key=lambda p: int(p.stem))
VISP = sorted((REAL / "visp_grid36").glob("grid36-*.png"))

SPECS = ["caltab:7x7:30", "circles:6x6:30", "circles:10x10:25.4:origin-dot",
         "acircles:4x11:20:light", "circles:5x4:12:light:origin-dot:diameter=5",
         "chessboard:9x6:25", "charuco:5x7:30:22:DICT_5X5_100"]


@pytest.mark.parametrize("spec", SPECS)
def test_spec_round_trip_and_file(spec, tmp_path):
    t = target_from_spec(spec)
    assert target_from_spec(t.spec()) == t
    for suffix in (".yaml", ".json"):
        save_target(t, tmp_path / f"t{suffix}")
        assert load_target(tmp_path / f"t{suffix}") == t
        assert target_from_spec(str(tmp_path / f"t{suffix}")) == t
    P = t.points_target_mm
    assert P.shape == (t.n_points, 3) and np.all(P[:, 2] == 0)
    x0, x1, y0, y1 = t.bounds_mm
    assert x0 < P[:, 0].min() and P[:, 0].max() < x1 and y0 < P[:, 1].min() < P[:, 1].max() < y1


def test_opencv_object_points():
    # OpenCV's calibration sample: symmetric (j s, i s), asymmetric ((2 j + i % 2) s, i s)
    a = target_from_spec("acircles:4x11:20").points_target_mm
    assert a.shape == (44, 3)
    assert np.allclose(a[:5, :2], [[0, 0], [40, 0], [80, 0], [120, 0], [20, 20]])
    c = target_from_spec("circles:7x5:10").points_target_mm
    assert np.allclose(c[[0, 1, 7]][:, :2], [[0, 0], [10, 0], [0, 10]])
    ch = target_from_spec("chessboard:9x6:25").points_target_mm
    assert np.allclose(ch[[0, 1, 9]][:, :2], [[0, 0], [25, 0], [0, 25]])
    assert target_from_spec(None).spec() == "caltab:7x7:30"


def test_symmetry_of_each_kind():
    sym = {s: target_from_spec(s).rotation_symmetry_deg for s in
           ["circles:6x6:30", "circles:7x5:30", "circles:6x6:30:origin-dot", "acircles:4x11:20",
            "acircles:4x10:20", "chessboard:9x6:25", "chessboard:8x6:25", "caltab:7x7:30",
            "charuco:5x7:30:22:DICT_5X5_100"]}
    assert sym == {"circles:6x6:30": 90, "circles:7x5:30": 180, "circles:6x6:30:origin-dot": 0,
                   "acircles:4x11:20": 0, "acircles:4x10:20": 180, "chessboard:9x6:25": 0,
                   "chessboard:8x6:25": 180, "caltab:7x7:30": 0,
                   "charuco:5x7:30:22:DICT_5X5_100": 0}
    perms = symmetry_permutations(target_from_spec("circles:3x2:1").points_target_mm)
    assert len(perms) == 4 and np.array_equal(perms[0], np.arange(6))


@pytest.mark.parametrize("spec, match", [
    ("blobs:6x6:30", "unknown target"), ("circles:6x6", "COLSxROWS:SPACING"),
    ("circles:6by6:30", "COLSxROWS"), ("circles:6x6:-3", "positive"),
    ("circles:6x6:30:glow", "unknown modifier"), ("circles:6x6:30:diameter=40", "diameter"),
    ("charuco:5x7:30:40:DICT_5X5_100", "marker"), ("charuco:5x7:30:22:DICT_9X9_1", "dictionary"),
    ("chessboard:1x6:25", "2x2")])
def test_bad_specs_are_refused(spec, match):
    with pytest.raises(InputError, match=match):
        target_from_spec(spec)


def test_bad_target_files(tmp_path):
    (tmp_path / "a.yaml").write_text("kind: circles\ncols: 6\n")
    with pytest.raises(ModelFileError, match="missing field"):
        load_target(tmp_path / "a.yaml")
    (tmp_path / "b.json").write_text("{not json")
    with pytest.raises(ModelFileError):
        target_from_spec(str(tmp_path / "b.json"))
    with pytest.raises(ModelFileError, match="not found"):
        target_from_spec(str(tmp_path / "missing.yaml"))
    (tmp_path / "c.yaml").write_text("spec: circles:6x6:30:light\n")
    assert load_target(tmp_path / "c.yaml") == target_from_spec("circles:6x6:30:light")


def test_halcon_files_go_to_the_halcon_module(tmp_path, monkeypatch):
    import sys
    import types

    from cutterpose.calibration.targets import Target

    class FakePlate(Target):  # stands in for halcon_plate.HalconPlate
        kind = "fake_halcon"
        points_target_mm = np.zeros((4, 3))
        bounds_mm = (0, 1, 0, 1)
        detect = darkness = to_dict = lambda *a: None
        from_dict = from_spec = classmethod(lambda *a: None)

        @classmethod
        def from_file(cls, path):
            t = cls()
            t.path = path
            return t

    mod = types.ModuleType("cutterpose.calibration.halcon_plate")
    mod.HalconPlate = FakePlate
    monkeypatch.setitem(sys.modules, "cutterpose.calibration.halcon_plate", mod)
    (tmp_path / "plate.descr").write_text("x")
    t = target_from_spec(str(tmp_path / "plate.descr"))
    assert isinstance(t, FakePlate) and t.path == tmp_path / "plate.descr"


def test_detection_is_falsy_with_a_reason():
    t = target_from_spec("circles:6x6:30")
    d = t.detect(np.full((120, 160), 128, np.uint8))
    assert not d and "not found" in d.reason and len(d.ids) == 0
    assert not t.detect(np.zeros((0, 0), np.uint8)) and t.detect(np.zeros(5)).reason
    assert TargetDetection(np.zeros((2, 2)), [3, 4])


def test_real_visp_grid_keeps_opencv_order_with_its_symmetry():
    t = target_from_spec("circles:6x6:30")
    for p in VISP:
        g = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        d = t.detect(g)
        assert d, f"{p.name}: {d.reason}"
        assert len(d.ids) == 36 and d.rotation_ambiguity_deg == 90
        ok, ref = cv2.findCirclesGrid(g, (6, 6), flags=cv2.CALIB_CB_SYMMETRIC_GRID)
        assert ok
        ref = ref.reshape(-1, 2)
        # the same points as OpenCV's, each within a pixel (ours: ellipse fits), same order
        obj = t.points_target_mm
        own = d.points_px[np.argsort(d.ids)]
        assert np.abs(own - ref).max() < 1.0, p.name
        grid = own.reshape(6, 6, 2)
        ex, ey = grid[0, 1] - grid[0, 0], grid[1, 0] - grid[0, 0]
        assert ex[0] * ey[1] - ex[1] * ey[0] > 0  # right-handed
        assert np.allclose(obj[1, :2] - obj[0, :2], [30, 0])


def test_real_rct_grid_is_oriented_by_its_origin_dot():
    t = target_from_spec("circles:10x10:25.4:origin-dot")
    sizes = []
    for p in RCT:
        g = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        d = t.detect(g)
        assert d, f"{p.name}: {d.reason}"
        assert d.rotation_ambiguity_deg == 0 and len(d.ids) >= 99
        if 0 in d.ids:
            sizes.append(np.prod(d.axes_px[d.ids == 0][0]) / np.median(np.prod(d.axes_px, 1)))
        # the origin dot is dark at its image point (a larger dot than its neighbours)
        by_id = dict(zip(d.ids.tolist(), d.points_px))
        grid_right = by_id[1] - by_id[0] if 0 in by_id else by_id[2] - by_id[1]
        grid_down = by_id[10] - by_id[0] if 0 in by_id else by_id[20] - by_id[10]
        assert grid_right[0] * grid_down[1] - grid_right[1] * grid_down[0] > 0
    assert min(sizes) > 2.0  # the origin dot's ellipse area against the median circle
    # image 2: the origin dot is cut by the left border, the order still comes from it
    d2 = t.detect(cv2.imread(str(RCT[2]), cv2.IMREAD_GRAYSCALE))
    assert 0 not in d2.ids and "cut by the image border" in d2.info["failed_circles"][0]
