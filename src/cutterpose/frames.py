"""Camera frames as they arrive: raw 8-bit buffers (as a GigE camera delivers them), arrays, or
image files.

A GigE Vision camera such as the paper's Allied Vision Manta G-1236 hands over each frame as a
buffer of ``width * height`` bytes (pixel format ``Mono8``): no header and nothing to decode. A
raw frame is wrapped as a ``(height, width)`` ``uint8`` array over the same memory
(``np.frombuffer``, no copy) or read from a file in one ``np.fromfile``; a PNG decode of a
12-Mpx frame costs tens of milliseconds, this costs none (bytes) or one read (file).

Convention:
    A raw frame is row-major, top row first, one byte per pixel (GenICam ``PixelFormat``
    ``Mono8``), exactly ``width * height`` bytes. Its size comes from the caller: ``raw_size``
    (the CLI's ``--raw WIDTHxHEIGHT``), or a sidecar JSON beside the file, ``<file>.json``
    (``frame_0001.raw.json`` for ``frame_0001.raw``): ``{"width": 4112, "height": 3008,
    "pixel_format": "Mono8"}``; a buffer given to :func:`cutterpose.pipeline.measure` is a frame
    of the camera model's size. Pixels as in :mod:`cutterpose.geometry.camera`.

References:
    GenICam Pixel Format Naming Convention (PFNC) 2.1, ``Mono8``; GigE Vision 2.0, image
    payload.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np

from .errors import ImageError, InputError

__all__ = ["RAW_SUFFIXES", "parse_raw_size", "frame_from_buffer", "read_raw", "raw_sidecar",
           "load_frame"]

#: file name endings read as raw frames without ``raw_size`` (then a sidecar gives the size)
RAW_SUFFIXES = (".raw", ".mono8")


def parse_raw_size(spec: str) -> tuple[int, int]:
    """``"4112x3008"`` -> ``(4112, 3008)`` (width, height)."""
    m = re.fullmatch(r"\s*(\d+)\s*[xX*]\s*(\d+)\s*", str(spec))
    if not m or int(m.group(1)) < 1 or int(m.group(2)) < 1:
        raise InputError(f"--raw must be WIDTHxHEIGHT in pixels (e.g. 4112x3008), got {spec!r}")
    return int(m.group(1)), int(m.group(2))


def _check_size(n_bytes: int, width: int, height: int, where: str) -> None:
    need = int(width) * int(height)
    if n_bytes != need:
        hint = ""
        if need and n_bytes == 2 * need:
            hint = " (twice that: a 16-bit frame? only Mono8 is read raw)"
        raise ImageError(f"{where}: raw frame has {n_bytes} bytes but {width} x {height} Mono8 "
                         f"needs {need}{hint}")


def frame_from_buffer(buffer, width: int, height: int, where: str = "raw frame") -> np.ndarray:
    """A ``(height, width)`` uint8 view of a raw Mono8 buffer (bytes, bytearray, memoryview or a
    1-D uint8 array); no copy, no decode.

    Raises
    ------
    ImageError
        The buffer does not hold exactly ``width * height`` bytes.
    """
    if isinstance(buffer, np.ndarray):
        if buffer.dtype != np.uint8:
            raise ImageError(f"{where}: raw buffer must be uint8, got {buffer.dtype}")
        flat = buffer.reshape(-1)
    else:
        try:
            flat = np.frombuffer(buffer, dtype=np.uint8)
        except TypeError:
            raise ImageError(f"{where}: expected bytes, bytearray or memoryview, got "
                             f"{type(buffer).__name__}") from None
    _check_size(flat.size, width, height, where)
    return flat.reshape(int(height), int(width))


def raw_sidecar(path) -> tuple[int, int] | None:
    """Width and height from the sidecar ``<file>.json`` of a raw frame, or None if none."""
    side = Path(str(path) + ".json")
    if not side.is_file():
        return None
    try:
        doc = json.loads(side.read_text())
        w, h = int(doc["width"]), int(doc["height"])
    except (json.JSONDecodeError, UnicodeDecodeError, KeyError, TypeError, ValueError) as e:
        raise ImageError(f"{side}: a raw frame's sidecar needs integer 'width' and 'height' "
                         f"({type(e).__name__}: {e})") from None
    fmt = str(doc.get("pixel_format", "Mono8"))
    if fmt.lower() != "mono8":
        raise ImageError(f"{side}: pixel_format {fmt!r} is not supported; raw frames must be "
                         "Mono8 (8-bit grey)")
    if w < 1 or h < 1:
        raise ImageError(f"{side}: width and height must be positive, got {w} x {h}")
    return w, h


def read_raw(path, width: int | None = None, height: int | None = None) -> np.ndarray:
    """Read a raw Mono8 frame file (one ``np.fromfile``, no decode); the size is given or
    taken from its sidecar.

    Raises
    ------
    ImageError
        Missing file, no size (neither given nor a sidecar), or a file of the wrong length.
    """
    path = Path(path)
    if not path.is_file():
        raise ImageError(f"{path}: raw frame file not found")
    if width is None or height is None:
        size = raw_sidecar(path)
        if size is None:
            raise ImageError(f"{path}: raw frame of unknown size: give --raw WIDTHxHEIGHT or a "
                             f"sidecar {path.name}.json with width and height")
        width, height = size
    _check_size(path.stat().st_size, width, height, str(path))
    return np.fromfile(path, dtype=np.uint8).reshape(int(height), int(width))


def load_frame(source, camera=None, raw_size: tuple[int, int] | None = None) -> np.ndarray:
    """Any frame as an array, decoding only what is encoded.

    Parameters
    ----------
    source : an array (returned as it is); a raw buffer (bytes, bytearray, memoryview) of
        ``raw_size`` or else the camera's size; or a path: a raw frame if ``raw_size`` is given,
        its name ends in :data:`RAW_SUFFIXES` or it has a sidecar, else an image file (PNG,
        TIFF...) decoded by :func:`cutterpose.image.load_image`.
    camera : gives the size of a raw buffer when ``raw_size`` is None.

    Raises
    ------
    ImageError
        Unreadable file, or a raw frame of the wrong size.
    """
    if isinstance(source, np.ndarray):
        return source
    if isinstance(source, (bytes, bytearray, memoryview)):
        if raw_size is None:
            if camera is None:
                raise InputError("a raw frame buffer needs its size (raw_size or a camera)")
            raw_size = tuple(camera.image_size_px)
        return frame_from_buffer(source, *raw_size)
    if isinstance(source, (str, Path)):
        path = Path(source)
        if raw_size is not None:
            return read_raw(path, *raw_size)
        if path.suffix.lower() in RAW_SUFFIXES or Path(str(path) + ".json").is_file():
            return read_raw(path)
        from .image import load_image

        return load_image(path)
    raise ImageError(f"expected an image path, an array or a raw buffer, got "
                     f"{type(source).__name__}")
