"""The physically based renderer (render/pbr.py): scene parameters, geometry and truth without
Mitsuba; small scalar_rgb renders (a tenth-scale Table 1 camera) with it."""

import json
import sys

import numpy as np
import pytest

from cutterpose.errors import InputError
from cutterpose.geometry.camera import camera_from_dict, default_camera
from cutterpose.geometry.holder import default_holder
from cutterpose.geometry.pose import Pose
from cutterpose.render import pbr, sets

HOLDER = default_holder()


def small_camera():
    """The Table 1 camera at a tenth of its resolution (412 x 301 px, 2.4 mm per pixel at
    600 mm): the same field of view and distortion, a hundredth of the rendering cost."""
    d = default_camera("table1").to_dict()
    d["image_size_px"] = [412, 301]
    d["pixel_size_m"] = [p * 10 for p in d["pixel_size_m"]]
    d["principal_point_px"] = [(p + 0.5) / 10 - 0.5 for p in d["principal_point_px"]]
    return camera_from_dict(d)


def params(name, seed=0):
    return pbr.draw_params(pbr.field_preset(name), HOLDER, np.random.default_rng(seed))


def test_missing_mitsuba_is_a_typed_error(monkeypatch):
    monkeypatch.setitem(sys.modules, "mitsuba", None)
    with pytest.raises(pbr.MitsubaMissingError, match=r"pip install -e '\.\[field\]'"):
        pbr.load_mitsuba("scalar_rgb")


def test_unknown_preset():
    with pytest.raises(pbr.InputError, match="sharp, new, worn"):
        pbr.field_preset("muddy")


def test_params_follow_the_presets_and_the_seed():
    assert params("worn", 3) == params("worn", 3)
    assert params("worn", 3) != params("worn", 4)
    for seed in range(20):
        s, n, w = params("sharp", seed), params("new", seed), params("worn", seed)
        assert s["radius_hi_mm"] == 0 and s["profile"] == "sharp" and not s["chips"]
        assert not s["slurry"] and s["cutter"] is not None
        assert 0.5 <= n["radius_lo_mm"] <= n["radius_hi_mm"] <= 1.5 and not n["slurry"]
        assert n["cutter"] is not None and not n["chips"]
        assert 1.5 <= w["radius_lo_mm"] <= w["radius_hi_mm"] <= 5.0
        assert 1 <= len(w["slurry"]) <= 4 and w["slurry"][0]["across_edge"]
        assert 2 <= len(w["chips"]) <= 6 and w["corrosion"] > 0 and w["wet_patches"] >= 1
    json.dumps(params("worn"))  # the truth file stores them


def test_fillet_profile_and_chips():
    p = params("new", 1)
    p.update(profile="round", chips=[])
    # points on the top face at distance s outside the middle of edge 0 (y = -90, along X)
    s = np.array([0.0, 0.25, 0.5, 1.0, 3.0])
    X, Y = np.zeros_like(s), -90.0 - s
    r = pbr.edge_radius(p, X, Y)
    Z = pbr.surface_depth(p, HOLDER, X, Y)
    t = np.clip(r - s, 0, None)
    assert np.allclose(Z, r - np.sqrt(r * r - t * t))
    assert Z[0] == pytest.approx(r[0]) and Z[-1] == 0.0
    p["profile"] = "chamfer"
    assert np.allclose(pbr.surface_depth(p, HOLDER, X, Y), np.clip(r - s, 0, None))
    p["chips"] = [{"edge": 0, "x_mm": 0.0, "y_mm": -90.0, "half_length_mm": 4.0,
                   "half_width_mm": 2.0, "depth_mm": 3.0, "wobble": [0.0, 0.0]}]
    assert pbr.surface_depth(p, HOLDER, X, Y)[0] == pytest.approx(3.0)


def test_radius_truth_per_edge():
    p = params("worn", 2)
    e = pbr.edge_radius_stats(p, HOLDER)
    assert len(e) == HOLDER.n_corners
    for d in e:
        assert p["radius_lo_mm"] - 1e-9 <= d["radius_min_mm"] <= d["radius_mean_mm"]
        assert d["radius_mean_mm"] <= d["radius_max_mm"] <= p["radius_hi_mm"] + 1e-9
    assert sum(len(d["chips"]) for d in e) == len(p["chips"])


