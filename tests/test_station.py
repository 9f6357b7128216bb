"""One measuring station for every front end (:mod:`cutterpose.station`): the cell file, the
CLI's arguments and the Python API build the same station and measure the same way."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from cutterpose.budget import Tolerance
from cutterpose.cli import app
from cutterpose.errors import InputError
from cutterpose.geometry.camera_files import save_camera
from cutterpose.geometry.holder import default_holder
from cutterpose.geometry.pose import Pose
from cutterpose.pipeline import QualityLimits, measure, station_params
from cutterpose.render.analytic import render_holder
from cutterpose.station import build_station
from test_features import SCALE, small_camera

TRUE = Pose.from_euler(1, 2, -3, 4, -5, 605)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    d = tmp_path_factory.mktemp("station")
    cam = small_camera()
    save_camera(cam, d / "cam.json")
    img = render_holder(TRUE, cam, default_holder(), "easy", seed=2).image
    cv2.imwrite(str(d / "h.png"), img)
    return d, cam, img


def test_station_from_arguments_is_what_measure_was_given(scene):
    """The station's limits and parameters are those the front ends put together by hand
    before: the distance centres the working range, the options override the limits."""
    _, cam, _ = scene
    s = build_station(cam, None, "dm+", distance_mm=650.0, edge_break_mm=0.0,
                      tolerance=Tolerance(position_mm=2.0))
    assert s.limits == QualityLimits(range_center_dof=(0, 0, 0, 0, 0, 650.0), edge_break_mm=0.0,
                                     tolerance=Tolerance(position_mm=2.0))
    assert s.params == station_params(cam, "field", 650.0)
    given = QualityLimits(max_rms_px=2.0)
    assert build_station(cam, limits=given, edge_shape="round").limits == QualityLimits(
        max_rms_px=2.0, edge_shape="round")
    assert build_station(cam, limits={"max_rms_px": 2.0, "tolerance": {"angle_deg": 0.5}}
                         ).limits.tolerance == Tolerance(angle_deg=0.5)
    with pytest.raises(InputError):
        build_station(cam, method="nope")
    with pytest.raises(InputError):
        build_station(cam, chain="other")
    with pytest.raises(InputError):
        build_station(cam, limits={"max_rms": 1.0})


def test_cli_cell_and_api_measure_the_same(scene, tmp_path):
    """The CLI's ``measure``, a cell file's station and the Python API give the same pose and
    verdict for the same settings (fails if one of them assembles its own limits)."""
    from cutterpose.service.config import load_cell

    d, cam, img = scene
    tol = ["--budget-tol-mm", str(1.0 / SCALE), "--budget-tol-deg", str(0.3 / SCALE)]
    res = CliRunner().invoke(app, ["measure", str(d / "h.png"), "--camera", str(d / "cam.json"),
                                   "--method", "dm+", "--edge-break-mm", "0", "--json", *tol])
    assert res.exit_code == 0, res.output
    cli = json.loads(res.stdout)
    (tmp_path / "cell.toml").write_text(
        f'camera = "{d / "cam.json"}"\nmethod = "dm+"\n[tolerances]\nedge_break_mm = 0\n'
        f"[tolerances.tolerance]\nposition_mm = {1.0 / SCALE}\nangle_deg = {0.3 / SCALE}\n")
    cell = load_cell(tmp_path / "cell.toml", need_token=False)
    m_cell = cell.station.measure(img)
    api = measure(img, cam, None, "dm+", station_params(cam),
                  QualityLimits(edge_break_mm=0.0,
                                tolerance=Tolerance(1.0 / SCALE, 0.3 / SCALE)))
    assert cell.limits == cell.station.limits == QualityLimits(
        edge_break_mm=0.0, tolerance=Tolerance(1.0 / SCALE, 0.3 / SCALE))
    for m in (m_cell, api):
        assert m.ok == cli["quality"]["ok"] and m.quality.reason == cli["quality"]["reason"]
        assert np.allclose(m.pose.dof, [cli["pose"][k] for k in (
            "alpha_deg", "beta_deg", "gamma_deg", "X_mm", "Y_mm", "Z_mm")], rtol=0, atol=1e-9)


def test_station_robot_path_needs_the_handeye(scene):
    """The base frame at a station without a hand-eye calibration is a clear error."""
    _, cam, img = scene
    s = build_station(cam, method="dm+", edge_break_mm=0.0)
    with pytest.raises(InputError, match="hand-eye"):
        s.measure(img, T_base_flange=Pose.from_euler(0, 0, 0, 0, 0, 0))
