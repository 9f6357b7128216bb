"""The edge look calibrated in the cell (``cutterpose calibrate-edge-look``, ``--edge-look``):
the band model's photometry fitted on a reference holder at known poses so that ``dm+b`` puts
the design edge where the known pose does."""

from __future__ import annotations

import json
from dataclasses import replace

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from cutterpose.calibration.edge_look import (
    EdgeLookCalibration,
    ReferenceImage,
    calibrate_edge_look,
    calibrate_offsets,
    load_edge_look,
    save_edge_look,
    shift_at_truth,
)
from cutterpose.calibration.edge_look import edge_look_from_dict as load_edge_look_dict
from cutterpose.cli import app
from cutterpose.errors import EdgeLookFileError
from cutterpose.geometry.camera import default_camera
from cutterpose.geometry.holder import default_holder
from cutterpose.geometry.pose import Pose
from cutterpose.image import edge_model as em
from cutterpose.image.edge_band import (
    STEP_PX,
    BandLooks,
    DesignEdgeOffsets,
    model_grid_px,
    sample_band,
    view_lean,
)
from cutterpose.pipeline import QualityLimits, measure
from cutterpose.render.analytic import preset, render_holder

CAM = default_camera("table1")
HOLDER = default_holder()
#: a look unlike the nominal one (a broader, stronger lobe, darker walls)
TRUE_LOOK = em.EdgeLook(specular=0.7, shininess=12.0, wall_albedo=0.15, pocket_level=0.08)
runner = CliRunner()


def model_reference(pose: Pose, look: em.EdgeLook, seed: int, blur_px: float = 0.9,
                    shift_mm: float = 0.0, n_seg: int = 2,
                    depth_mm: float = 0.0) -> ReferenceImage:
    """A reference image whose band profiles are the edge model's own for ``look`` at the true
    pose (its design edge ``shift_mm`` outwards, and as if ``depth_mm`` below the face: plus
    ``depth_mm`` times the segment's view lean), one radius per edge (0.5-1.6 mm), a grey
    offset and gain per segment and 1 grey level of noise: the sampling geometry of
    ``sample_band``, the values of the model."""
    rng = np.random.default_rng(seed)
    blank = np.zeros(CAM.image_size_px[::-1], np.uint8)
    bp = sample_band(blank, CAM, HOLDER, pose.R, pose.t_mm, n_seg=n_seg, positions=12)
    n = len(HOLDER.corners_mm)
    r_edge = rng.uniform(0.5, 1.6, n)
    per_end = np.stack([np.roll(r_edge, 1), r_edge], axis=1)[..., None]     # (N, 2, 1)
    view = em.edge_views(pose.R, pose.t_mm, CAM.K, HOLDER, look)
    grid = model_grid_px(bp)
    w0, (bl,) = em.blurred_profiles(per_end, view, em.cross_section(view, look),
                                    [(blur_px, 0.0)], grid, STEP_PX)
    f = bp.frac[:, None]
    m = (1 - f) * bl[bp.edge, 1, 0] + f * bl[(bp.edge + 1) % n, 0, 0]    # (S, G0)
    S = len(bp.edge)
    shift_px = (shift_mm + depth_mm * view_lean(view, bp.edge, bp.frac)) * bp.px_per_mm
    mw = np.array([np.interp(bp.w_px - s, w0, row) for s, row in zip(shift_px, m)])
    y = (rng.uniform(20, 40, (S, 1)) + rng.uniform(120, 200, (S, 1)) * mw
         + rng.normal(0, 1.0, mw.shape))
    bp.values = y
    return ReferenceImage(f"model{seed}", bp, CAM, HOLDER, pose.R, pose.t_mm, "round")


@pytest.fixture(scope="module")
def model_refs():
    return [model_reference(Pose.from_euler(3, -4, 2, 10, -8, 605), TRUE_LOOK, 1),
            model_reference(Pose.from_euler(-5, 2, -3, -12, 6, 620), TRUE_LOOK, 2)]


