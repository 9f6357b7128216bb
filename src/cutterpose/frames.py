"""Camera frames as they arrive: raw buffers (as a GigE camera delivers them), arrays, or image
files.

A GigE Vision camera such as the paper's Allied Vision Manta G-1236 hands over each frame as a
buffer of ``width * height`` bytes (pixel format ``Mono8``): no header and nothing to decode. A
raw frame is wrapped as a ``(height, width)`` ``uint8`` array over the same memory
(``np.frombuffer``, no copy) or read from a file in one ``np.fromfile``; a PNG decode of a
12-Mpx frame costs tens of milliseconds, this costs none (bytes) or one read (file).

A camera set to more than 8 bits delivers ``Mono10``, ``Mono12``, ``Mono14`` or ``Mono16``
(two bytes per pixel, little-endian, LSB-aligned) or a packed 12-bit format, ``Mono12Packed``
(GigE Vision: two pixels in three bytes, the first and last byte each a pixel's top 8 bits) or
``Mono12p`` (PFNC: the same three bytes, bits in order from the least significant). Those are
read into the same 8-bit frame: each pixel's top 8 bits (the measurement works on 8-bit grey;
8-bit quantisation, 0.29 grey levels rms, is far below the shot noise of a lit steel face).

Convention:
    A raw frame is row-major, top row first, one byte per pixel (GenICam ``PixelFormat``
    ``Mono8``, the default), exactly ``width * height`` bytes; for the other formats
    :func:`raw_bytes` gives the length (packed formats: an even ``width * height``). Its
    size comes from the caller: ``raw_size`` (the CLI's ``--raw WIDTHxHEIGHT``, its format
    ``--pixel-format``), or a sidecar JSON beside the file, ``<file>.json``
    (``frame_0001.raw.json`` for ``frame_0001.raw``): ``{"width": 4112, "height": 3008,
    "pixel_format": "Mono8"}``; a buffer given to :func:`cutterpose.pipeline.measure` is a frame
    of the camera model's size. Pixels as in :mod:`cutterpose.geometry.camera`.

References:
    GenICam Pixel Format Naming Convention (PFNC) 2.1, ``Mono8`` .. ``Mono16``, ``Mono12p``;
    GigE Vision 2.0, image payload and ``Mono12Packed``.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np

from .errors import ImageError, InputError

__all__ = ["RAW_SUFFIXES", "PIXEL_FORMATS", "parse_raw_size", "raw_bytes", "frame_from_buffer",
           "read_raw", "raw_sidecar", "raw_sidecar_format", "load_frame"]

#: file name endings read as raw frames without ``raw_size`` (then a sidecar gives the size)
RAW_SUFFIXES = (".raw", ".mono8")
#: the raw pixel formats read (lower-case name -> (bytes per two pixels, significant bits))
PIXEL_FORMATS = {"mono8": (2, 8), "mono10": (4, 10), "mono12": (4, 12), "mono14": (4, 14),
                 "mono16": (4, 16), "mono12packed": (3, 12), "mono12p": (3, 12)}
_NAMES = {"mono12packed": "Mono12Packed", "mono12p": "Mono12p"}


def _format(pixel_format: str, where: str = "raw frame") -> str:
    fmt = str(pixel_format).strip().lower()
    if fmt not in PIXEL_FORMATS:
        raise ImageError(f"{where}: pixel format {pixel_format!r} is not read; use one of "
                         "Mono8, Mono10, Mono12, Mono14, Mono16, Mono12Packed, Mono12p")
    return fmt


def raw_bytes(width: int, height: int, pixel_format: str = "Mono8") -> int:
    """The length in bytes of a raw ``width x height`` frame of ``pixel_format``."""
    per_two, _ = PIXEL_FORMATS[_format(pixel_format)]
    return int(width) * int(height) * per_two // 2


def parse_raw_size(spec: str) -> tuple[int, int]:
    """``"4112x3008"`` -> ``(4112, 3008)`` (width, height)."""
    m = re.fullmatch(r"\s*(\d+)\s*[xX*]\s*(\d+)\s*", str(spec))
    if not m or int(m.group(1)) < 1 or int(m.group(2)) < 1:
        raise InputError(f"--raw must be WIDTHxHEIGHT in pixels (e.g. 4112x3008), got {spec!r}")
    return int(m.group(1)), int(m.group(2))


def _check_size(n_bytes: int, width: int, height: int, where: str,
                fmt: str = "mono8") -> None:
    if not all(isinstance(v, int | np.integer) and 1 <= v <= 1 << 20 for v in (width, height)):
        raise ImageError(f"{where}: a raw frame's width and height must be whole numbers from "
                         f"1 to {1 << 20}, got {width!r} x {height!r}")
    n = int(width) * int(height)
    if PIXEL_FORMATS[fmt][0] == 3 and n % 2:
        raise ImageError(f"{where}: a packed 12-bit frame needs an even number of pixels, got "
                         f"{width} x {height}")
    need = raw_bytes(width, height, fmt)
    if n_bytes != need:
        hint = ""
        if fmt == "mono8" and need and n_bytes == 2 * need:
            hint = " (twice that: a 16-bit frame? give its pixel format, e.g. Mono12)"
        elif fmt == "mono8" and need and 2 * n_bytes == 3 * need:
            hint = " (1.5 times that: a packed 12-bit frame? give Mono12Packed or Mono12p)"
        raise ImageError(f"{where}: raw frame has {n_bytes} bytes but {width} x {height} "
                         f"{_NAMES.get(fmt, fmt.capitalize())} needs {need}{hint}")


def _top_bits(flat: np.ndarray, fmt: str) -> np.ndarray:
    """Each pixel's top 8 bits from a flat byte buffer of ``fmt`` (not Mono8)."""
    per_two, bits = PIXEL_FORMATS[fmt]
    if per_two == 4:
        return (flat.view("<u2") >> (bits - 8)).astype(np.uint8)
    b = flat.reshape(-1, 3)
    out = np.empty((len(b), 2), np.uint8)
    if fmt == "mono12packed":           # byte 0: pixel 0's bits 11..4; byte 2: pixel 1's
        out[:, 0] = b[:, 0]
    else:                               # mono12p: pixel 0 = byte 0 + the low nibble of byte 1
        out[:, 0] = (b[:, 0] >> 4) | (b[:, 1] << 4)
    out[:, 1] = b[:, 2]
    return out.reshape(-1)


