"""Image input and the first filters of section 2.1: reading, grey conversion, sanity checks,
the reduced image, and the 7 x 7 median + global threshold (applied in a band of tiles).

Convention:
    Grey images are ``uint8`` arrays ``(rows, cols)``; pixels as in
    :mod:`cutterpose.geometry.camera`.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ..errors import ImageError
from ..geometry.camera import Camera
from .header import MAX_PIXELS, MIN_SIDE_PX, check_header
from .params import FeatureParams


def load_image(path, expected_px: tuple[int, int] | None = None) -> np.ndarray:
    """Read an image file as 8-bit grey.

    Colour images are converted to grey, 16-bit images scaled to 8 bits. The size is read
    from the file's header and checked before a pixel is decoded
    (:func:`cutterpose.image.header.check_header`): ``expected_px`` (the camera's
    ``(width, height)``) when given, else the pixel budget; a side under 32 px is refused.

    Raises
    ------
    ImageError
        Missing file, a directory, not an image, a truncated/corrupt image, or a size no stage
        can use (from the header, before decoding).
    """
    path = Path(path)
    if not path.exists():
        raise ImageError(f"{path}: image file not found")
    if not path.is_file():
        raise ImageError(f"{path}: not a file")
    try:
        data = np.fromfile(str(path), dtype=np.uint8)
    except OSError as e:
        raise ImageError(f"{path}: cannot be read ({e.strerror or e})") from None
    if data.size == 0:
        raise ImageError(f"{path}: empty file, not an image")
    check_header(data.tobytes(), str(path), expected_px)
    try:
        img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    except cv2.error as e:
        raise ImageError(f"{path}: {decode_refusal(e)}") from None
    if img is None:
        raise ImageError(f"{path}: not a readable image (unknown format, truncated or corrupt)")
    if _png_truncated(data):
        raise ImageError(f"{path}: truncated PNG (no IEND chunk)")
    img = as_grey_u8(img, str(path))
    if min(img.shape) < MIN_SIDE_PX:
        raise ImageError(f"{path}: image is {img.shape[1]} x {img.shape[0]} px; the "
                         f"measurement needs at least {MIN_SIDE_PX} px on each side")
    return img


def decode_refusal(e: Exception) -> str:
    """One line for an OpenCV decoder's exception (its header limits: module
    :mod:`cutterpose.image.header`)."""
    text = " ".join(str(e).split())
    if "MAX_IMAGE" in text:
        return (f"the header promises more than the {MAX_PIXELS / 1e6:.0f} Mpx read "
                "(OPENCV_IO_MAX_IMAGE_PIXELS; not decoded)")
    return f"not decoded ({text[-160:] or 'decoder error'})"


def _png_truncated(data: np.ndarray) -> bool:
    # libpng may decode a cut PNG partially (the missing rows black) without an error.
    is_png = data.size >= 8 and bytes(data[:8]) == b"\x89PNG\r\n\x1a\n"
    return is_png and b"IEND" not in bytes(data[-32:])


#: the bit depths a 16-bit container may hold (Mono10, Mono12, Mono14 and full 16-bit frames)
U16_DEPTHS = (8, 10, 12, 14, 16)


def as_grey_u8(img: np.ndarray, where: str = "image") -> np.ndarray:
    """An image array as contiguous 8-bit grey (colour -> grey, 16 bit / float -> 8 bit).

    A 16-bit array keeps its top 8 significant bits: its depth is the least of
    :data:`U16_DEPTHS` that holds its largest value, so a 12-bit camera's frame saved
    LSB-aligned (0..4095, as GigE Vision's Mono12 and most 16-bit PNG/TIFF writers store it)
    becomes ``v >> 4``, not the near-black ``v >> 8`` a full 16-bit frame needs."""
    a = np.asarray(img)
    if a.ndim == 3 and a.shape[2] in (3, 4):
        a = cv2.cvtColor(a, cv2.COLOR_BGR2GRAY if a.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)
    elif a.ndim == 3 and a.shape[2] == 1:
        a = a[:, :, 0]
    if a.ndim != 2:
        raise ImageError(f"{where}: expected a grey or colour image, got an array of shape "
                         f"{a.shape}")
    if a.dtype == np.uint16:
        top = int(a.max()) if a.size else 0
        bits = next(b for b in U16_DEPTHS if top < (1 << b))
        a = (a >> (bits - 8)).astype(np.uint8)
    elif a.dtype != np.uint8:
        if not np.issubdtype(a.dtype, np.number) or not np.all(np.isfinite(a)):
            raise ImageError(f"{where}: image holds non-numeric or non-finite values")
        hi = 1.0 if a.max() <= 1.0 else 255.0
        a = np.clip(np.rint(a * (255.0 / hi)), 0, 255).astype(np.uint8)
    return np.ascontiguousarray(a)


def check_image(image: np.ndarray, camera: Camera, small: np.ndarray | None = None) -> None:
    """Refuse images that cannot show the holder: wrong size, black, saturated, uniform.

    Raises
    ------
    ImageError
        With the measured statistic in the message.
    """
    check_frame_size(image, camera)
    s = np.ascontiguousarray(small if small is not None else image[::8, ::8])
    # from the grey-level histogram (one pass; the same values as np.percentile)
    counts = cv2.calcHist([s], [0], None, [256], [0, 256]).ravel()
    p01, p50, p99 = percentiles_from_histogram(counts, (1, 50, 99))
    saturated = float(counts[250:].sum() / counts.sum())
    if p99 < 20:
        raise ImageError(f"image is black (99th percentile grey level {p99:.0f}): no light or "
                         "lens cap on")
    if saturated > 0.5:
        raise ImageError(f"image is saturated ({100 * saturated:.0f} % of pixels at "
                         "255): overexposed")
    if p99 - p01 < 10:
        raise ImageError(f"image is nearly uniform (grey levels {p01:.0f}..{p99:.0f}): "
                         "nothing to measure")


def check_frame_size(image: np.ndarray, camera: Camera) -> None:
    """Refuse an image that is not the camera's size, or too small for any stage (a side under
    :data:`~cutterpose.image.header.MIN_SIDE_PX`), before any filter runs on it.

    Raises
    ------
    ImageError
        The sizes found and wanted, in one line.
    """
    h, w = np.shape(image)[:2]
    if (w, h) != tuple(camera.image_size_px):
        cw, ch = camera.image_size_px
        raise ImageError(f"image is {w} x {h} px but the camera model is for {cw} x {ch} px "
                         "(wrong camera file, or a resized/cropped image)")
    if min(w, h) < MIN_SIDE_PX:
        raise ImageError(f"image is {w} x {h} px; the measurement needs at least "
                         f"{MIN_SIDE_PX} px on each side")


def percentiles_from_histogram(counts: np.ndarray, q) -> list[float]:
    """Percentiles ``q`` (0..100) of integer data given its histogram ``counts`` (value ``v``
    occurs ``counts[v]`` times), with ``np.percentile``'s default linear interpolation between
    the order statistics."""
    cum = np.cumsum(counts)
    n = int(cum[-1])
    out = []
    for qq in q:
        pos = qq / 100.0 * (n - 1)
        lo = int(np.floor(pos))
        hi = min(lo + 1, n - 1)
        v_lo = float(np.searchsorted(cum, lo, side="right"))
        v_hi = float(np.searchsorted(cum, hi, side="right"))
        out.append(v_lo + (v_hi - v_lo) * (pos - lo))
    return out


def reduce_image(image: np.ndarray, factor: int) -> np.ndarray:
    """Area-averaged reduction by an integer factor (the image for the ROI search)."""
    if factor <= 1:
        return image
    h, w = image.shape
    if w // factor < 1 or h // factor < 1:
        raise ImageError(f"image is {w} x {h} px, too small to reduce {factor}x (at least "
                         f"{MIN_SIDE_PX} px on each side)")
    return cv2.resize(image, (w // factor, h // factor), interpolation=cv2.INTER_AREA)


def binarize(sub: np.ndarray, small_sub: np.ndarray, level: int, params: FeatureParams
             ) -> np.ndarray:
    """Median filter and global threshold of the ROI: grey in ``[level, threshold_high]`` -> 255.

    With ``band_only`` the ROI is cut in tiles of ``tile_px``; the reduced image (each pixel the
    mean of ``roi_downscale^2`` pixels) is thresholded first, and only tiles where that coarse
    binary changes within one reduced pixel are median-filtered and thresholded at full
    resolution; the others take the coarse value. The pocket's interior and the face far from
    its edge never reach the 7 x 7 median, which is what makes 12 Mpx frames fast.
    """
    k, lo, hi = params.median_ksize, level, params.threshold_high
    if not params.band_only or params.roi_downscale <= 1:
        med = cv2.medianBlur(sub, k) if k > 1 else sub
        return cv2.inRange(med, lo, hi)
    s = params.roi_downscale
    T = max(s, (params.tile_px // s) * s)
    b = T // s
    H, W = sub.shape
    ny, nx = -(-H // T), -(-W // T)
    # coarse binary padded to whole tiles; a missing border strip counts as mixed
    cb = np.full((ny * b, nx * b), 127, np.uint8)
    cs = small_sub[: ny * b, : nx * b]
    cb[: cs.shape[0], : cs.shape[1]] = np.where((cs >= lo) & (cs <= hi), 255, 0)
    kernel = np.ones((3, 3), np.uint8)
    mixed_small = cv2.dilate(cb, kernel) != cv2.erode(cb, kernel)
    mixed = mixed_small.reshape(ny, b, nx, b).any(axis=(1, 3))
    value = (cb.reshape(ny, b, nx, b).mean(axis=(1, 3)) > 127).astype(np.uint8) * 255
    binary = np.repeat(np.repeat(value, T, axis=0), T, axis=1)[:H, :W].copy()
    r = k // 2
    for i, j in zip(*np.nonzero(mixed)):
        y0, x0 = i * T, j * T
        y1, x1 = min(y0 + T, H), min(x0 + T, W)
        py0, px0 = max(y0 - r, 0), max(x0 - r, 0)
        py1, px1 = min(y1 + r, H), min(x1 + r, W)
        tile = sub[py0:py1, px0:px1]
        med = cv2.medianBlur(tile, k) if k > 1 else tile
        binary[y0:y1, x0:x1] = cv2.inRange(med[y0 - py0: y1 - py0, x0 - px0: x1 - px0], lo, hi)
    return binary
