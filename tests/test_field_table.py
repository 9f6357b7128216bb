"""The field table counts what the verdict accepted and what it should not have."""

import csv

import numpy as np
import pytest
from typer.testing import CliRunner

from cutterpose.cli import app
from cutterpose.errors import InputError
from cutterpose.experiments.field import field_markdown, field_stats
from cutterpose.experiments.report import trial_rows, write_trials_csv
from cutterpose.geometry.pose import Pose


def _set(folder, errors_mm, accepted):
    """A result folder with one method: image k has a Z error errors_mm[k] and a verdict."""
    rows, truth = [], Pose.from_euler(1, 2, 3, 4, 5, 600)
    for k, dz in enumerate(errors_mm):
        est = Pose.from_euler(1, 2, 3, 4, 5, 600 + dz) if np.isfinite(dz) else None
        rows += trial_rows(k, np.nan, "dm+", truth.R, truth.t_mm,
                           est.R if est else np.full((3, 3), np.nan),
                           est.t_mm if est else np.full(3, np.nan), 1.0)
    folder.mkdir()
    write_trials_csv(rows, folder / "trials.csv")
    with open(folder / "verdicts.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["trial", "method", "accepted", "reason"])
        for k, ok in enumerate(accepted):
            w.writerow([k, "dm+", int(ok), "" if ok else f"budget {k}.5 mm > 1 mm"])


def test_counts_accepted_refused_and_wrong_accepted(tmp_path):
    _set(tmp_path / "worn", [0.1, -0.2, 1.5, 3.0, np.nan], [1, 1, 1, 0, 0])
    (s,) = field_stats(tmp_path / "worn")
    assert (s["n"], s["accepted"], s["refused"], s["no_pose"]) == (5, 3, 2, 1)
    assert s["accepted_bad"] == 1                      # the accepted 1.5 mm
    assert s["trans_max_mm"] == pytest.approx(1.5)
    assert s["bias"][5] == pytest.approx((0.1 - 0.2 + 1.5) / 3)
    assert s["refused_trans_median_mm"] == pytest.approx(3.0)
    assert s["refusals"] == {"budget # mm > # mm": 2}


def test_cli_writes_the_table_and_rejects_bad_pairs(tmp_path):
    _set(tmp_path / "a", [0.05, 0.02, -0.01], [1, 1, 1])
    res = CliRunner().invoke(app, ["experiment", "field-table", f"new={tmp_path / 'a'}",
                                   "--out", str(tmp_path / "out")])
    assert res.exit_code == 0, res.output
    assert "| new | dm+ | 3 | 3 | 0 |" in (tmp_path / "out" / "field.md").read_text()
    res = CliRunner().invoke(app, ["experiment", "field-table", str(tmp_path / "a")])
    assert res.exit_code != 0 and "NAME=RESULTS_DIR" in res.output
    with pytest.raises(InputError, match="verdicts.csv"):
        field_stats(tmp_path)


def test_budget_honesty_from_budgets_csv(tmp_path):
    """z = |e| / std per DOF, coverage by the 3-sigma figures, Mahalanobis^2 read back."""
    _set(tmp_path / "s", [0.1, -0.4, 2.0], [1, 1, 0])
    with open(tmp_path / "s" / "budgets.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["trial", "method", "position_3sigma_mm", "angle_3sigma_deg",
                    "std_alpha_deg", "std_beta_deg", "std_gamma_deg", "std_X_mm", "std_Y_mm",
                    "std_Z_mm", "mahalanobis2"])
        # std Z 0.2 mm: the errors are 0.5, 2 and 10 std
        for k, d2 in enumerate([0.25, 4.0, 100.0]):
            w.writerow([k, "dm+", 0.6, 0.1, 0.01, 0.01, 0.01, 0.1, 0.1, 0.2, d2])
    (s,) = field_stats(tmp_path / "s")
    assert (s["budget_n"], s["budget_covered"], s["budget_covered_accepted"],
            s["budget_accepted"]) == (3, 2, 2, 2)      # 2 mm > 0.6 mm: not covered
    assert s["z_median"][5] == pytest.approx(2.0)
    assert s["z_max"][5] == pytest.approx(10.0)
    assert s["z_median"][0] == pytest.approx(0.0, abs=1e-9)
    assert s["mahalanobis2_median"] == pytest.approx(4.0)
    assert "| s | dm+ | 3 | 2/3; 2/2 |" in field_markdown([s])


def test_budget_cells_carry_std_and_mahalanobis():
    from cutterpose.budget import budget_from_dof_cov
    from cutterpose.experiments.images import _budget_cells
    from cutterpose.experiments.report import BUDGET_STD_COLUMNS, ERR_COLUMNS

    C = np.diag([0.01, 0.04, 0.0001, 0.01, 0.01, 0.25])
    C[0, 5] = C[5, 0] = 0.03
    b = budget_from_dof_cov({"noise": C}, [1, 2, 3, 4, 5, 600])
    e = np.array([0.1, -0.2, 0.01, 0.05, 0.0, 0.4])
    row = dict(zip(ERR_COLUMNS, e))
    cells = _budget_cells(b, row)
    assert len(cells) == 3 + len(BUDGET_STD_COLUMNS)
    assert [float(c) for c in cells[2:8]] == pytest.approx(np.sqrt(np.diag(C)), rel=1e-4)
    assert float(cells[8]) == pytest.approx(e @ np.linalg.solve(C, e), rel=1e-4)
    assert _budget_cells(None, row) == [""] * 9
    row["Z_err_mm"] = np.nan                              # no pose: no distance
    assert _budget_cells(b, row)[8] == ""


def test_retakes_count_holders_by_their_first_accepted_view(tmp_path):
    """Three holders x 2 views: holder 0 accepted at once, holder 1 on the retake (1.5 mm off:
    counted as a bad used view), holder 2 never."""
    _set(tmp_path / "r", [0.1, 0.2, 3.0, 1.5, 2.0, 2.5], [1, 1, 0, 1, 0, 0])
    with open(tmp_path / "r" / "corners.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["trial", "file", "holder_index", "view"])
        for k in range(6):
            w.writerow([k, f"img_{k:04d}.png", k // 2, k % 2])
    (s,) = field_stats(tmp_path / "r")
    assert s["holders"] == 3
    assert s["accepted_within_views"] == [1, 2]
    assert s["retake_trans_max_mm"] == pytest.approx(1.5)     # holder 0 view 0, holder 1 view 1
    assert s["retake_bad"] == 1
    assert "| r | dm+ | 3 | 1 / 2 |" in field_markdown([s])
    _set(tmp_path / "p", [0.1], [1])
    assert "holders" not in field_stats(tmp_path / "p")[0]
