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
