"""The verdict re-applied at other angle tolerances, from an `experiment images` folder."""

import csv
import json

import numpy as np
import pytest
from typer.testing import CliRunner

from cutterpose.cli import app
from cutterpose.errors import InputError
from cutterpose.experiments.acceptance import acceptance_curve, acceptance_markdown
from cutterpose.experiments.report import trial_rows, write_trials_csv
from cutterpose.geometry.pose import Pose

# per image: rotation error about alpha (deg), Z error (mm), 3-sigma position (mm) and angle
# (deg) of the budget, and the run's verdict reason ("" accepted at 1 mm / 0.3 deg)
IMAGES = [
    (0.05, 0.1, 0.5, 0.20, ""),
    (0.08, -0.2, 0.6, 0.28, ""),
    (0.20, 0.3, 0.7, 0.35, "error budget: rotation uncertain by 0.350 deg (3 sigma) > 0.3 deg"),
    (0.60, 0.2, 0.8, 0.42, "error budget: rotation uncertain by 0.420 deg (3 sigma) > 0.3 deg"),
    (0.10, 0.4, 1.4, 0.25, "error budget: position at the grasp point uncertain by 1.40 mm"),
    (0.04, 0.1, 0.5, 0.22, "pose too uncertain: std [...]"),
    (np.nan, np.nan, np.nan, np.nan, "FeatureError: no holder"),
]


def _run(folder):
    truth = Pose.from_euler(1, 2, 3, 4, 5, 600)
    rows = []
    for k, (da, dz, *_) in enumerate(IMAGES):
        if np.isfinite(da):
            est = Pose.from_euler(1 + da, 2, 3, 4, 5, 600 + dz)
            R, t = est.R, est.t_mm
        else:
            R, t = np.full((3, 3), np.nan), np.full(3, np.nan)
        rows += trial_rows(k, np.nan, "dm+b", truth.R, truth.t_mm, R, t, 1.0)
    folder.mkdir()
    write_trials_csv(rows, folder / "trials.csv")
    with open(folder / "verdicts.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["trial", "method", "accepted", "reason"])
        for k, im in enumerate(IMAGES):
            w.writerow([k, "dm+b", int(im[4] == ""), im[4]])
    with open(folder / "budgets.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["trial", "method", "position_3sigma_mm", "angle_3sigma_deg"])
        for k, im in enumerate(IMAGES):
            if np.isfinite(im[2]):
                w.writerow([k, "dm+b", im[2], im[3]])


def test_tolerances_reapply_the_budget_and_keep_other_refusals(tmp_path):
    _run(tmp_path / "worn")
    c = acceptance_curve(tmp_path / "worn", tolerances_deg=(0.3, 0.4, 0.5))
    assert c["n"] == 7 and c["accepted_by_verdict"] == 2
    acc = {r["angle_tol_deg"]: r for r in c["rows"]}
    # at the run's own tolerance the verdicts come back
    assert acc[0.3]["accepted"] == 2 and acc[0.3]["accepted_bad"] == 0
    # 0.4 deg takes image 2; 0.5 deg image 3 too, 0.6 deg off: a wrong pose counted
    assert acc[0.4]["accepted"] == 3
    assert acc[0.5]["accepted"] == 4 and acc[0.5]["accepted_bad"] == 1
    assert acc[0.5]["rot_max_deg"] == pytest.approx(0.60, abs=1e-6)
    # the position budget (image 4), "pose too uncertain" (5) and no pose (6) stay refused
    assert all(r["accepted"] <= 4 for r in c["rows"])
    # ceilings: within 1 mm and 0.5 deg are images 0, 1, 2, 4, 5; within 0.1 deg 0, 1, 4, 5
    assert c["ceiling_good"] == 5
    assert c["ceiling_p95_0p1"] == 4
    md = acceptance_markdown([c])
    assert "| worn | dm+b | 7 | 0.50 deg | 4 (57 %) |" in md


def test_cli_writes_table_json_and_plot_and_rejects_bad_input(tmp_path):
    _run(tmp_path / "a")
    out = tmp_path / "out"
    res = CliRunner().invoke(app, ["experiment", "acceptance", f"worn={tmp_path / 'a'}",
                                   "--tolerances", "0.3,0.45", "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert "| worn | dm+b | 7 | 0.45 deg | 4 (57 %) |" in res.output
    assert json.loads((out / "acceptance.json").read_text())[0]["rows"][1]["accepted"] == 4
    assert (out / "acceptance.png").stat().st_size > 1000
    for bad in (["--tolerances", "0.3,x"], ["--tolerances", "-1"]):
        res = CliRunner().invoke(app, ["experiment", "acceptance", f"worn={tmp_path / 'a'}",
                                       *bad, "--out", str(out)])
        assert res.exit_code != 0 and "--tolerances" in res.output
    res = CliRunner().invoke(app, ["experiment", "acceptance", str(tmp_path / "a")])
    assert res.exit_code != 0 and "NAME=RESULTS_DIR" in res.output
    with pytest.raises(InputError, match="no trials of method"):
        acceptance_curve(tmp_path / "a", method="dm+")


def test_reapplied_tolerance_equals_a_run_with_it(tmp_path):
    """`experiment acceptance` at a tolerance gives the count that `experiment images
    --budget-tol-deg` at that tolerance gives (the budgets are the same; only the line moves)."""
    from cutterpose.geometry.camera_files import save_camera
    from test_features import small_camera

    cam_file = tmp_path / "small.json"
    save_camera(small_camera(0.5), cam_file)
    runner = CliRunner()
    r = runner.invoke(app, ["render-set", "--out", str(tmp_path / "set"), "--count", "4",
                            "--seed", "3", "--camera", str(cam_file), "--preset", "easy"])
    assert r.exit_code == 0, r.output
    counts = {}
    for tol in ("0.3", "0.05"):
        r = runner.invoke(app, ["experiment", "images", str(tmp_path / "set"), "--methods",
                                "dm+", "--edge-break-mm", "0", "--budget-tol-deg", tol,
                                "--out", str(tmp_path / f"run_{tol}")])
        assert r.exit_code == 0, r.output
        c = acceptance_curve(tmp_path / f"run_{tol}", method="dm+", tolerances_deg=(0.3, 0.05))
        counts[tol] = (c["accepted_by_verdict"], [row["accepted"] for row in c["rows"]])
    assert counts["0.3"][0] > counts["0.05"][0], counts    # the tighter run refuses more
    assert counts["0.3"][1][1] == counts["0.05"][0]           # ... as the re-applied line says
    assert counts["0.3"][1][0] == counts["0.3"][0]
    bad = runner.invoke(app, ["experiment", "images", str(tmp_path / "set"), "--methods", "dm+",
                              "--budget-tol-deg", "nan", "--out", str(tmp_path / "x")])
    assert bad.exit_code != 0 and "--budget-tol-deg" in bad.output
