"""The runnable examples in the public API's docstrings: each module's ``>>>`` examples run
here (doctest), so that a documented call that no longer works fails the tests."""

import doctest
import importlib

import pytest

#: the modules whose docstrings hold examples of the public API
MODULES = [
    "cutterpose",                     # measuring one image (pipeline.measure)
    "cutterpose.geometry.pose",       # Pose
    "cutterpose.geometry.camera",     # default_camera, project, normalize_px
    "cutterpose.geometry.holder",     # default_holder
    "cutterpose.geometry.se3",        # skew, se3_exp, se3_log
    "cutterpose.frames",              # frame_from_buffer
    "cutterpose.tracking.tracker",    # Tracker (its example is skipped: it needs frames)
    "cutterpose.station",             # build_station
    "cutterpose.methods",             # get_method, what a method says of itself
]


@pytest.mark.parametrize("name", MODULES)
def test_docstring_examples_run(name):
    module = importlib.import_module(name)
    result = doctest.testmod(module, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    assert result.failed == 0
    assert result.attempted > 0 or name == "cutterpose.tracking.tracker"