def test_geometry_walls_meet_the_face():
    p = params("worn", 5)
    g = pbr.build_geometry(p, HOLDER, step_mm=1.0)
    top, walls = g["top"][0], g["walls"][0]
    # every wall-top vertex is a vertex of the face (no crack along the edge)
    wt = walls.V[walls.V[:, 2] < p["pocket_depth_mm"] - 1e-3]
    keys = {tuple(v) for v in np.round(top.V, 4)}
    assert all(tuple(v) in keys for v in np.round(wt, 4))
    assert {"cutter_ring", "cutter_hub", "plate", "floor"} <= set(g)
    assert sum(k.startswith("slurry") for k in g) == len(p["slurry"])


def test_hidden_corners_by_slurry_and_chips():
    p = params("sharp", 0)
    p["cutter"] = None
    p["slurry"] = [{"x_mm": 120.0, "y_mm": -60.0, "rx_mm": 12.0, "ry_mm": 12.0, "rz_mm": 6.0,
                    "yaw_deg": 0.0, "across_edge": True, "corner": 2, "wet": False,
                    "albedo": 0.2, "roughness": 0.9, "shape_seed": 1}]
    p["chips"] = [{"edge": 10, "x_mm": 110.0, "y_mm": 90.0, "half_length_mm": 12.0,
                   "half_width_mm": 3.0, "depth_mm": 2.0, "wobble": [0.0, 0.0]}]
    g = pbr.build_geometry(p, HOLDER, step_mm=2.0)
    h = pbr.hidden_corners(p, HOLDER, Pose.nominal(), g)
    assert h.get(2) == ["slurry"] and h.get(10) == ["chip"] and set(h) == {2, 10}


# ------------------------------------------------------------------------------------------
# with Mitsuba (scalar_rgb: no LLVM needed)
@pytest.fixture(scope="module")
def mi():
    pytest.importorskip("mitsuba")
    return pbr.load_mitsuba("scalar_rgb")


def test_sharp_edge_sits_on_the_design_edge(mi):
    cam = small_camera()
    pose = Pose.from_euler(4, -6, 3, 8, -5, 605)
    r = pbr.render_field(pose, cam, HOLDER, "sharp", seed=1, variant="scalar_rgb", spp=16,
                         sensor=False)
    assert r.image.shape == (301, 412) and r.image.dtype == np.uint8
    assert np.allclose(r.corners_px, cam.project(pose.apply(HOLDER.points_holder_mm)))
    off = pbr.edge_step_offsets(r.value, pose, cam, HOLDER, step_mm=2.0)
    off = off[np.isfinite(off)]
    assert len(off) >= 12
    # a tenth-scale image: 0.05 px here is 0.5 px of the real camera; the full-scale figure is
    # in docs/notes/render_pbr.md
    assert abs(off.mean()) < 0.05 and np.abs(off).max() < 0.25
    # the top face is bright, the pocket dark
    assert r.value[tuple(np.round(r.corners_px[0] + [-6, -6]).astype(int)[::-1])] > 70


def test_worn_image_and_truth(mi, tmp_path):
    cam = small_camera()
    r = pbr.render_field(Pose.from_euler(-3, 5, -2, -6, 4, 590), cam, HOLDER, "worn", seed=7,
                         variant="scalar_rgb", spp=4)
    assert 10 < r.image.mean() < 200
    t = r.truth_dict("a.png")
    assert t["difficulty"] == "worn" and len(t["corners_px"]) == 20
    assert t["occluded_corners"] == sorted(int(k) for k in t["hidden_corners"])
    assert len(t["edges"]) == 20 and t["render"]["variant"] == "scalar_rgb"
    path = pbr.save_field_rendered(r, tmp_path / "a.png", cam)
    doc = json.loads(path.with_suffix(".truth.json").read_text())
    assert doc["images"][0]["file"] == "a.png"


