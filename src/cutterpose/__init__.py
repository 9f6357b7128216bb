"""cutterpose: 6-DOF pose of a shield machine's disc cutter holder from one camera image.

Implements Yang et al.'s monocular method (initial pose from vanishing points and contour area,
refined by distance matching) next to the PnP baselines it is compared with.
"""

import os as _os

# The solvers work on tiny matrices (<= 840 x 715), where a multi-threaded BLAS only adds
# synchronisation: measured 10-50x slower QR on a busy 2-core machine. Takes effect only when
# numpy is first imported through cutterpose; set the variable yourself to override.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    _os.environ.setdefault(_var, "1")

from .geometry.camera import Camera, DivisionCamera, OpenCVCamera, PinholeCamera, default_camera
from .geometry.camera_files import load_camera, save_camera
from .geometry.holder import Holder, default_holder, load_holder
from .geometry.pose import Pose
from .solvers.estimate import PoseEstimate

__version__ = "0.1.0"

__all__ = ["Camera", "PinholeCamera", "DivisionCamera", "OpenCVCamera", "load_camera",
           "save_camera", "default_camera", "Holder", "load_holder", "default_holder", "Pose",
           "PoseEstimate", "__version__"]
