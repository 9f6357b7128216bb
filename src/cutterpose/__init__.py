"""cutterpose: 6-DOF pose of a shield machine's disc cutter holder from one camera image.

Implements Yang et al.'s monocular method (initial pose from vanishing points and contour area,
refined by distance matching) next to the PnP baselines it is compared with.
"""

from .camera import Camera, DivisionCamera, OpenCVCamera, PinholeCamera, default_camera, load_camera
from .estimate import PoseEstimate
from .holder import Holder, default_holder, load_holder
from .pose import Pose

__version__ = "0.1.0"

__all__ = ["Camera", "PinholeCamera", "DivisionCamera", "OpenCVCamera", "load_camera",
           "default_camera", "Holder", "load_holder", "default_holder", "Pose", "PoseEstimate",
           "__version__"]
