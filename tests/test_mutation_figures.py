"""The protocol's error figures (PROTOCOL.md, "Error figures") on hand-computed cases
(issue 33): rotations of known angle about known axes, the gross-failure thresholds at their
edge, the wrap at +-180 deg, and the summary statistics of a handful of rows worked out here."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cutterpose.experiments.report import summarize, trial_rows
from cutterpose.geometry.pose import (
    FAIL_ROT_DEG,
    FAIL_TRANS_MM,
    geodesic_deg,
    pose_errors,
    rotation_from_euler_deg,
    wrap_deg,
)


def _turn(axis, deg):
    a = np.asarray(axis, float)
    return Rotation.from_rotvec(np.radians(deg) * a / np.linalg.norm(a)).as_matrix()


@pytest.mark.parametrize("deg", [1e-7, 0.01, 1.0, 45.0, 179.0])
def test_geodesic_is_the_turn_angle(deg):
    R0 = rotation_from_euler_deg(20, -30, 40)
    for axis in ([1, 0, 0], [0, 1, 0], [0, 0, 1], [1, -2, 0.5]):
        assert geodesic_deg(R0, R0 @ _turn(axis, deg)) == pytest.approx(deg, rel=1e-9)
        assert geodesic_deg(R0 @ _turn(axis, deg), R0) == pytest.approx(deg, rel=1e-9)


def test_wrap_edges():
    np.testing.assert_array_equal(wrap_deg([-180.0, 180.0, 540.0, -540.0, 0.0, 359.0, -181.0]),
                                  [180.0, 180.0, 180.0, 180.0, 0.0, -1.0, 179.0])


def test_pose_errors_hand_computed_and_thresholds():
    """Per-DOF differences (angles wrapped), the geodesic angle and the translation norm; a
    trial fails above 2 deg or 10 mm (at them it does not) and when it has no pose."""
    R_true = rotation_from_euler_deg(170.0, 10.0, -5.0)
    t_true = np.array([1.0, 2.0, 600.0])
    rows_R, rows_t = [], []
    for dg, dt in ((0.5, [3.0, 4.0, 0.0]),                    # 0.5 deg about z, 5 mm
                   (FAIL_ROT_DEG, [0.0, 0.0, FAIL_TRANS_MM]),   # at both thresholds
                   (FAIL_ROT_DEG * 1.0001, [0, 0, 0]),
                   (0.0, [0.0, 0.0, FAIL_TRANS_MM * 1.0001])):
        rows_R.append(R_true @ _turn([0, 0, 1], dg))
        rows_t.append(t_true + dt)
    rows_R.append(np.full((3, 3), np.nan))
    rows_t.append(np.full(3, np.nan))
    e = pose_errors(np.repeat(R_true[None], 5, 0), np.repeat(t_true[None], 5, 0),
                    np.array(rows_R), np.array(rows_t))
    np.testing.assert_allclose(e.rot_deg[:4], [0.5, FAIL_ROT_DEG, FAIL_ROT_DEG * 1.0001, 0.0],
                               atol=1e-9)
    np.testing.assert_allclose(e.trans_mm[:4], [5.0, FAIL_TRANS_MM, 0.0,
                                                FAIL_TRANS_MM * 1.0001], atol=1e-12)
    np.testing.assert_array_equal(e.failed, [False, False, True, True, True])
    np.testing.assert_allclose(e.dof[0, 3:], [3.0, 4.0, 0.0])
    assert np.all(np.isnan(e.dof[4])) and np.isnan(e.rot_deg[4])
    # a turn about the holder's own z at alpha = 170 deg: gamma-ish change, wrapped (no 360)
    assert np.all(np.abs(e.dof[:4, :3]) < 5.0)
    # across the +-180 wrap of alpha: 179.5 vs -179.5 is 1 deg, not 359
    e = pose_errors(rotation_from_euler_deg(179.5, 0, 0), [0, 0, 600],
                    rotation_from_euler_deg(-179.5, 0, 0), [0, 0, 600])
    np.testing.assert_allclose(e.dof[0, :3], [1.0, 0.0, 0.0], atol=1e-9)
    assert e.rot_deg[0] == pytest.approx(1.0, rel=1e-9) and not e.failed[0]


def _rows():
    """Three trials of method A at sigma 1 (one failed), one of A at sigma 0.5, two of B at
    sigma 1 (one without a pose): errors as (rotation about z in deg, shift along x in mm)."""
    R = np.eye(3)
    t = np.array([0.0, 0.0, 600.0])
    rows = []
    for k, (m, s, deg, dx, ms) in enumerate((("A", 1.0, 0.2, 1.0, 10.0),
                                             ("A", 1.0, 0.4, 3.0, 30.0),
                                             ("A", 1.0, 3.0, 2.0, 20.0),     # > 2 deg: failed
                                             ("B", 1.0, 0.1, -1.0, 5.0),
                                             ("A", 0.5, 0.1, 0.5, 7.0))):
        rows += trial_rows(k, s, m, R, t, _turn([0, 0, 1], deg), t + [dx, 0, 0], ms)
    rows += trial_rows(9, 1.0, "B", R, t, np.full((3, 3), np.nan), np.full(3, np.nan), 8.0)
    # a method seen only at sigma 0.5, and images (sigma unknown: NaN, summarised last)
    rows += trial_rows(10, 0.5, "C", R, t, _turn([0, 0, 1], 0.3), t, 9.0)
    rows += trial_rows(11, np.nan, "A", R, t, _turn([0, 0, 1], 0.2), t, 4.0)
    return rows


def test_trial_rows_columns():
    rows = _rows()
    r = rows[1]
    assert (r["trial"], r["sigma_px"], r["method"], r["failed"], r["time_ms"]) == \
        (1, 1.0, "A", 0, 30.0)
    assert r["gamma_err_deg"] == pytest.approx(0.4) and r["rot_err_deg"] == pytest.approx(0.4)
    assert r["X_err_mm"] == 3.0 and r["trans_err_mm"] == 3.0 and r["Y_err_mm"] == 0.0
    assert rows[2]["failed"] == 1 and rows[2]["rot_err_deg"] == pytest.approx(3.0)
    last = rows[5]
    assert last["failed"] == 1 and math.isnan(last["rot_err_deg"]) and \
        math.isnan(last["X_err_mm"]) and math.isnan(last["trans_err_mm"])


def test_summary_hand_computed():
    """std over the non-failed trials (n - 1), std_all over all with a pose, bias, median and
    95th percentile (linear interpolation) of the errors, median time; ascending sigma, methods
    in first-seen order."""
    stats = summarize(_rows())
    assert [(s["sigma_px"], s["method"]) for s in stats[:4]] == [(0.5, "A"), (0.5, "C"),
                                                                  (1.0, "A"), (1.0, "B")]
    assert math.isnan(stats[4]["sigma_px"]) and stats[4]["method"] == "A" and len(stats) == 5
    assert stats[1]["rot_median"] == pytest.approx(0.3)
    stats = [stats[0], stats[2], stats[3]]
    a = stats[1]
    assert (a["n"], a["failed"], a["no_pose"]) == (3, 1, 0)
    assert a["std"][5] == 0.0 and a["std"][3] == pytest.approx(math.sqrt(2.0))  # 1, 3
    assert a["std"][2] == pytest.approx(math.sqrt(0.02))                       # 0.2, 0.4
    assert a["std_all"][3] == pytest.approx(1.0)                               # 1, 3, 2
    assert a["bias"][3] == pytest.approx(2.0) and a["bias"][2] == pytest.approx(0.3)
    assert a["rot_median"] == pytest.approx(0.4) and a["trans_median"] == pytest.approx(2.0)
    # 95th percentile of (0.2, 0.4, 3.0): 0.4 + 0.9 * 2.6; of (1, 2, 3): 2.9
    assert a["rot_p95"] == pytest.approx(0.4 + 0.9 * 2.6)
    assert a["trans_p95"] == pytest.approx(2.9)
    assert a["time_median_ms"] == 20.0
    b = stats[2]
    assert (b["n"], b["failed"], b["no_pose"]) == (2, 1, 1)
    assert len(b["std"]) == 6 and all(math.isnan(v) for v in b["std"])   # one good trial
    assert b["bias"][3] == -1.0 and b["rot_median"] == pytest.approx(0.1)
    assert b["time_median_ms"] == 6.5
    lone = stats[0]
    assert lone["n"] == 1 and lone["bias"][3] == 0.5 and lone["rot_p95"] == pytest.approx(0.1)
    # no rows of a (sigma, method): no entry; no good trial at all: NaN bias
    only_fail = [r for r in _rows() if r["method"] == "B" and r["failed"]]
    (s,) = summarize(only_fail)
    assert len(s["bias"]) == 6 and all(math.isnan(v) for v in s["bias"])
    assert len(s["std_all"]) == 6 and math.isnan(s["rot_median"])