def test_calibration_recovers_a_known_look(model_refs):
    """From profiles the edge model made with a known look, the fit with the shift held at 0
    recovers that look's lobe, and the design edge then comes out where the pose puts it."""
    ticks = []
    cal = calibrate_edge_look(model_refs, rounds=1, tick=lambda *a: ticks.append(a))
    # the progress callback saw every evaluation of the first round, counting up
    assert len(ticks) > 10 and ticks[0][:2] == (1, 1)
    assert [t[1] for t in ticks if t[0] == 1] == list(range(1, 1 + sum(t[0] == 1
                                                                      for t in ticks)))
    assert abs(cal.look.specular / TRUE_LOOK.specular - 1) < 0.1, cal.look
    assert abs(cal.look.shininess / TRUE_LOOK.shininess - 1) < 0.15, cal.look
    # the nominal look leaves most of the cost; the recovered one only the noise
    assert cal.report["cost_ratio_to_start"] < 0.2
    sd = cal.sd()
    assert all(np.isfinite(v) and v >= 0 for v in sd.values())
    calibrated = shift_at_truth(model_refs, cal.band_looks(), shapes=("round",))
    generic = shift_at_truth(model_refs, shapes=("round",))
    assert abs(calibrated["mean_px"]) < 0.05
    assert abs(calibrated["mean_px"]) < abs(generic["mean_px"])


def test_calibration_with_worker_processes_is_the_same(model_refs):
    """``workers=2``: the cost evaluated in two processes (each holding the reference images)
    gives the same look, covariance and report as one process."""
    one = calibrate_edge_look(model_refs, rounds=1)
    two = calibrate_edge_look(model_refs, rounds=1, workers=2)
    assert two.x == one.x and two.cov_mean == one.cov_mean
    assert two.report["cost_ratio_to_start"] == one.report["cost_ratio_to_start"]


def test_offset_calibration_recovers_a_known_offset():
    """Profiles of the right look whose design edge lies 0.03 mm outside the true one: dm+b's fit
    puts it there (to its scan's grid: 0.2 px steps and a parabola, ~0.01 mm), the offset
    calibration finds the opposite offset for the fillets (none for a shape it never saw), and
    with it the design edge comes out at the known pose again."""
    poses = [Pose.from_euler(3, -4, 2, 10, -8, 605), Pose.from_euler(-5, 2, -3, -12, 6, 620),
             Pose.from_euler(1, 5, 4, 4, 10, 596)]
    refs = [model_reference(p, TRUE_LOOK, 10 + i, shift_mm=0.03, n_seg=4)
            for i, p in enumerate(poses)]
    cal = _calibration(specular=TRUE_LOOK.specular, shininess=TRUE_LOOK.shininess,
                       wall_albedo=TRUE_LOOK.wall_albedo, pocket_level=TRUE_LOOK.pocket_level)
    before = shift_at_truth(refs, cal.band_looks(), shapes=("round",))
    cal = calibrate_offsets(refs, cal, shapes=("round",))
    off = dict(cal.offsets.offset_mm)
    assert set(off) == {"round"}
    assert abs(before["mean_mm"] - 0.03) < 0.012
    assert abs(off["round"] + before["mean_mm"]) < 0.004, off
    after = shift_at_truth(refs, cal.band_looks(), shapes=("round",))
    assert abs(after["mean_mm"]) < 0.004
    back = load_edge_look_dict(cal.to_dict())
    assert back.offsets.offset_mm == cal.offsets.offset_mm