def test_render_set_is_an_image_set(mi, tmp_path):
    from cutterpose.experiments.images import load_image_set

    cam = small_camera()
    sets.render_field_set(2, 5, tmp_path, "new", cam, variant="scalar_rgb", spp=2)
    camera, holder, entries = load_image_set(tmp_path)
    assert len(entries) == 2 and (tmp_path / entries[1]["file"]).exists()
    assert all(e["difficulty"] == "new" and e["engine"] == "pbr" for e in entries)
    # deterministic per seed
    a = json.loads((tmp_path / "truth.json").read_text())["images"][0]["params"]
    sets.render_field_set(1, 5, tmp_path / "again", "new", cam, variant="scalar_rgb", spp=2)
    assert json.loads((tmp_path / "again" / "truth.json").read_text())["images"][0][
        "params"] == a
    # an interrupted set goes on where it stopped
    sets.render_field_set(2, 5, tmp_path / "again", "new", cam, variant="scalar_rgb", spp=2,
                         resume=True)
    b = json.loads((tmp_path / "again" / "truth.json").read_text())["images"]
    assert [e["params"] for e in b] == [e["params"] for e in entries]


def test_pbr_approach_sequence_same_scene_fresh_noise(tmp_path, monkeypatch):
    """render-sequence --engine pbr: the scene is drawn once from the seed (same holder in
    every frame), the noise per frame; without Mitsuba, a typed error naming the extra."""
    from cutterpose.render.sequence import render_sequence

    monkeypatch.setenv("CUTTERPOSE_PBR_VARIANT", "scalar_rgb")
    path = render_sequence(tmp_path / "seq", 3, 700.0, 600.0, small_camera(), seed=2,
                           engine_name="pbr", spp=1)
    doc = json.loads(path.read_text())
    assert doc["sequence"]["engine"] == "pbr" and "new" in doc["presets"]
    assert [e["frame"] for e in doc["images"]] == [0, 1, 2]
    assert all(e["params"] == doc["images"][0]["params"] for e in doc["images"])
    assert all(e["render"]["spp"] == 1 for e in doc["images"])
    z = [e["t_cam_holder_mm"][2] for e in doc["images"]]
    assert z == pytest.approx([700.0, 650.0, 600.0])
    import cv2

    imgs = [cv2.imread(str(tmp_path / "seq" / e["file"]), cv2.IMREAD_GRAYSCALE)
            for e in doc["images"]]
    assert all(im.shape == (301, 412) and im.std() > 5 for im in imgs)
    with pytest.raises(pbr.InputError, match="pbr preset"):
        render_sequence(tmp_path / "bad", 2, settings="field", engine_name="pbr")
    monkeypatch.setitem(sys.modules, "mitsuba", None)
    with pytest.raises(pbr.MitsubaMissingError, match=r"\[field\]"):
        render_sequence(tmp_path / "none", 2, engine_name="pbr")


def test_render_set_views_show_one_holder_from_several_poses(mi, tmp_path):
    """--views: the same scene (wear, chips, slurry, textures), another pose and noise per view;
    views=1 stays the plain set."""
    cam = small_camera()
    sets.render_field_set(4, 7, tmp_path / "v", "worn", cam, variant="scalar_rgb", spp=1,
                         views=2)
    doc = json.loads((tmp_path / "v" / "truth.json").read_text())
    im = doc["images"]
    assert doc["views"] == 2
    assert [(e["holder_index"], e["view"]) for e in im] == [(0, 0), (0, 1), (1, 0), (1, 1)]
    assert im[0]["seed"] == im[1]["seed"] != im[2]["seed"]
    assert im[0]["edge_profile"] == im[1]["edge_profile"]
    assert im[0]["params"]["slurry"] == im[1]["params"]["slurry"]
    assert im[0]["params"] != im[2]["params"]
    assert not np.allclose(im[0]["dof"], im[1]["dof"])
    sets.render_field_set(1, 7, tmp_path / "one", "worn", cam, variant="scalar_rgb", spp=1)
    one = json.loads((tmp_path / "one" / "truth.json").read_text())["images"][0]
    # view 0 of holder h is image h of the plain set, the other views are retakes
    assert "view" not in one and one["params"] == im[0]["params"]
    assert one["dof"] == im[0]["dof"]
    assert (tmp_path / "one" / "img_0000.png").read_bytes() == \
        (tmp_path / "v" / "img_0000.png").read_bytes()
    with pytest.raises(InputError, match="views"):
        sets.render_field_set(1, 7, tmp_path / "x", "worn", cam, views=0)
