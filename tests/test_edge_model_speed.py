"""The fast paths of the edge model and of dm+r (issue 13 on top of issue 10): they must give
the offsets of the reference computation, :func:`cutterpose.image.edge_model.edge_offsets_mm`."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy.interpolate import PchipInterpolator

from cutterpose.geometry.camera import default_camera
from cutterpose.geometry.holder import default_holder
from cutterpose.geometry.pose import Pose
from cutterpose.image import edge_model as em
from cutterpose.image.edge_model import (
    LOOK_VARIANTS,
    TABLE_RADII_MM,
    EdgeLook,
    OffsetTable,
    build_offset_grid,
    edge_offsets_mm,
    edge_views,
    look_offsets_mm,
    radius_offsets_mm,
    tabulated_w_px,
)

HOLDER = default_holder()
CAM = default_camera("table1")
POSES = [Pose.from_euler(3, -4, 2, 5, -8, 610), Pose.from_euler(-7, 6, -3, -15, 12, 575)]


def test_per_radius_tables_equal_the_reference_offsets():
    for pose in POSES:
        for shape in ("round", "chamfer"):
            look = EdgeLook(shape=shape)
            v = edge_views(pose.R, pose.t_mm, CAM.K, HOLDER, look)
            ref = edge_offsets_mm(TABLE_RADII_MM, v, look, with_rival=False)["delta_mm"]
            fast = radius_offsets_mm(TABLE_RADII_MM, v, look)
            assert np.nanmax(np.abs(fast - ref)) < 1e-4
            assert np.array_equal(np.isnan(fast), np.isnan(ref))


def test_batched_looks_and_rival_equal_the_reference():
    pose = POSES[1]
    looks = [replace(lk, shape="round") for lk in LOOK_VARIANTS] + [EdgeLook(shape="chamfer")]
    v = edge_views(pose.R, pose.t_mm, CAM.K, HOLDER)
    for r in (0.7, 2.5):
        d, (rival_d, ratio) = look_offsets_mm(r, v, looks, rival_look=0)
        for k, lk in enumerate(looks):
            ref = edge_offsets_mm(np.array([r]), v, lk)
            err = np.abs(d[k] - ref["delta_mm"][..., 0])
            # the shading is evaluated at the grid points instead of interpolated: equal to
            # ~1e-4 px, except where two rises of the profile tie
            assert np.nanmedian(err) < 1e-4 and np.nanmean(err < 1e-3) > 0.95
        ref = edge_offsets_mm(np.array([r]), v, looks[0])
        assert np.nanmean(np.abs(ratio - ref["rival_ratio"][..., 0]) < 1e-3) > 0.95


def test_table_evaluation_equals_scipy_pchip():
    t = OffsetTable(POSES[0].R, POSES[0].t_mm, CAM.K, HOLDER)
    p = PchipInterpolator(t.radii, t.delta, axis=-1)
    for r in (0.0, 0.1, 0.77, 2.0, 6.4, 6.5):
        val, slope = t(r)
        assert np.allclose(val, p(r), atol=1e-12) and np.allclose(slope, p.derivative()(r),
                                                                   atol=1e-12)
    many = t.many([0.3, 1.7, 9.0])[0]
    assert np.allclose(many[2], t(6.5)[0]) and np.allclose(many[1], t(1.7)[0])


def test_shipped_grid_is_current_and_close_to_the_exact_offsets():
    # stale grid (the model changed, the file did not): some nodes rebuilt and compared
    grids = em._shipped_grids()
    look = EdgeLook()
    assert em.look_key(look) in grids and em.look_key(EdgeLook(shape="chamfer")) in grids
    it, im, ir = [20, 80], [5, 10], [8, 40, 90]
    fresh = build_offset_grid(look, em.GRID_THETA_DEG[it], em.GRID_M[im], em.GRID_RHO_PX[ir])
    shipped = grids[em.look_key(look)][np.ix_(it, im, ir)]
    assert np.median(np.abs(fresh - shipped)) < 0.005
    # interpolated offsets: close to the exact ones except near jumps of delta(r)
    for pose in POSES:
        t = OffsetTable(pose.R, pose.t_mm, CAM.K, HOLDER)
        tg = OffsetTable(pose.R, pose.t_mm, CAM.K, HOLDER, tabulated=True)
        assert tg.tabulated and not t.tabulated
        err = np.abs(tg.delta - t.delta)
        assert np.median(err) < 0.005 and np.percentile(err, 90) < 0.03
    # outside the grid (a ring light, a radius beyond it): no grid, the exact model
    v = edge_views(POSES[0].R, POSES[0].t_mm, CAM.K, HOLDER)
    assert tabulated_w_px(np.array([1.0]), v, EdgeLook(ring_radius_mm=40.0)) is None
    assert tabulated_w_px(np.array([20.0]), v, look) is None
