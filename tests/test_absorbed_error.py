"""benchmarks/absorbed_error.py: the absorbed / visible split of design-edge errors."""

import importlib.util
from pathlib import Path

import numpy as np

_path = Path(__file__).resolve().parents[1] / "benchmarks" / "absorbed_error.py"
_spec = importlib.util.spec_from_file_location("absorbed_error", _path)
ae = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(ae)


def _setup(seed=0):
    rng = np.random.default_rng(seed)
    edge = np.repeat(np.arange(20), 4)
    J = rng.normal(size=(80, 6))
    pattern = rng.normal(size=(80, 1))
    return rng, edge, J, pattern


def test_errors_from_the_noise_model_read_about_one():
    rng, edge, J, pattern = _setup()
    vis, abs_ = [], []
    for _ in range(300):
        e = 1.5 * rng.normal(size=80) + 1.0 * rng.normal(size=20)[edge]
        r = ae.energies(e, J, edge, np.column_stack([pattern, pattern]))
        vis.append(r["visible"] / r["exp_visible"])
        abs_.append(r["absorbed"] / r["exp_absorbed"])
    assert 0.9 < np.mean(vis) < 1.1
    assert 0.8 < np.mean(abs_) < 1.25


def test_a_pose_like_error_is_absorbed_and_its_pattern_explains_it():
    rng, edge, J, pattern = _setup(1)
    # an error that is the pattern, which lies mostly in the range of J
    pattern = J @ rng.normal(size=(6, 1)) + 0.1 * rng.normal(size=(80, 1))
    e = rng.normal(size=80) + 5.0 * pattern[:, 0]
    r = ae.energies(e, J, edge, np.column_stack([pattern, rng.normal(size=(80, 1))]))
    assert 0.7 < r["visible"] / r["exp_visible"] < 1.5           # the residuals do not see it
    assert r["absorbed"] / r["exp_absorbed"] > 20
    assert r["absorbed_minus_1"] / r["exp_absorbed_minus_1"] < 3  # the pattern accounts for it
