"""``dm+b``: the band across a broken pocket edge measured and fitted with the edge model, so
that the pose is the design edge's (issue 10, "measure the break itself")."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from cutterpose.geometry.camera import default_camera
from cutterpose.geometry.holder import default_holder
from cutterpose.geometry.pose import Pose
from cutterpose.image.edge_band import fit_band, sample_band
from cutterpose.methods import get_method
from cutterpose.pipeline import QualityLimits, measure
from cutterpose.render.analytic import preset, render_holder

CAM = default_camera("table1")
HOLDER = default_holder()
LIMITS = QualityLimits(edge_shape="unknown")


@pytest.fixture(scope="module")
def chamfered():
    """A new holder with 45 deg chamfers of 0.5-1.5 mm (the analytic ``new``, chamfered)."""
    pose = Pose.from_euler(3, -4, 2, 10, -8, 610)
    return pose, render_holder(pose, CAM, HOLDER, replace(preset("new"), edge_shape="chamfer"),
                               seed=3, noise_seed=4)


@pytest.fixture(scope="module")
def filleted():
    """A new holder with fillets of 0.5-1.5 mm (the analytic ``new``)."""
    pose = Pose.from_euler(-2, 3, -3, -12, 5, 614)
    return pose, render_holder(pose, CAM, HOLDER, preset("new"), seed=5, noise_seed=6)


@pytest.mark.parametrize("case", ["chamfered", "filleted"])
def test_dm_plus_b_measures_the_design_edge(case, request):
    """dm+ takes the innermost rise, the design polygon moved in depth by the break: its Z is
    off by a fraction of the break. dm+b fits the band and removes most of that bias (Table 1
    camera: 4 px per mm of break at 600 mm; a fillet's face junction is soft, so its radius
    and the design edge trade off more than a chamfer's)."""
    pose, r = request.getfixturevalue(case)
    plain = measure(r.image, CAM, HOLDER, method="dm+", limits=LIMITS)
    band = measure(r.image, CAM, HOLDER, method="dm+b", limits=LIMITS)
    assert plain.pose is not None and band.pose is not None
    z_plain = abs(plain.pose.dof[5] - pose.dof[5])
    z_band = abs(band.pose.dof[5] - pose.dof[5])
    assert z_plain > 0.15                        # the bias this test is about is there
    assert z_band < 0.6 * z_plain and z_band < 0.1
    err = band.pose.dof - pose.dof
    assert np.all(np.abs(err[:3]) < 0.1) and np.all(np.abs(err[3:5]) < 0.1)
    assert band.ok, band.quality.reason
    # the budget covers the actual error at the grasp point (3 sigma)
    assert np.linalg.norm(band.pose.t_mm - pose.t_mm) < band.quality.budget.position_3sigma_mm


@pytest.mark.parametrize("case,shape", [("chamfered", "chamfer"), ("filleted", "round")])
def test_band_fit_finds_the_shape_and_radius(case, shape, request):
    """At the true pose the profile fit picks the break's shape and each edge's radius."""
    pose, r = request.getfixturevalue(case)
    bp = sample_band(r.image, CAM, HOLDER, pose.R, pose.t_mm)
    assert bp.valid.all()
    fit = fit_band(bp, CAM, HOLDER, pose.R, pose.t_mm)
    assert fit.best.look.shape == shape
    true_r = np.asarray(r.edge_radius_mm)[bp.edge]
    assert np.median(np.abs(fit.best.radius_mm - true_r)) < 0.15
    # the design edge is where the model puts it: shifts of a few tenths of a px at most
    assert np.median(np.abs(fit.best.shift_px)) < 0.15


def test_band_reported_in_json(chamfered):
    _, r = chamfered
    m = measure(r.image, CAM, HOLDER, method="dm+b", limits=LIMITS)
    d = json.loads(json.dumps(m.to_dict()))
    assert d["edge_band"]["shape"] == "chamfer"
    assert 0.5 <= d["edge_band"]["radius_median_mm"] <= 1.6
    parts = d["quality"]["budget"]["parts"]
    assert set(parts) == {"noise", "edge model", "model floor"}
    assert all(p["position_3sigma_mm"] >= 0 for p in parts.values())
    # the residuals' split (a clean analytic render: a few tenths of a px at most)
    eb = d["edge_band"]
    assert 0 < eb["residual_within_edge_px"] < 0.5
    assert 0 <= eb["residual_shared_per_edge_px"] < 0.5


def test_dm_plus_b_without_an_image_says_so():
    est = get_method("dm+b").solve(np.zeros((20, 2)), CAM, HOLDER)
    assert not est and "needs the image" in est.reason


def test_dm_plus_b_refuses_when_the_edges_are_hidden(chamfered):
    """Most of the image blanked out after the features were found: too few segments have a
    band, so no pose (a falsy estimate with the reason), never a confident one."""
    from cutterpose.image import FeatureParams, detect_features
    from cutterpose.pipeline import measure_features

    _, r = chamfered
    feats = detect_features(r.image, CAM, HOLDER, FeatureParams.for_camera(CAM))
    img = feats.image.copy()
    img[:, : int(0.75 * img.shape[1])] = 0
    feats.image = img
    m = measure_features(feats, CAM, HOLDER, method="dm+b", limits=LIMITS)
    assert not m.ok
    assert m.pose is None or "band" in m.quality.reason or "budget" in m.quality.reason


def test_dm_plus_b_on_the_papers_chain(chamfered):
    """The band needs only the image and a start: it works behind section 2.1's chain too."""
    from cutterpose.image import FeatureParams

    pose, r = chamfered
    m = measure(r.image, CAM, HOLDER, method="dm+b", params=FeatureParams.paper(),
                limits=LIMITS)
    assert m.pose is not None, m.quality.reason
    assert abs(m.pose.dof[5] - pose.dof[5]) < 0.15
    assert m.to_dict()["features"]["order"] == "contour"


def test_dm_plus_b_starts_from_the_outline_and_needs_no_corners(chamfered):
    """On the field chain ``dm+b`` starts from the pocket outline's pose: ``measure`` skips the
    line fits (no corners, no 'lines' stage), and the pose is the same, to the last digit,
    when the corners are detected anyway (so ``experiment images``, which detects them once
    for every method, measures what ``measure`` gives). Fails if the start or the sampled
    edges came from the corners again."""
    pose, r = chamfered
    fast = measure(r.image, CAM, HOLDER, method="dm+b", limits=LIMITS)
    full = measure(r.image, CAM, HOLDER, method="dm+b", limits=LIMITS, corners=True)
    assert fast.ok and full.ok, (fast.quality.reason, full.quality.reason)
    assert fast.features.segmentation == "outline" and full.features.segmentation == "field"
    assert "lines" not in fast.timings_ms and "lines" in full.timings_ms
    assert len(fast.corners_px) == 0 and len(full.corners_px) == 20
    assert np.array_equal(fast.pose.dof, full.pose.dof)
    assert fast.estimate.start.method == "outline"
    d = json.loads(json.dumps(fast.to_dict()))
    assert d["corners_px"] == [] and d["features"]["segmentation"] == "outline"
    # dm+ still detects its corners
    plain = measure(r.image, CAM, HOLDER, method="dm+", limits=LIMITS)
    assert plain.features.segmentation == "field" and len(plain.corners_px) == 20


def test_outline_start_refuses_a_degenerate_homography():
    from cutterpose.pipeline import outline_start

    assert outline_start(np.zeros((3, 3)), CAM) is None
    assert outline_start(np.full((3, 3), np.nan), CAM) is None
    H = CAM.K @ np.column_stack([np.eye(3)[:, :2], [0, 0, 600.0]])
    est = outline_start(H, CAM)
    assert est and np.allclose(est.t_cam_holder_mm, [0, 0, 600]) and np.allclose(
        est.R_cam_holder, np.eye(3))


def test_dm_plus_b_falls_back_to_the_corners_when_the_outline_start_fails(chamfered,
                                                                          monkeypatch):
    """An outline homography bent by what lies on a worn edge gives a start the band cannot
    follow (a held-back worn image: corners 21 px off, the band on 9 of 40 segments): then
    ``measure`` detects the corners and starts from their pose, says so, and measures the
    pose (fails without the fall-back: no pose)."""
    import cutterpose.solvers.edge_band as eb

    pose, r = chamfered
    bad = pose.dof + np.array([4.3, -2.6, -1.2, 2.5, 0.0, -8.4])
    far = Pose.from_euler(*bad)

    def bent(H, camera, method="outline"):
        return eb.PoseEstimate(method, far.R, far.t_mm)

    monkeypatch.setattr(eb, "outline_start", bent)
    m = measure(r.image, CAM, HOLDER, method="dm+b", limits=LIMITS)
    assert m.pose is not None, m.quality.reason
    assert "edge segments" in m.estimate.start_failed
    assert m.features.segmentation == "field"
    err = m.pose.dof - pose.dof
    assert np.all(np.abs(err[:3]) < 0.1) and abs(err[5]) < 0.3


def test_overlay_text_wraps_the_band_summary(chamfered):
    """The overlay's text box holds the band's long summary line whole (wrapped to its width,
    not cut at the image's edge)."""
    from cutterpose.overlay import _lines

    _, r = chamfered
    m = measure(r.image, CAM, HOLDER, method="dm+b", limits=LIMITS)
    lines = _lines(m)
    assert max(len(t) for t in lines) <= 92
    assert "shared per edge" in " ".join(lines)
