"""The image stage (paper section 2.1 and beyond): image -> region -> contour -> edges -> corners.

Modules, in the order a measurement uses them: :mod:`.preprocessing` (input, checks, median and
threshold), :mod:`.region` (region of interest), :mod:`.contour` (inside contour and its
segmentation), :mod:`.edges` (sub-pixel gradient lines, wear), :mod:`.contour_model` (the
model-guided fallback), :mod:`.corners` (intersections and checks), :mod:`.features` (the chain).
"""

from .features import detect_features
from .params import FeatureParams, Features, Segment
from .preprocessing import as_grey_u8, check_image, load_image

__all__ = ["detect_features", "FeatureParams", "Features", "Segment", "load_image", "as_grey_u8",
           "check_image"]
