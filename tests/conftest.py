import numpy as np
import pytest

from cutterpose import default_camera, default_holder


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
