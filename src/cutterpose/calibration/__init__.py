"""Calibration: :mod:`.plate` (the 7 x 7 circle plate: model, detection, rendering) and
:mod:`.intrinsics` (Zhang's method with the division or OpenCV model)."""
