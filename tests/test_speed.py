"""Speed work of issue 13: the vectorised pieces give what the plain formulas give.

The batched sampler against per-point bilinear interpolation through the exact distortion, the
batched Tukey IRLS against one line at a time, the FFT template correlation against
``cv2.matchTemplate``, the row smoothing against SciPy, the per-group medians against
``np.median``, and dm+ from a close start against the full dm+.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.ndimage import gaussian_filter1d

from cutterpose.geometry.camera import default_camera
from cutterpose.geometry.holder import default_holder
from cutterpose.geometry.pose import Pose, geodesic_deg
from cutterpose.geometry.working_range import MotionRange
from cutterpose.image import FeatureParams
from cutterpose.image.edges import group_median, sample_profiles, smooth_rows
from cutterpose.image.lines import lmeds_line, lmeds_lines, median_rows, tukey_line, tukey_lines
from cutterpose.image.region import _outline_template, correlate_templates
from cutterpose.solvers import matching


def _smooth_image(h: int, w: int) -> np.ndarray:
    v, u = np.mgrid[0:h, 0:w].astype(float)
    return (100 + 60 * np.sin(u / 37.0) * np.cos(v / 23.0)).astype(np.float32)


def _bilinear(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Plain bilinear interpolation at (..., 2) pixel positions (inside the image)."""
    u, v = uv[..., 0], uv[..., 1]
    u0, v0 = np.floor(u).astype(int), np.floor(v).astype(int)
    fu, fv = u - u0, v - v0
    a = img.astype(float)
    return ((1 - fu) * (1 - fv) * a[v0, u0] + fu * (1 - fv) * a[v0, u0 + 1]
            + (1 - fu) * fv * a[v0 + 1, u0] + fu * fv * a[v0 + 1, u0 + 1])


def test_vectorised_sampler_equals_the_plain_formula():
    """All 20 edges' profiles in one call = per point ``I(distort(q + o n))`` bilinear
    (exact distortion, no remap): within the remap's 1/32 px position quantisation (the
    image's slope is <= 3 DN/px, so <= 0.05 DN), on a signal that varies by ~100 DN; and
    bit for bit the same as one call per edge."""
    cam = default_camera("table1")             # division model: the profiles are bent
    hol = default_holder()
    img = _smooth_image(1400, 2000)
    origin = np.array([1100.0, 800.0])
    pose = Pose.from_euler(4, -6, 7, 12, -9, 605)
    R, t = pose.R, pose.t_mm
    X = hol.points_holder_mm @ R.T + t
    ideal = (X @ cam.K.T)[:, :2] / (X @ cam.K.T)[:, 2:3]
    nxt = np.roll(ideal, -1, axis=0)
    d = (nxt - ideal) / np.linalg.norm(nxt - ideal, axis=1, keepdims=True)
    n_out = np.column_stack([d[:, 1], -d[:, 0]])
    offsets = np.arange(-6.0, 6.0 + 1e-9, 0.25)
    bases, normals, which = [], [], []
    for k in range(len(ideal)):
        ts = np.arange(10.0, np.linalg.norm(nxt[k] - ideal[k]) - 10.0, 7.0)
        bases.append(ideal[k] + ts[:, None] * d[k])
        normals.append(np.repeat(n_out[k][None], len(ts), axis=0))
        which.append(np.full(len(ts), k))
    base, nrm, which = np.vstack(bases), np.vstack(normals), np.concatenate(which)
    prof = sample_profiles(img, origin, cam, base, nrm, offsets)
    assert prof.shape == (len(base), len(offsets))
    q = base[:, None, :] + offsets[None, :, None] * nrm[:, None, :]
    plain = _bilinear(img, cam.distort_px(q.reshape(-1, 2)).reshape(q.shape) - origin)
    assert np.ptp(plain) > 80.0
    assert np.abs(prof - plain).max() < 0.05
    for k in range(len(ideal)):
        one = sample_profiles(img, origin, cam, base[which == k], nrm[which == k], offsets)
        assert np.array_equal(one, prof[which == k])


