"""The cell file of `cutterpose serve`: validated once at start, a bad field named (issue 12)."""

import dataclasses
import json

import numpy as np
import pytest

from cutterpose.errors import CellFileError
from cutterpose.pipeline import QualityLimits
from cutterpose.service.config import _Tolerances, bundled_cell_path, load_cell
from cutterpose.service.loadtest import write_cell

ENV = {"CUTTERPOSE_TOKEN": "s3cret-token"}


def test_bundled_cell_is_the_table1_camera():
    cell = load_cell(None, env=ENV)
    assert bundled_cell_path().is_file()
    assert tuple(cell.camera.image_size_px) == (4112, 3008)
    assert cell.camera.model == "division"
    assert cell.holder(None).n_corners == 20
    assert cell.limits == QualityLimits()
    assert cell.token == "s3cret-token" and cell.for_worker().token == ""
    assert "s3cret" not in repr(cell) and "s3cret" not in str(cell.describe())


def test_tolerance_keys_are_quality_limit_fields():
    names = {f.name for f in dataclasses.fields(QualityLimits)}
    assert set(_Tolerances.model_fields) == names


@pytest.mark.parametrize("body, field", [
    ("[service]\nworkers = -1\n", "service.workers"),
    ("[service]\nmax_body_mb = 0\n", "service.max_body_mb"),
    ("[service]\nworker = 2\n", "service.worker"),            # unknown key (typo)
    ("[tolerances]\nmax_std_dof = [1, 2, 3]\n", "tolerances.max_std_dof"),
    ("[tolerances]\nmax_std_dof = [1, 2, 3, 4, 5, -6]\n", "tolerances.max_std_dof"),
    ("[tolerances]\nedge_break_mm = -0.5\n", "tolerances.edge_break_mm"),
    ("method = \"nope\"\n", "method"),
    ("camera = \"missing.json\"\n", "camera"),
    ("handeye = \"missing.json\"\n", "handeye"),
    ("default_holder = \"other\"\n", "default_holder"),
    ("[holders]\ndefault = \"missing.json\"\n", "holders.default"),
    ("name = 3\n", "name"),
    ("distance_mm = -600\n", "distance_mm"),
    ("camera = [\n", "not valid TOML"),
])
def test_a_bad_field_is_named(tmp_path, body, field):
    p = tmp_path / "cell.toml"
    p.write_text(body)
    with pytest.raises(CellFileError) as e:
        load_cell(p, env=ENV)
    msg = str(e.value)
    assert field in msg and str(p) in msg and "\n" not in msg


def test_tolerances_reach_the_limits(tmp_path):
    p = tmp_path / "cell.toml"
    p.write_text("[tolerances]\nmax_rms_px = 0.7\nmax_std_dof = [1, 1, 1, 3, 3, 3]\n"
                 "edge_break_mm = 0\n")
    lim = load_cell(p, env=ENV).limits
    assert lim.max_rms_px == 0.7 and lim.max_std_dof == (1, 1, 1, 3, 3, 3)
    assert lim.edge_break_mm == 0 and QualityLimits().edge_break_mm is None
    assert lim.max_corner_residual_px == QualityLimits().max_corner_residual_px


def test_token_from_env_or_file_never_missing(tmp_path):
    with pytest.raises(CellFileError, match="CUTTERPOSE_TOKEN"):
        load_cell(None, env={})
    cell = write_cell(tmp_path, factor=4, token="from-file")
    assert load_cell(cell, env={}).token == "from-file"
    assert load_cell(cell, env={"CUTTERPOSE_TOKEN": "env-wins"}).token == "env-wins"
    (tmp_path / "token.txt").write_text("two words\n")
    with pytest.raises(CellFileError, match="token"):
        load_cell(cell, env={})


def test_data_dir_env_wins_and_reduced_camera(tmp_path):
    cell = write_cell(tmp_path / "c", factor=4)
    c = load_cell(cell, env=ENV | {"CUTTERPOSE_DATA_DIR": str(tmp_path / "elsewhere")})
    assert c.service.data_dir == (tmp_path / "elsewhere").resolve()
    assert tuple(c.camera.image_size_px) == (1028, 752)
    assert load_cell(cell, env=ENV).service.data_dir == (tmp_path / "c" / "data").resolve()


def test_handeye_file_is_checked(tmp_path):
    (tmp_path / "he.json").write_text('{"T_flange_cam": [[1, 0, 0], [0, 1, 0]]}')
    (tmp_path / "cell.toml").write_text('handeye = "he.json"\n')
    with pytest.raises(CellFileError, match="handeye.*T_base_plate|handeye.*T_flange_cam"):
        load_cell(tmp_path / "cell.toml", env=ENV)
    eye = np.eye(4).tolist()
    (tmp_path / "he.json").write_text(json.dumps(
        {"T_flange_cam": eye, "T_base_plate": eye, "covariance": np.eye(6).tolist()}))
    he = load_cell(tmp_path / "cell.toml", env=ENV).handeye
    assert np.allclose(he.T_flange_cam.matrix, np.eye(4))


def test_robot_section(tmp_path):
    (tmp_path / "cell.toml").write_text("[robot]\naccuracy_mm = 0.1\ngrasp_tolerance_mm = 2\n")
    c = load_cell(tmp_path / "cell.toml", env=ENV)
    assert c.robot_accuracy.position_mm == 0.1 and c.grasp_tolerance.position_mm == 2.0
    (tmp_path / "cell.toml").write_text("[robot]\ngrasp_tolerance_mm = -1\n")
    with pytest.raises(CellFileError, match="robot.grasp_tolerance_mm"):
        load_cell(tmp_path / "cell.toml", env=ENV)
    (tmp_path / "cell.toml").write_text('chain = "magic"\n')
    with pytest.raises(CellFileError, match="chain"):
        load_cell(tmp_path / "cell.toml", env=ENV)


def test_station_distance_sets_the_search_and_the_range(tmp_path):
    """``distance_mm``: the region search's outline at that depth and the working range
    centred there; an explicit ``range_center_dof`` wins; without it the paper's 600 mm."""
    p = tmp_path / "cell.toml"
    p.write_text("distance_mm = 720\n")
    cell = load_cell(p, env=ENV)
    assert cell.feature_params().roi_depths_mm == (720.0,)
    assert cell.limits.range_center_dof == (0.0, 0.0, 0.0, 0.0, 0.0, 720.0)
    p.write_text("distance_mm = 720\n[tolerances]\nrange_center_dof = [0, 0, 0, 5, 0, 700]\n")
    assert load_cell(p, env=ENV).limits.range_center_dof == (0, 0, 0, 5, 0, 700)
    plain = load_cell(None, env=ENV)
    assert plain.feature_params().roi_depths_mm == (600.0,)
    assert plain.limits.range_center_dof[5] == 600.0