def test_offset_calibration_recovers_a_known_depth():
    """Profiles whose design edge images as a point 0.3 mm below the face would (a parallax of
    0.3 mm x the view's lean across the edge, a tilt error that grows with the tilt): the
    calibration keeps the depth (it predicts left-out images better), finds it, and with it the
    pose fitted at the known poses loses the error it had (here mostly sideways: a parallax
    moves the whole contour)."""
    rng = np.random.default_rng(3)
    poses = [Pose.from_euler(*rng.uniform(-10, 10, 3), *rng.uniform(-15, 15, 2),
                             rng.uniform(585, 620)) for _ in range(9)]
    refs = [model_reference(p, TRUE_LOOK, 30 + i, n_seg=4, depth_mm=0.3)
            for i, p in enumerate(poses)]
    cal = _calibration(specular=TRUE_LOOK.specular, shininess=TRUE_LOOK.shininess,
                       wall_albedo=TRUE_LOOK.wall_albedo, pocket_level=TRUE_LOOK.pocket_level)
    cal = calibrate_offsets(refs, cal, shapes=("round",))
    rep = cal.report["design_edge_offset"]["round"]
    assert rep["loo_error"]["uniform+depth"] < rep["loo_error"]["uniform"]
    assert abs(dict(cal.offsets.depth_mm)["round"] - 0.3) < 0.06, rep
    before, after = (np.array(rep[k]) for k in ("pose_error_sd_before", "pose_error_sd_after"))
    assert np.all(after[3:5] < 0.3 * before[3:5]), (before, after)   # X, Y
    back = load_edge_look_dict(cal.to_dict())
    assert back.offsets.depth_mm == cal.offsets.depth_mm
    assert back.offsets.cov_mm2 == cal.offsets.cov_mm2
    c = np.array(dict(cal.offsets.cov_mm2)["round"])
    assert c[1, 1] > 0 and np.isclose(np.sqrt(c[1, 1]), rep["depth_sd_mm"])
    z = [p.t_mm[2] for p in poses]
    assert back.offsets.distance_range_mm == pytest.approx((min(z), max(z)))
    looks = back.band_looks().offsets
    assert looks.covers(min(z)) and looks.covers(max(z) * 1.04)
    assert not looks.covers(max(z) * 1.1) and not looks.covers(min(z) * 0.9)
    assert not replace(looks, distance_range_mm=None).covers(min(z))
    lo, hi = dict(back.offsets.radius_range_mm)["round"]
    assert 0.4 < lo <= hi < 1.8            # the references' radii: 0.5-1.6 mm per edge
    assert looks.covers(min(z), "round", hi) and looks.covers(min(z), "chamfer", 0.0)
    assert not looks.covers(min(z), "round", hi + 0.5)
    assert not looks.covers(min(z), "round", lo - 0.3)


def test_offset_of_a_calibrated_depth_follows_the_lean():
    """``DesignEdgeOffsets.offset``: uniform offset minus depth x lean, per shape; 0 for a shape
    without a calibration."""
    lk = DesignEdgeOffsets(offset_mm=(("chamfer", 0.02),), depth_mm=(("chamfer", 0.4),))
    lean = np.array([-0.3, 0.0, 0.2])
    assert np.allclose(lk.offset("chamfer", lean), 0.02 - 0.4 * lean)
    assert np.allclose(lk.offset("round", lean), 0.0)
    assert lk and not DesignEdgeOffsets() and not BandLooks(em.EdgeLook()).offsets


def test_view_lean_is_the_parallax_of_a_point_below_the_face():
    """A point ``d`` below the face on an edge images where the face point ``d tan(theta)``
    outwards of it does (``tan(theta)`` from :func:`view_lean`): the camera's ray through the
    point crosses the face that far out across the edge (along the edge it moves too, which
    does not move the edge's line)."""
    pose = Pose.from_euler(6, -5, 3, 20, -10, 600)
    blank = np.zeros(CAM.image_size_px[::-1], np.uint8)
    bp = sample_band(blank, CAM, HOLDER, pose.R, pose.t_mm, n_seg=4, positions=4)
    view = em.edge_views(pose.R, pose.t_mm, CAM.K, HOLDER)
    lean = view_lean(view, bp.edge, bp.frac)
    d = 2.0
    below = bp.points_holder_mm + [0.0, 0.0, d]               # +Z: away from the camera
    C = -pose.R.T @ pose.t_mm
    ray = below - C
    on_face = C + (-C[2] / ray[:, 2])[:, None] * ray
    across = np.sum((on_face - bp.points_holder_mm)[:, :2] * HOLDER.edge_normals[bp.edge], 1)
    # linear between the edge's ends: exact at them, to ~1e-3 mm between
    assert np.abs(across - d * lean).max() < 0.005
    assert np.ptp(lean) > 0.1


