"""What the service's worker processes run: image decoding, :func:`cutterpose.pipeline.measure`
and the overlay picture (functions called as ``fn(cell, *args)``, :mod:`.workers`).

Image bodies: PNG, TIFF and JPEG are recognised by their first bytes (which must agree with the
declared content type) and checked for truncation where the format allows it (PNG: ``IEND``
chunk; JPEG: end-of-image marker) before any work is queued (:func:`check_encoded`); the size in
the header must be the camera's before a pixel is decoded (:func:`decode_image`), so a small
file claiming a huge image costs nothing. Raw bodies are 8-bit grey, row-major, ``width x
height`` bytes.

Convention:
    Images are ``uint8`` grey ``(rows, cols)`` (:mod:`cutterpose.image.preprocessing`); sizes
    are ``(width, height)`` in pixels.
"""

from __future__ import annotations

import os
import time

import numpy as np

from ..errors import ImageError
from .config import Cell
from .robot_frame import robot_frame

__all__ = ["FORMATS", "MEDIA_TYPES", "sniff_format", "check_encoded", "decode_image",
           "init_worker", "measure_job", "overlay_job", "ping_job"]

#: content type -> format name
FORMATS = {"image/png": "png", "image/tiff": "tiff", "image/jpeg": "jpeg",
           "application/octet-stream": "raw"}
#: format name -> content type and file extension of a stored image
MEDIA_TYPES = {"png": ("image/png", ".png"), "tiff": ("image/tiff", ".tiff"),
               "jpeg": ("image/jpeg", ".jpg"), "raw": ("application/octet-stream", ".raw")}
_MAGIC = {"png": (b"\x89PNG\r\n\x1a\n",), "jpeg": (b"\xff\xd8\xff",),
          "tiff": (b"II*\x00", b"MM\x00*")}


def sniff_format(data: bytes) -> str | None:
    """``png`` / ``jpeg`` / ``tiff`` from the first bytes, else None."""
    for fmt, heads in _MAGIC.items():
        if any(data.startswith(h) for h in heads):
            return fmt
    return None


def check_encoded(data: bytes, fmt: str) -> None:
    """Cheap checks of an encoded body before it is queued.

    Raises
    ------
    ImageError
        Not the declared format, or visibly truncated.
    """
    found = sniff_format(data)
    if found != fmt:
        what = f"a {found.upper()} image" if found else "not a PNG, TIFF or JPEG image"
        raise ImageError(f"the body is {what} but the content type says {fmt.upper()}")
    # libpng / libjpeg decode a cut file partially (missing rows grey or black) without error
    if fmt == "png" and b"IEND" not in data[-32:]:
        raise ImageError("truncated PNG (no IEND chunk at the end)")
    if fmt == "jpeg" and b"\xff\xd9" not in data[-64:]:
        raise ImageError("truncated JPEG (no end-of-image marker)")


def decode_image(data: bytes, fmt: str, size_px: tuple[int, int] | None,
                 expected_px: tuple[int, int]) -> np.ndarray:
    """The body as an 8-bit grey image of the camera's size.

    Parameters
    ----------
    data : the body.
    fmt : ``png``, ``tiff``, ``jpeg`` or ``raw``.
    size_px : ``(width, height)`` of a raw body (ignored otherwise).
    expected_px : the camera's ``(width, height)``.

    Raises
    ------
    ImageError
        Unreadable, wrong size, or a raw body whose length is not ``width * height``.
    """
    import cv2

    from ..image import as_grey_u8
    from ..image.header import check_header
    from ..image.preprocessing import decode_refusal

    ew, eh = expected_px
    if fmt == "raw":
        w, h = size_px
        if len(data) != w * h:
            raise ImageError(f"raw body has {len(data)} bytes but width x height = {w} x {h} "
                             f"= {w * h} (8-bit grey, one byte per pixel)")
        if (w, h) != (ew, eh):
            raise ImageError(f"image is {w} x {h} px but the camera model is for {ew} x {eh} "
                             "px (wrong camera file, or a resized/cropped image)")
        return np.frombuffer(data, np.uint8).reshape(h, w).copy()
    # the size from the header, before a pixel is decoded (a small file may claim a huge image)
    check_header(data, None, (ew, eh))
    try:
        img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    except cv2.error as e:
        raise ImageError(decode_refusal(e)) from None
    if img is None:
        raise ImageError(f"not a readable {fmt.upper()} image (corrupt or truncated)")
    img = as_grey_u8(img, "image")
    if img.shape != (eh, ew):
        raise ImageError(f"decoded image is {img.shape[1]} x {img.shape[0]} px, expected "
                         f"{ew} x {eh}")
    return img


def init_worker(cell: Cell) -> Cell:
    """Worker initializer: the cell (camera, holders, limits) is loaded once per process; a
    first measurement of a blank image warms the imports and caches."""
    w, h = cell.camera.image_size_px
    try:
        cell.station.measure(np.zeros((h, w), np.uint8))
    except ImageError:
        pass  # a black image is refused: expected, the point was the imports
    return cell


def ping_job(cell: Cell) -> int:
    """The worker's pid (tests and diagnostics)."""
    return os.getpid()


def measure_job(cell: Cell, data: bytes, fmt: str, size_px, holder: str | None,
                flange_row) -> dict:
    """Decode the body, measure, add the robot-frame step.

    Returns
    -------
    dict : ``measurement`` (``Measurement.to_dict()``), ``robot`` (:func:`robot_frame`),
        ``image`` (``width_px``, ``height_px``), ``worker`` (``pid``, ``decode_ms``,
        ``measure_ms``).
    """
    t0 = time.perf_counter()
    img = decode_image(data, fmt, size_px, tuple(cell.camera.image_size_px))
    t1 = time.perf_counter()
    hol = cell.holder(holder)
    m = cell.station.measure(img, holder=hol)
    t2 = time.perf_counter()
    return {"measurement": m.to_dict(), "robot": robot_frame(m, cell, hol, flange_row),
            "image": {"width_px": int(img.shape[1]), "height_px": int(img.shape[0])},
            "worker": {"pid": os.getpid(), "decode_ms": round((t1 - t0) * 1e3, 3),
                       "measure_ms": round((t2 - t1) * 1e3, 3)}}


def overlay_job(cell: Cell, path: str, fmt: str, size_px, holder: str | None,
                width_px: int = 1000) -> bytes:
    """The overlay PNG of a stored image, measured again (the same deterministic pipeline)."""
    import cv2

    from ..overlay import draw_overlay
    with open(path, "rb") as f:
        data = f.read()
    img = decode_image(data, fmt, size_px, tuple(cell.camera.image_size_px))
    hol = cell.holder(holder)
    m = cell.station.measure(img, holder=hol)
    ok, buf = cv2.imencode(".png", draw_overlay(img, m, cell.camera, hol, width_px))
    if not ok:  # pragma: no cover - PNG encoding of a valid BGR image
        raise ImageError("could not encode the overlay")
    return buf.tobytes()
