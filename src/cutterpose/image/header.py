"""An encoded image's size from its header, read before a pixel is decoded.

A 900 KB PNG can hold a 30000 x 30000 image (a "decompression bomb"): decoding it costs 1.9 GB
and seconds before its size can be compared with the camera's. The size is in the first bytes
of the common formats, so it is read there and checked first (:func:`check_header`): the
camera's size when it is known, else a pixel budget (:data:`MAX_PIXELS`).

Read by hand here because the core depends on OpenCV only, whose Python API has no header-only
read (Pillow, which has one, is the service's optional extra); the three layouts are short:

- PNG: the ``IHDR`` chunk right after the signature (ISO/IEC 15948, 11.2.2);
- JPEG: the first start-of-frame marker ``SOFn`` (ITU-T T.81, B.2.2), after any APPn/DQT/...
  segments;
- TIFF and BigTIFF: tags ``ImageWidth`` (256) and ``ImageLength`` (257) of the first IFD
  (TIFF 6.0, section 2; BigTIFF: 8-byte offsets and counts), the page OpenCV decodes.

Every other format OpenCV reads (BMP, PNM, WebP, JPEG 2000, EXR, ...) is bounded by OpenCV's
own header check, ``OPENCV_IO_MAX_IMAGE_PIXELS``, which ``cutterpose`` sets to
:data:`MAX_PIXELS` when it is imported before ``cv2`` (``cutterpose/__init__.py``); its
``cv2.error`` becomes an :class:`~cutterpose.errors.ImageError` in
:func:`cutterpose.image.load_image`.

Convention:
    Sizes ``(width, height)`` in pixels.
"""

from __future__ import annotations

import struct

from ..errors import ImageError

__all__ = ["MAX_PIXELS", "MIN_SIDE_PX", "header_size", "check_header"]

#: the largest image read without a camera to compare with: 64 Mpx (5x the paper's 12-Mpx
#: camera; a 16-bit colour image of this size decodes to 512 MB)
MAX_PIXELS = 1 << 26
#: the smallest side of an image any stage accepts (the region search reduces the image 8x and
#: still needs a few pixels across)
MIN_SIDE_PX = 32

_PNG = b"\x89PNG\r\n\x1a\n"
# SOF0..SOF15 without DHT (C4), JPG (C8) and DAC (CC)
_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}


def _png(data: bytes) -> tuple[int, int]:
    if len(data) < 24 or data[12:16] != b"IHDR":
        raise ImageError("PNG without an IHDR chunk (corrupt file)")
    return struct.unpack(">II", data[16:24])


def _jpeg(data: bytes) -> tuple[int, int]:
    i, n = 2, len(data)
    while i + 4 <= n:
        if data[i] != 0xFF:
            raise ImageError(f"JPEG: no marker at byte {i} (corrupt file)")
        marker = data[i + 1]
        if marker == 0xFF:                      # fill byte
            i += 1
            continue
        if marker in (0x01, 0xD8) or 0xD0 <= marker <= 0xD7:  # no length
            i += 2
            continue
        if marker in (0xD9, 0xDA):              # end of image / start of scan before a frame
            break
        (length,) = struct.unpack(">H", data[i + 2:i + 4])
        if marker in _SOF:
            if i + 9 > n:
                break
            h, w = struct.unpack(">HH", data[i + 5:i + 9])
            if h == 0:
                raise ImageError("JPEG: the height is given after the scan (DNL marker), "
                                 "not read")
            return w, h
        if length < 2:
            raise ImageError(f"JPEG: segment length {length} at byte {i} (corrupt file)")
        i += 2 + length
    raise ImageError("JPEG without a frame header (truncated or corrupt file)")


def _tiff(data: bytes) -> tuple[int, int]:
    end = "<" if data[:2] == b"II" else ">"
    big = struct.unpack(end + "H", data[2:4])[0] == 43
    try:
        if big:
            (ifd,) = struct.unpack(end + "Q", data[8:16])
            (count,) = struct.unpack(end + "Q", data[ifd:ifd + 8])
            start, size, head = ifd + 8, 20, end + "HHQ"
        else:
            (ifd,) = struct.unpack(end + "I", data[4:8])
            (count,) = struct.unpack(end + "H", data[ifd:ifd + 2])
            start, size, head = ifd + 2, 12, end + "HHI"
        found = {}
        for k in range(min(count, 4096)):
            e = start + k * size
            tag, typ, _ = struct.unpack(head, data[e:e + struct.calcsize(head)])
            if tag in (256, 257):
                v = e + struct.calcsize(head)
                fmt = {3: "H", 4: "I", 16: "Q"}.get(typ)
                if fmt is None:
                    raise ImageError(f"TIFF: tag {tag} has type {typ}, not an integer")
                (found[tag],) = struct.unpack(end + fmt, data[v:v + struct.calcsize(fmt)])
    except struct.error:
        raise ImageError("TIFF: the first image directory lies outside the file (truncated "
                         "or corrupt)") from None
    if 256 not in found or 257 not in found:
        raise ImageError("TIFF without ImageWidth / ImageLength in its first directory")
    return found[256], found[257]


def header_size(data: bytes) -> tuple[str, int, int] | None:
    """``(format, width, height)`` from the first bytes of a PNG, JPEG or TIFF file; None for
    any other format.

    Raises
    ------
    ImageError
        The file starts as one of the three but its header is cut or corrupt.
    """
    data = data if isinstance(data, bytes) else bytes(data)
    if data.startswith(_PNG):
        return ("png", *_png(data))
    if data.startswith(b"\xff\xd8\xff"):
        return ("jpeg", *_jpeg(data))
    if data[:4] in (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+"):
        return ("tiff", *_tiff(data))
    return None


def check_header(data: bytes, where: str | None = None,
                 expected_px: tuple[int, int] | None = None,
                 max_pixels: int = MAX_PIXELS) -> tuple[int, int] | None:
    """Refuse from the header alone an image that no stage could use: a side under
    :data:`MIN_SIDE_PX`, more than ``max_pixels``, or not the camera's ``expected_px``.

    Returns
    -------
    ``(width, height)`` from the header, or None when the format has none read here.

    Raises
    ------
    ImageError
        One line (starting with ``where``, a file name, when given): the size found and the
        size wanted.
    """
    found = header_size(data)
    if found is None:
        return None
    fmt, w, h = found
    at = f"{where}: " if where else ""
    if expected_px is not None and (w, h) != tuple(expected_px):
        ew, eh = expected_px
        raise ImageError(f"{at}image is {w} x {h} px but the camera model is for {ew} x "
                         f"{eh} px (wrong camera file, or a resized/cropped image)")
    if min(w, h) < MIN_SIDE_PX:
        raise ImageError(f"{at}image is {w} x {h} px; the measurement needs at least "
                         f"{MIN_SIDE_PX} px on each side")
    if w * h > max_pixels:
        raise ImageError(f"{at}{fmt.upper()} header says {w} x {h} px = {w * h / 1e6:.0f} "
                         f"Mpx, more than the {max_pixels / 1e6:.0f} Mpx read without a camera "
                         "size to compare with (not decoded)")
    return w, h