def _calibration(**look) -> EdgeLookCalibration:
    lk = replace(em.EdgeLook(profile_sigma_px=0.0), **look)
    x = (float(np.log(lk.specular)), float(np.log(lk.shininess)), lk.wall_albedo,
         lk.pocket_level)
    cov = tuple(tuple(1e-4 * (i == j) for j in range(4)) for i in range(4))
    return EdgeLookCalibration(lk, x, cov, cov)


@pytest.fixture(scope="module")
def new_holder(tmp_path_factory):
    """A new holder with fillets of 0.5-1.5 mm (the analytic ``new``) and a look file."""
    d = tmp_path_factory.mktemp("look")
    pose = Pose.from_euler(-2, 3, -3, -12, 5, 614)
    img = render_holder(pose, CAM, HOLDER, preset("new"), seed=5, noise_seed=6).image
    cv2.imwrite(str(d / "img.png"), img)
    cal = replace(_calibration(specular=1.3, shininess=33.0, wall_albedo=0.2,
                               pocket_level=0.1),
                  offsets=DesignEdgeOffsets(offset_mm=(("chamfer", 0.02), ("round", -0.01)),
                                            scatter_mm=(("chamfer", 0.03), ("round", 0.03)),
                                            distance_range_mm=(590.0, 630.0)))
    save_edge_look(cal, d / "look.json")
    return pose, img, cal, d


