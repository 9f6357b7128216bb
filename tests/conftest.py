"""Shared fixtures, and the one Hypothesis profile mechanism of the suite.

Hypothesis profiles (select with ``HYPOTHESIS_PROFILE=NAME``; every property test takes its
settings from here and sets only ``max_examples`` and the like itself):

* ``ci`` (the default, and always when ``CI`` is set): ``derandomize=True`` (the examples follow
  from the test's source, so a run in a clean clone sees the same inputs as the last one),
  no example database, no deadline (two shared cores make timings noisy);
* ``explore``: random examples and a local database, for hunting new failures by hand
  (``HYPOTHESIS_PROFILE=explore pytest tests/test_pose.py``); a failure found there is kept as
  an ``@example`` in the test.
* ``fuzz`` (``make fuzz``): as ``explore``, and the fuzz tests of the input readers
  (``tests/test_fuzz_*.py``) run 50 times their CI examples (``fuzz_support.examples``).
"""

import os

import numpy as np
import pytest
from hypothesis import HealthCheck, settings

from cutterpose import default_camera, default_holder

settings.register_profile("ci", derandomize=True, database=None, deadline=None,
                          suppress_health_check=[HealthCheck.too_slow])
settings.register_profile("explore", derandomize=False, deadline=None,
                          suppress_health_check=[HealthCheck.too_slow])
settings.register_profile("fuzz", derandomize=False, deadline=None,
                          suppress_health_check=[HealthCheck.too_slow])
HYPOTHESIS_PROFILE = "ci" if os.environ.get("CI") else os.environ.get("HYPOTHESIS_PROFILE", "ci")
settings.load_profile(HYPOTHESIS_PROFILE)


@pytest.fixture(scope="session")
def cam_syn():
    return default_camera("synthetic")


@pytest.fixture(scope="session")
def cam_t1():
    return default_camera("table1")


@pytest.fixture(scope="session")
def holder():
    return default_holder()


@pytest.fixture
def rng():
    return np.random.default_rng(1234)


@pytest.fixture(scope="session")
def cam_quarter():
    """The Table 1 camera at a quarter of its resolution (4x the pixel pitch, f and kappa in
    metres unchanged): fast images with the same optics."""
    from cutterpose.geometry.camera import DivisionCamera

    full = default_camera("table1")
    return DivisionCamera(full.focal_length_m, full.kappa_per_m2,
                          tuple(np.array(full.pixel_size_m) * 4),
                          tuple((np.array(full.principal_point_px) + 0.5) / 4 - 0.5),
                          (full.image_size_px[0] // 4, full.image_size_px[1] // 4))
