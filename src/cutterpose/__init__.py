"""cutterpose: 6-DOF pose of a shield machine's disc cutter holder from one camera image.

Implements Yang et al.'s monocular method (initial pose from vanishing points and contour area,
refined by distance matching) next to the PnP baselines it is compared with.

Measuring one image (:func:`cutterpose.pipeline.measure`): the pose of the holder in the camera
frame, its std per DOF, and the verdict (``ok``, else the reason it was refused). Here on an
image rendered at a known pose by a quarter-size Table 1 camera (4x larger pixels, so the
verdict refuses the pose: its rotation is not known to the 0.3 deg tolerance):

>>> import numpy as np
>>> from cutterpose import DivisionCamera, Pose, default_camera, default_holder
>>> from cutterpose.pipeline import measure
>>> from cutterpose.render.analytic import render_holder
>>> c = default_camera("table1")
>>> (sx, sy), (cx, cy), (w, h) = c.pixel_size_m, c.principal_point_px, c.image_size_px
>>> camera = DivisionCamera(c.focal_length_m, c.kappa_per_m2, (4 * sx, 4 * sy),
...                         ((cx + 0.5) / 4 - 0.5, (cy + 0.5) / 4 - 0.5), (w // 4, h // 4))
>>> holder = default_holder()
>>> truth = Pose.from_euler(2.0, -1.0, 0.5, 3.0, -4.0, 600.0)   # deg, deg, deg, mm, mm, mm
>>> image = render_holder(truth, camera, holder, "easy", seed=1).image
>>> m = measure(image, camera, holder)
>>> m.ok, m.quality.reason                                       # doctest: +ELLIPSIS
(False, 'error budget: rotation uncertain by ... deg (3 sigma) > 0.3 deg...')
>>> bool(np.all(np.abs(m.pose.dof - truth.dof) < 0.5))          # deg and mm
True
"""

import os as _os

# The solvers work on tiny matrices (<= 840 x 715), where a multi-threaded BLAS only adds
# synchronisation: measured 10-50x slower QR on a busy 2-core machine. Takes effect only when
# numpy is first imported through cutterpose; set the variable yourself to override.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    _os.environ.setdefault(_var, "1")
# OpenCV's decoders refuse an image whose header promises more pixels than this (read once, at
# "import cv2"): the pixel budget of the formats cutterpose.image.header does not read (64 Mpx,
# header.MAX_PIXELS; OpenCV's default is 1 Gpx, 1-8 GB decoded)
if not _os.environ.get("OPENCV_IO_MAX_IMAGE_PIXELS"):
    _os.environ["OPENCV_IO_MAX_IMAGE_PIXELS"] = str(1 << 26)

from .geometry.camera import Camera, DivisionCamera, OpenCVCamera, PinholeCamera, default_camera
from .geometry.camera_files import load_camera, save_camera
from .geometry.holder import Holder, default_holder, load_holder
from .geometry.pose import Pose
from .solvers.estimate import PoseEstimate

__version__ = "0.1.0"

__all__ = ["Camera", "PinholeCamera", "DivisionCamera", "OpenCVCamera", "load_camera",
           "save_camera", "default_camera", "Holder", "load_holder", "default_holder", "Pose",
           "PoseEstimate", "__version__"]