def test_edge_look_changes_the_fitted_look(new_holder):
    """``measure(edge_look=...)``: dm+b fits the calibrated look instead of the generic ones
    (without it, a generic look as before), and the budget's edge-model term carries the
    calibration's offset scatter; given the variants too, they are fitted for the budget."""
    from cutterpose.image import FeatureParams, detect_features
    from cutterpose.solvers.edge_band import refine_features

    pose, img, cal, _ = new_holder
    limits = QualityLimits(edge_shape="unknown")
    plain = measure(img, CAM, HOLDER, method="dm+b", limits=limits)
    calib = measure(img, CAM, HOLDER, method="dm+b", limits=limits, edge_look=cal)
    b0, b1 = plain.estimate.band, calib.estimate.band
    generic = {(v.specular, v.shininess) for v in em.LOOK_VARIANTS}
    assert (b0.fit.best.look.specular, b0.fit.best.look.shininess) in generic
    assert not b0.calibrated
    assert b1.calibrated
    assert (b1.fit.best.look.specular, b1.fit.best.look.shininess) == (1.3, 33.0)
    parts = calib.quality.budget.to_dict()["parts"]
    assert parts["edge model"]["position_3sigma_mm"] > 0.01
    # the measured scatter replaces the generic floor (a calibration without offsets keeps it)
    assert "model floor" not in parts
    assert "model floor" in plain.quality.budget.to_dict()["parts"]
    bare = measure(img, CAM, HOLDER, method="dm+b", limits=limits,
                   edge_look=replace(cal, offsets=DesignEdgeOffsets()))
    assert "model floor" in bare.quality.budget.to_dict()["parts"]
    # offsets measured at other distances do not vouch for this one (the pose is at 614 mm),
    # nor on breaks unlike this one
    far = measure(img, CAM, HOLDER, method="dm+b", limits=limits,
                  edge_look=replace(cal, offsets=replace(cal.offsets,
                                                         distance_range_mm=(800.0, 900.0))))
    assert "model floor" in far.quality.budget.to_dict()["parts"]
    big = tuple((k, (3.0, 5.0)) for k in ("round", "chamfer"))
    worn_ref = measure(img, CAM, HOLDER, method="dm+b", limits=limits,
                       edge_look=replace(cal, offsets=replace(cal.offsets,
                                                              radius_range_mm=big)))
    assert "model floor" in worn_ref.quality.budget.to_dict()["parts"]
    # outside what it covers the calibration's own correction is a 1-sigma part of its own
    # (how it carries there was not measured); inside, and without offsets, no such part
    for m in (far, worn_ref):
        ext = m.quality.budget.to_dict()["parts"]["calibration extrapolated"]
        assert ext["position_3sigma_mm"] > 0
    for m in (calib, plain, bare):
        assert "calibration extrapolated" not in m.quality.budget.to_dict()["parts"]
    # and the JSON says why
    assert calib.estimate.band.to_dict()["look"]["calibration_covers"] is True
    assert far.estimate.band.to_dict()["look"]["calibration_covers"] is False
    assert plain.estimate.band.to_dict()["look"]["calibration_covers"] is None
    # the variants round the look (band_looks(variant_axes=...)) enter the edge-model term
    feats = detect_features(img, CAM, HOLDER, FeatureParams.for_camera(CAM))
    start = plain.estimate.start
    est = refine_features(start, feats, CAM, HOLDER, edge_look=cal.band_looks(variant_axes=2))
    b2 = est.band
    varied = [lf.look for lf in b2.fit.plausible if lf.look.shape == b2.fit.best.look.shape]
    assert len(varied) >= 2

    def photometry(v):
        return v.specular, v.shininess, v.wall_albedo, v.pocket_level

    assert all(photometry(v) != photometry(b2.fit.best.look) for v in varied)


def test_calibrated_depth_moves_the_pose_and_enters_the_budget(new_holder):
    """A calibrated depth of the design edge moves each segment by depth x lean (the pose with
    it differs from the pose without), and its uncertainty (the (offset, depth) covariance)
    widens the budget's edge-model term."""
    from cutterpose.image import FeatureParams, detect_features
    from cutterpose.solvers.edge_band import refine_features

    pose, img, cal, _ = new_holder
    feats = detect_features(img, CAM, HOLDER, FeatureParams.for_camera(CAM))
    start = measure(img, CAM, HOLDER, method="dm+").estimate
    base = cal.band_looks()
    shapes = ("round", "chamfer")
    def with_offsets(looks, **kw):
        return replace(looks, offsets=replace(looks.offsets, **kw))

    deep = with_offsets(base, depth_mm=tuple((k, 0.4) for k in shapes))
    unsure = with_offsets(deep, cov_mm2=tuple((k, ((0.0, 0.0), (0.0, 0.04))) for k in shapes))
    e0, e1, e2 = (refine_features(start, feats, CAM, HOLDER, edge_look=lk)
                  for lk in (base, deep, unsure))
    assert e0 and e1 and e2
    assert np.linalg.norm(e1.t_cam_holder_mm - e0.t_cam_holder_mm) > 0.02
    m1, m2 = (np.trace(e.band.cov_parts["edge model"][3:, 3:]) for e in (e1, e2))
    assert m2 > m1 * 1.2, (m1, m2)
    # the offset and the depth are propagated jointly: anti-correlated as a calibration finds
    # them (the segments see the pocket edge from its inside, tan(theta) < 0, so a larger
    # depth and a smaller offset move them alike), they widen the budget less than the same
    # variances taken apart
    a, b = 0.04, 0.2
    apart = with_offsets(deep, cov_mm2=tuple((k, ((a * a, 0.0), (0.0, b * b))) for k in shapes))
    joint = with_offsets(deep, cov_mm2=tuple((k, ((a * a, -a * b), (-a * b, b * b)))
                                           for k in shapes))
    m_apart, m_joint = (np.trace(refine_features(start, feats, CAM, HOLDER, edge_look=lk)
                                 .band.cov_parts["edge model"][3:, 3:])
                        for lk in (apart, joint))
    assert m_joint < 0.7 * m_apart, (m_joint, m_apart)