def frame_from_buffer(buffer, width: int, height: int, where: str = "raw frame",
                      pixel_format: str = "Mono8") -> np.ndarray:
    """A ``(height, width)`` uint8 frame from a raw buffer (bytes, bytearray, memoryview or a
    1-D uint8 array): for ``Mono8`` a view (no copy, no decode), for the wider formats each
    pixel's top 8 bits (module doc).

    Raises
    ------
    ImageError
        An unknown pixel format, or a buffer that is not exactly one frame of it.

    Examples
    --------
    >>> frame_from_buffer(bytes(range(12)), 4, 3)
    array([[ 0,  1,  2,  3],
           [ 4,  5,  6,  7],
           [ 8,  9, 10, 11]], dtype=uint8)
    >>> frame_from_buffer(bytes(range(12)), 5, 3)
    Traceback (most recent call last):
    ...
    cutterpose.errors.ImageError: raw frame: raw frame has 12 bytes but 5 x 3 Mono8 needs 15
    """
    fmt = _format(pixel_format, where)
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
    _check_size(flat.size, width, height, where, fmt)
    if fmt != "mono8":
        flat = _top_bits(flat, fmt)
    return flat.reshape(int(height), int(width))


def raw_sidecar(path) -> tuple[int, int] | None:
    """Width and height from the sidecar ``<file>.json`` of a raw frame, or None if none."""
    found = raw_sidecar_format(path)
    return None if found is None else found[:2]


def raw_sidecar_format(path) -> tuple[int, int, str] | None:
    """Width, height and pixel format (default ``Mono8``) from the sidecar ``<file>.json`` of a
    raw frame, or None if there is none."""
    side = Path(str(path) + ".json")
    if not side.is_file():
        return None
    try:
        doc = json.loads(side.read_text())
        w, h = int(doc["width"]), int(doc["height"])
    except (json.JSONDecodeError, UnicodeDecodeError, KeyError, TypeError, ValueError,
            OverflowError, RecursionError) as e:
        raise ImageError(f"{side}: a raw frame's sidecar needs integer 'width' and 'height' "
                         f"({type(e).__name__}: {e})") from None
    fmt = _format(doc.get("pixel_format", "Mono8"), f"{side}: pixel_format")
    if w < 1 or h < 1:
        raise ImageError(f"{side}: width and height must be positive, got {w} x {h}")
    return w, h, fmt


def read_raw(path, width: int | None = None, height: int | None = None,
             pixel_format: str | None = None) -> np.ndarray:
    """Read a raw frame file (one ``np.fromfile``; Mono8 needs no decode); the size and the
    pixel format are given or taken from its sidecar (format default ``Mono8``).

    Raises
    ------
    ImageError
        Missing file, no size (neither given nor a sidecar), an unknown pixel format or a file
        of the wrong length.
    """
    path = Path(path)
    if not path.is_file():
        raise ImageError(f"{path}: raw frame file not found")
    side = raw_sidecar_format(path) if width is None or height is None or \
        pixel_format is None else None
    if width is None or height is None:
        if side is None:
            raise ImageError(f"{path}: raw frame of unknown size: give --raw WIDTHxHEIGHT or a "
                             f"sidecar {path.name}.json with width and height")
        width, height = side[:2]
    fmt = _format(pixel_format if pixel_format is not None else
                  (side[2] if side is not None else "mono8"), str(path))
    _check_size(path.stat().st_size, width, height, str(path), fmt)
    flat = np.fromfile(path, dtype=np.uint8)
    if fmt != "mono8":
        flat = _top_bits(flat, fmt)
    return flat.reshape(int(height), int(width))


def load_frame(source, camera=None, raw_size: tuple[int, int] | None = None,
               pixel_format: str | None = None) -> np.ndarray:
    """Any frame as an array, decoding only what is encoded.

    Parameters
    ----------
    source : an array (returned as it is); a raw buffer (bytes, bytearray, memoryview) of
        ``raw_size`` or else the camera's size; or a path: a raw frame if ``raw_size`` is given,
        its name ends in :data:`RAW_SUFFIXES` or it has a sidecar, else an image file (PNG,
        TIFF...) decoded by :func:`cutterpose.image.load_image`.
    camera : gives the size of a raw buffer when ``raw_size`` is None.
    pixel_format : of a raw frame (default: its sidecar's, else ``Mono8``).

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
        return frame_from_buffer(source, *raw_size, pixel_format=pixel_format or "Mono8")
    if isinstance(source, (str, Path)):
        path = Path(source)
        if raw_size is not None:
            return read_raw(path, *raw_size, pixel_format=pixel_format)
        if path.suffix.lower() in RAW_SUFFIXES or Path(str(path) + ".json").is_file():
            return read_raw(path, pixel_format=pixel_format)
        from .image import load_image

        # the camera's size is checked from the file's header, before a pixel is decoded
        return load_image(path, tuple(camera.image_size_px) if camera is not None else None)
    raise ImageError(f"expected an image path, an array or a raw buffer, got "
                     f"{type(source).__name__}")
