"""The field table counts what the verdict accepted and what it should not have."""

import csv

import numpy as np
import pytest
from typer.testing import CliRunner

from cutterpose.cli import app
from cutterpose.errors import InputError
from cutterpose.experiments.field import field_stats
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