def test_cli_edge_look_option(new_holder):
    """``cutterpose measure --edge-look``: the JSON says which look was fitted."""
    _, _, _, d = new_holder
    res = runner.invoke(app, ["measure", str(d / "img.png"), "--json", "--edge-look",
                              str(d / "look.json")])
    assert res.exit_code in (0, 3), res.output
    look = json.loads(res.stdout)["edge_band"]["look"]
    assert look["calibrated"] is True and look["specular"] == 1.3


def _good_dict():
    return _calibration(specular=0.9, shininess=30.0).to_dict()


@pytest.mark.parametrize("change,words", [
    (lambda d: d.update(format="camera"), "not an edge look file"),
    (lambda d: d.update(version=7), "version"),
    (lambda d: d["look"].update(specular="bright"), "specular"),
    (lambda d: d["look"].update(shininess=float("nan")), "shininess"),
    (lambda d: d["look"].update(wall_albedo=-0.2), "wall_albedo"),
    (lambda d: d.pop("look"), "look"),
    (lambda d: d.update(cov_mean=[[1.0, 2.0], [2.0, 1.0]]), "cov_mean"),
    (lambda d: d.update(cov_image=[[-1.0 if i == j else 0.0 for j in range(4)]
                                   for i in range(4)]), "cov_image"),
    (lambda d: d.update(blurs_px=[]), "blurs_px"),
    (lambda d: d.update(x=[0.0, 1.0]), "'x'"),
    (lambda d: d.update(design_edge_offset_mm={"square": 0.01}), "design_edge_offset_mm"),
    (lambda d: d.update(design_edge_offset_mm={"round": 3.0}), "design_edge_offset_mm"),
    (lambda d: d.update(design_edge_depth_mm={"chamfer": 7.0}), "design_edge_depth_mm"),
    (lambda d: d.update(design_edge_depth_mm={"chamfer": "deep"}), "design_edge_depth_mm"),
    (lambda d: d.update(distance_range_mm=[700.0, 600.0]), "distance_range_mm"),
    (lambda d: d.update(design_edge_offset_depth_cov_mm2={"round": [[1.0, 2.0], [2.0, 1.0]]}),
     "design_edge_offset_depth_cov_mm2"),
    (lambda d: d.update(design_edge_offset_depth_cov_mm2={"round": [1.0]}),
     "design_edge_offset_depth_cov_mm2"),
    (lambda d: d.update(distance_range_mm="near"), "distance_range_mm"),
    (lambda d: d.update(radius_range_mm={"round": [2.0, 1.0]}), "radius_range_mm"),
    (lambda d: d.update(radius_range_mm={"round": 1.0}), "radius_range_mm"),
])
def test_malformed_look_file_is_a_typed_error(tmp_path, change, words):
    d = _good_dict()
    change(d)
    p = tmp_path / "look.json"
    p.write_text(json.dumps(d))
    with pytest.raises(EdgeLookFileError, match=words):
        load_edge_look(p)


def test_version_1_look_file_reads_without_a_depth(tmp_path):
    """A file written before the depth (version 1) is read, with no depth."""
    d = _good_dict()
    d["version"] = 1
    for k in ("design_edge_depth_mm", "design_edge_depth_sd_mm"):
        d.pop(k, None)
    p = tmp_path / "v1.json"
    p.write_text(json.dumps(d))
    assert load_edge_look(p).offsets.depth_mm == ()


