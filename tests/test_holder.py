import json

import numpy as np
import pytest

from cutterpose.errors import HolderModelError
from cutterpose.geometry.holder import default_holder, holder_from_dict, load_holder


def _spec():
    h = default_holder()
    return h.to_dict()


def test_default_holder(holder):
    assert holder.n_corners == 20
    assert holder.area_mm2 == pytest.approx(57600.0)
    assert np.all(holder.points_holder_mm[:, 2] == 0)
    idx = holder.edge_direction_index
    assert idx.sum() == 10 and np.all(idx != np.roll(idx, 1))  # alternate X / Y
    # edge lines pass through both end corners
    L = holder.edge_lines
    for i, (p, q) in enumerate(holder.edges):
        assert abs(L[i, :2] @ p + L[i, 2]) < 1e-9 and abs(L[i, :2] @ q + L[i, 2]) < 1e-9


@pytest.mark.parametrize("mutate,msg", [
    (lambda d: d.pop("inner_contour_corners"), "inner_contour_corners"),
    (lambda d: d.pop("outer_rectangle"), "outer_rectangle"),
    (lambda d: d["outer_rectangle"].update(length_x="wide"), "outer_rectangle.length_x"),
    (lambda d: d["outer_rectangle"].update(width_y=-1), "outer_rectangle.width_y"),
    (lambda d: d["inner_contour_corners"][3].__setitem__(0, float("nan")), "non-finite"),
    (lambda d: d.__setitem__("inner_contour_corners",
                             [c + [5.0 if i == 4 else 0.0]
                              for i, c in enumerate(d["inner_contour_corners"])]), "not planar"),
    (lambda d: d["inner_contour_corners"][3].__setitem__(1, -55.0), "neither X nor Y"),
    (lambda d: d.__setitem__("inner_contour_corners", d["inner_contour_corners"][::-1]),
     "counter-clockwise"),
    (lambda d: d.__setitem__("inner_contour_corners", "abc"), "inner_contour_corners"),
    (lambda d: d["outer_rectangle"].update(length_x=300.0), "inside"),
    (lambda d: d.__setitem__("units", "inch"), "units"),
])
def test_malformed_holder_names_the_problem(mutate, msg):
    d = json.loads(json.dumps(_spec()))
    mutate(d)
    with pytest.raises(HolderModelError, match=msg):
        holder_from_dict(d)


def test_self_intersecting_contour_is_rejected():
    # a "bow-tie" rectilinear contour whose edges cross
    c = [[0, 0], [10, 0], [10, 10], [5, 10], [5, -5], [2, -5], [2, 5], [0, 5]]
    with pytest.raises(HolderModelError, match="cross"):
        holder_from_dict({"inner_contour_corners": c,
                          "outer_rectangle": {"length_x": 100, "width_y": 100}})


def test_load_holder_file_errors(tmp_path):
    with pytest.raises(HolderModelError, match="not found"):
        load_holder(tmp_path / "none.json")
    (tmp_path / "h.json").write_text("[1, 2")
    with pytest.raises(HolderModelError, match="JSON"):
        load_holder(tmp_path / "h.json")
    (tmp_path / "ok.json").write_text(json.dumps(_spec()))
    assert load_holder(tmp_path / "ok.json").area_mm2 == pytest.approx(57600.0)