def test_batched_tukey_lines_equal_one_line_at_a_time():
    rng = np.random.default_rng(5)
    pts, starts, scales = [], [], []
    for k in range(12):
        n = int(rng.integers(40, 900))
        a = rng.uniform(0, np.pi)
        d = np.array([np.cos(a), np.sin(a)])
        nn = np.array([-d[1], d[0]])
        t = rng.uniform(0, 800, n)
        p = t[:, None] * d + rng.normal(0, 0.1, (n, 1)) * nn + 300.0
        bad = rng.random(n) < 0.25                         # a quarter on a "lump"
        p[bad] += rng.uniform(1.0, 6.0, (bad.sum(), 1)) * nn
        L0, s0 = lmeds_line(p, seed=k)
        pts.append(p)
        starts.append(L0)
        scales.append(s0)
    L, s, w = tukey_lines(pts, np.array(starts), np.array(scales))
    for k, p in enumerate(pts):
        L1, s1, w1 = tukey_line(p, starts[k], scales[k])
        assert np.allclose(L[k], L1, atol=1e-9, rtol=0)
        assert s[k] == pytest.approx(s1, rel=1e-8)
        assert np.allclose(w[k], w1, atol=1e-9)


def test_seeded_pairs_are_the_seeded_generators_first_draws():
    """LMedS's hypotheses: the cached, restored generator draws what a fresh
    ``default_rng(seed)`` draws, every time and in any order of seeds."""
    from cutterpose.image.lines import _seeded_pairs

    for seed, n, h in [(0, 900, 64), (7, 5, 64), (3, 10 ** 6, 16), (0, 900, 64), (7, 6, 64)]:
        rng = np.random.default_rng(seed)
        ref = np.stack([rng.integers(0, n, h), rng.integers(0, n, h)])
        np.testing.assert_array_equal(_seeded_pairs(seed, n, h), ref)


def test_group_and_row_medians_equal_numpy():
    rng = np.random.default_rng(2)
    v = rng.normal(size=1001).astype(np.float32)
    g = rng.integers(0, 7, 1001)
    g[g == 3] = 4                                          # an empty group
    med = group_median(v, g, 7)
    for k in range(7):
        if k == 3:
            assert np.isnan(med[k])
        else:
            assert med[k] == np.median(v[g == k])
    a = rng.normal(size=(9, 64))
    assert np.array_equal(median_rows(a), np.median(a, axis=1))
    assert np.array_equal(median_rows(a[:, :63]), np.median(a[:, :63], axis=1))


@pytest.mark.parametrize("sigma", [0.8, 1.6, 3.2, 3.33])
def test_row_smoothing_equals_scipy(sigma):
    a = (np.random.default_rng(1).random((300, 49)) * 200).astype(np.float32)
    assert np.abs(smooth_rows(a, sigma) - gaussian_filter1d(a, sigma, axis=1)).max() < 1e-3


def test_fft_template_correlation_equals_match_template():
    cam, hol = default_camera("table1"), default_holder()
    rng = np.random.default_rng(4)
    image = rng.normal(size=(188, 257, 2)).astype(np.float32)
    tpls = [_outline_template(cam, hol, 16, g, 2)[0] for g in (-9.0, 0.0, 6.0)]
    for t, r in zip(tpls, correlate_templates(image, tpls)):
        ref = cv2.matchTemplate(image, t, cv2.TM_CCORR)
        assert r.shape == ref.shape
        assert np.abs(r - ref).max() < 1e-4 * np.abs(ref).max()
        assert cv2.minMaxLoc(r)[3] == cv2.minMaxLoc(ref)[3]


def test_dm_plus_from_a_close_start_is_the_full_dm_plus():
    """From a start 0.5 deg / 2 mm off (an outline homography is closer) the refinement alone
    ends where the full dm+ (coarse-to-fine grid, then the refinement) ends; from a start far
    off it says it did not converge instead of returning a wrong pose."""
    cam, hol = default_camera("table1"), default_holder()
    rng = np.random.default_rng(8)
    truth = Pose.from_euler(3, -5, 4, 9, -7, 612)
    corners = cam.project(truth.apply(hol.points_holder_mm)) + rng.normal(0, 0.2, (20, 2))
    rng_box = MotionRange(center_dof=(0, 0, 0, 0, 0, 600), half_width_dof=(10, 10, 10, 20, 20, 20))
    start = Pose.from_euler(3.5, -4.5, 4.5, 11, -5, 614)
    close = matching.refine_from_close_start(corners, cam, hol, (start.R, start.t_mm),
                                             motion_range=rng_box)
    full = matching.distance_match(corners, cam, hol, (start.R, start.t_mm),
                                   motion_range=rng_box, refine=True)
    assert close and full
    assert geodesic_deg(close.R_cam_holder, full.R_cam_holder) < 1e-6
    assert np.abs(close.t_cam_holder_mm - full.t_cam_holder_mm).max() < 1e-5
    # corners that do not fit the holder (5 px noise): refused with the reason, not returned
    bad_corners = corners + rng.normal(0, 5.0, corners.shape)
    bad = matching.refine_from_close_start(bad_corners, cam, hol, (start.R, start.t_mm),
                                           motion_range=rng_box, max_rms_px=1.5)
    assert not bad and "did not converge" in bad.reason