def test_look_file_round_trip_and_unreadable_files(tmp_path):
    cal = _calibration(specular=0.9, shininess=30.0, wall_albedo=0.1)
    save_edge_look(cal, tmp_path / "ok.json")
    back = load_edge_look(tmp_path / "ok.json")
    assert back.look == cal.look and back.x == cal.x and back.cov_image == cal.cov_image
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(EdgeLookFileError, match="not valid JSON"):
        load_edge_look(tmp_path / "bad.json")
    with pytest.raises(EdgeLookFileError, match="not found"):
        load_edge_look(tmp_path / "missing.json")


def test_cli_malformed_look_file_one_line(new_holder, tmp_path):
    _, _, _, d = new_holder
    p = tmp_path / "look.json"
    p.write_text(json.dumps({"format": "cutterpose-edge-look", "version": 1}))
    res = runner.invoke(app, ["measure", str(d / "img.png"), "--edge-look", str(p)])
    assert res.exit_code == 2
    assert "look" in res.output and "Traceback" not in res.output


def test_cell_file_edge_look(tmp_path):
    """``edge_look = "look.json"`` in the service's cell file: loaded at start and given to
    every measurement; a malformed one stops the start with the field named."""
    from cutterpose.errors import CellFileError
    from cutterpose.service.config import load_cell

    env = {"CUTTERPOSE_TOKEN": "s3cret-token"}
    save_edge_look(_calibration(specular=0.9, shininess=30.0), tmp_path / "look.json")
    (tmp_path / "cell.toml").write_text('edge_look = "look.json"\n')
    cell = load_cell(tmp_path / "cell.toml", env=env)
    assert cell.edge_look is not None and cell.edge_look.look.specular == 0.9
    assert cell.describe()["edge_look"] is True
    assert load_cell(None, env=env).edge_look is None
    (tmp_path / "bad.json").write_text('{"format": "cutterpose-edge-look", "version": 1}')
    (tmp_path / "bad.toml").write_text('edge_look = "bad.json"\n')
    with pytest.raises(CellFileError, match="edge_look"):
        load_cell(tmp_path / "bad.toml", env=env)


def test_cli_calibrate_needs_known_poses(tmp_path):
    """``calibrate-edge-look`` without a set's truth.json or a pose file says what it needs."""
    res = runner.invoke(app, ["calibrate-edge-look", str(tmp_path), "--out",
                              str(tmp_path / "look.json")])
    assert res.exit_code == 2 and "truth.json" in res.output and "--poses" in res.output
    cv2.imwrite(str(tmp_path / "a.png"), np.zeros((8, 8), np.uint8))
    (tmp_path / "poses.csv").write_text("x_mm,y_mm,z_mm,qx,qy,qz,qw\n0,0,600,0,0,0,1\n"
                                        "0,0,610,0,0,0,1\n")
    res = runner.invoke(app, ["calibrate-edge-look", str(tmp_path / "a.png"), "--poses",
                              str(tmp_path / "poses.csv"), "--out", str(tmp_path / "l.json")])
    assert res.exit_code == 2 and "1 images but 2 poses" in res.output


def test_cli_calibrate_pools_several_sets(tmp_path, monkeypatch):
    """``calibrate-edge-look SET SET``: the reference images of both sets are pooled (the look
    fit itself is stubbed here: it is tested above); a folder without truth.json is named."""
    import cutterpose.calibration.edge_look as el

    for seed in (3, 4):
        res = runner.invoke(app, ["render-set", "--count", "1", "--seed", str(seed),
                                  "--preset", "new", "--out", str(tmp_path / f"s{seed}")])
        assert res.exit_code == 0, res.output
    seen = {}

    def stub(refs, progress=None, tick=None, **kw):
        seen["n"] = len(refs)
        tick(1, 1, el.MAX_EVALS)
        return _calibration(specular=1.0, shininess=30.0)

    monkeypatch.setattr(el, "calibrate_edge_look", stub)
    res = runner.invoke(app, ["calibrate-edge-look", str(tmp_path / "s3"), str(tmp_path / "s4"),
                              "--no-offsets", "--json", "--out", str(tmp_path / "look.json")])
    assert res.exit_code == 0, res.output
    assert seen["n"] == 2
    assert load_edge_look(tmp_path / "look.json").report["shift_at_truth"]["calibrated"]
    res = runner.invoke(app, ["calibrate-edge-look", str(tmp_path / "s3"), str(tmp_path),
                              "--out", str(tmp_path / "l2.json")])
    assert res.exit_code == 2 and "not a rendered set" in res.output


