"""The failure floor of benchmarks/failure_floor.py: an ideal estimator's failure probability."""

import dataclasses
import importlib.util
from pathlib import Path

import numpy as np

from cutterpose.experiments.synthetic import generate_trials
from cutterpose.geometry.holder import default_holder
from cutterpose.geometry.pose import pose_errors
from cutterpose.methods import get_method

_path = Path(__file__).resolve().parents[1] / "benchmarks" / "failure_floor.py"
_spec = importlib.util.spec_from_file_location("failure_floor", _path)
floor = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(floor)


def _at_sigma(trials, sigma_px):
    return dataclasses.replace(trials, sigma_px=np.full(len(trials), float(sigma_px)))


def test_ideal_failure_probability_grows_with_noise():
    tr = generate_trials(60, 0.0, seed=4)
    p = [floor.ideal_failure_probability(_at_sigma(tr, s), n_samples=2000) for s in (0, 5, 20)]
    assert np.all(p[0] == 0.0)
    assert np.all(p[1] <= p[2] + 0.02) and p[2].mean() > p[1].mean() + 0.05
    assert np.all((p[2] >= 0) & (p[2] <= 1))


def test_ideal_failure_probability_matches_the_ml_estimate():
    # the worst-conditioned poses at a noise where they fail often: the ML estimate's failure
    # rate over repeated noise must agree with the ideal estimator's probability
    tr = generate_trials(200, 0.0, seed=8)
    p5 = floor.ideal_failure_probability(_at_sigma(tr, 5.0), n_samples=1000)
    worst = np.argsort(p5)[-4:]
    sub = _at_sigma(dataclasses.replace(
        tr, points_px=tr.points_px[worst], R_cam_holder=tr.R_cam_holder[worst],
        t_cam_holder_mm=tr.t_cam_holder_mm[worst], shift=tr.shift[worst],
        reverse=tr.reverse[worst]), 8.0)
    p_ideal = floor.ideal_failure_probability(sub, n_samples=4000)
    ml, holder = get_method("opencv-ippe-lm"), default_holder()
    rng = np.random.default_rng(0)
    draws = 300
    for k in range(len(sub)):
        R, t = np.empty((draws, 3, 3)), np.empty((draws, 3))
        for d in range(draws):
            est = ml.solve(sub.points_px[k] + rng.normal(0, 8.0, (20, 2)), sub.camera, holder)
            R[d], t[d] = est.R_cam_holder, est.t_cam_holder_mm
        rate = pose_errors(np.broadcast_to(sub.R_cam_holder[k], R.shape),
                           np.broadcast_to(sub.t_cam_holder_mm[k], t.shape), R, t).failed.mean()
        assert 0.05 < p_ideal[k] < 0.95
        assert abs(rate - p_ideal[k]) < 0.1, (k, rate, p_ideal[k])