def test_field_params_unchanged_by_the_speed_work():
    """The speed work changed no parameter of the field chain (its accuracy rests on them)."""
    p = FeatureParams()
    assert (p.refine_step_px, p.refine_half_width_px, p.search_gates_px, p.search_step_px) == \
        (1.0, 6.0, (40.0, 14.0, 6.0), 10.0)


def test_percentiles_from_the_histogram_equal_numpy():
    from cutterpose.image.preprocessing import percentiles_from_histogram
    from cutterpose.image.region import _percentile

    rng = np.random.default_rng(0)
    for n in (7, 1001, 50_000):
        a = rng.integers(0, 256, n).astype(np.uint8)
        got = percentiles_from_histogram(np.bincount(a, minlength=256), (1, 50, 90, 99))
        assert np.allclose(got, np.percentile(a, [1, 50, 90, 99]), atol=1e-9, rtol=0)
        f = rng.random(n).astype(np.float32)
        assert _percentile(f, 90.0) == pytest.approx(float(np.percentile(f, 90)), abs=1e-7)


def test_batched_lmeds_equals_one_set_at_a_time():
    """Same random pairs per set, the prior first, the same gate: the same line and scale."""
    rng = np.random.default_rng(6)
    sets, priors, gates = [], [], []
    for _k in range(9):
        n = int(rng.integers(30, 1200))                  # short sets and ranked long ones
        a = rng.uniform(0, np.pi)
        d, nn = np.array([np.cos(a), np.sin(a)]), np.array([-np.sin(a), np.cos(a)])
        t = rng.uniform(0, n, n)
        p = t[:, None] * d + rng.normal(0, 0.15, (n, 1)) * nn
        p[rng.random(n) < 0.3] += 4.0 * nn               # 30 % outliers
        sets.append(p)
        priors.append(np.array([nn[0], nn[1], -0.5]))
        gates.append(np.array([0.0 * d, n * d]))
    L, s = lmeds_lines(sets, priors=priors, seeds=range(9), gate_points=gates, gate_px=2.5)
    for k, p in enumerate(sets):
        L1, s1 = lmeds_line(p, prior=priors[k], seed=k, gate_points=gates[k], gate_px=2.5)
        assert np.allclose(L[k], L1, atol=1e-12) and s[k] == pytest.approx(s1, rel=1e-12)
        assert np.median(np.abs(p @ L[k][:2] + L[k][2])) < 0.3   # on the inliers' line


def test_outline_caches_forget_the_least_recently_used_entry():
    """An approach's outline search uses 45 coarse templates at every full measurement and a
    few fine ones per frame; a cache cleared whole when full (as before) rebuilt all of them
    about every other fall-back (~190 ms). The caches keep the recent entries instead, and
    :func:`prepare_outline_search` builds the coarse ones ahead (a tracker's worker)."""
    from cutterpose.image.region import (
        _OUTLINE_CACHE,
        _SPECTRUM_CACHE,
        _coarse_templates,
        _Recent,
        prepare_outline_search,
    )
    from cutterpose.tracking import approach_params

    c = _Recent(3)
    for k in "abc":
        c.keep(k, k.upper())
    assert c.recall("a") == "A"          # used: "b" is now the oldest
    c.keep("d", "D")
    assert list(c) == ["c", "a", "d"] and c.recall("b") is None
    cam, hol = default_camera("table1"), default_holder()
    params = approach_params(cam)
    _OUTLINE_CACHE.clear()
    _SPECTRUM_CACHE.clear()
    prepare_outline_search(cam, hol, params)
    gd, tpls = _coarse_templates(cam, hol, params)
    n = len(params.roi_depths_mm) * len(params.roi_gammas_deg)
    assert len(gd) == n == len(_OUTLINE_CACHE) == len(_SPECTRUM_CACHE) and n > 40
    # built once: the same objects again
    assert all(a is b for a, b in zip(tpls, _coarse_templates(cam, hol, params)[1]))