def test_tracker_fits_the_calibrated_look(new_holder):
    """``Tracker(edge_look=...)`` (and ``cutterpose track --edge-look``): the full measurement
    of the first frame fits the calibrated look, as ``measure`` does."""
    from cutterpose.tracking import Tracker

    pose, img, cal, _ = new_holder
    limits = QualityLimits(edge_shape="unknown")
    plain = Tracker(CAM, HOLDER, limits=limits).update(img)     # dm+b: the default
    calib = Tracker(CAM, HOLDER, "dm+b", limits=limits, edge_look=cal).update(img)
    assert plain.mode == calib.mode == "full"
    assert plain.measurement.method == calib.measurement.method == "dm+b"
    b0 = plain.measurement.estimate.band
    b1 = calib.measurement.estimate.band
    assert not b0.calibrated and b1.calibrated
    assert (b1.fit.best.look.specular, b1.fit.best.look.shininess) == (1.3, 33.0)


def test_only_methods_that_take_a_look_use_it(new_holder):
    """A calibrated look reaches the method that fits the edge's look (``dm+b``: its band fit
    says it is calibrated); ``dm+r``, which does not, measures the same pose with or without
    it rather than failing on it."""
    _, img, cal, _ = new_holder
    m = measure(img, CAM, HOLDER, method="dm+r", edge_look=cal)
    m0 = measure(img, CAM, HOLDER, method="dm+r")
    assert m.estimate.method == "dm+r" and m.pose is not None
    assert np.array_equal(m.pose.dof, m0.pose.dof)
    b = measure(img, CAM, HOLDER, method="dm+b", edge_look=cal)
    assert b.estimate.band is not None and b.estimate.band.calibrated


def test_extrapolated_calibration_part_is_its_correction(new_holder):
    """Beyond its reference distances the calibration's correction (offset and depth, each
    segment moved by ``offset - depth tan(theta)``) enters the budget as 1 sigma: that part's
    std per DOF is the pose change between measuring with and without the calibrated offsets
    (fails if the part were the uniform offset alone, or the correction's sign or size off)."""
    _, img, cal, _ = new_holder
    limits = QualityLimits(edge_shape="unknown")
    offs = replace(cal.offsets, offset_mm=(("chamfer", 0.05), ("round", 0.05)),
                   depth_mm=(("chamfer", 0.5), ("round", 0.5)), distance_range_mm=(800.0, 900.0))
    with_off = measure(img, CAM, HOLDER, method="dm+b", limits=limits,
                       edge_look=replace(cal, offsets=offs))
    without = measure(img, CAM, HOLDER, method="dm+b", limits=limits,
                      edge_look=replace(cal, offsets=DesignEdgeOffsets()))
    sd = np.sqrt(np.diag(with_off.quality.budget.parts["calibration extrapolated"]))
    dx = np.abs(with_off.pose.dof - without.pose.dof)
    assert dx[5] > 0.1                               # the correction matters in depth
    # (the second pass samples at the pose it is given, and the tilts move with that by a few
    # hundredths of a degree: docs/notes/edge_band.md, "How far the pose moves with its start")
    assert np.allclose(sd, dx, rtol=0.15, atol=[0.03] * 3 + [5e-3] * 3)
