"""Fuzz tests of every image and frame reader (issue 32): random bytes, valid files of every
format, depth and channel count truncated or corrupted, headers claiming extreme sizes, raw
frames of every pixel format with wrong sizes and sidecars. The property
(:mod:`fuzz_support`): a grey uint8 frame or a one-line typed error, within its time, memory
bounded."""

import json
import struct
import tempfile
import zlib
from pathlib import Path

import cv2
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from cutterpose.errors import ImageError, InputError
from cutterpose.frames import PIXEL_FORMATS, frame_from_buffer, parse_raw_size, read_raw
from cutterpose.geometry.camera import PinholeCamera
from cutterpose.image import load_image
from cutterpose.image.header import MIN_SIDE_PX, check_header, header_size
from cutterpose.service.jobs import check_encoded, decode_image, sniff_format
from fuzz_support import MemoryBound, examples, json_trees, mutated, mutated_bytes, typed_or_valid

TMP = Path(tempfile.mkdtemp(prefix="cutterpose-fuzz-images-"))
EXTS = [".png", ".jpg", ".tiff", ".bmp", ".webp", ".pgm"]


def _check_frame(out, where):
    if isinstance(out, ImageError | InputError):
        return
    assert isinstance(out, np.ndarray) and out.dtype == np.uint8 and out.ndim == 2, where
    assert min(out.shape) >= MIN_SIDE_PX, (where, out.shape)


@st.composite
def encoded(draw):
    """A valid image file's bytes: any format OpenCV writes, 1/3/4 channels, 8/16-bit."""
    ext = draw(st.sampled_from(EXTS))
    depth = np.uint16 if ext in (".png", ".tiff") and draw(st.booleans()) else np.uint8
    ch = draw(st.sampled_from([1, 3] if ext in (".jpg", ".pgm") else [1, 3, 4]))
    if ext == ".pgm":
        ch = 1
    h, w = draw(st.integers(1, 70)), draw(st.integers(1, 70))
    rng = np.random.default_rng(draw(st.integers(0, 2 ** 32 - 1)))
    a = rng.integers(0, np.iinfo(depth).max, (h, w, ch) if ch > 1 else (h, w)).astype(depth)
    ok, buf = cv2.imencode(ext, a)
    assert ok
    return ext, buf.tobytes()


def _load(data: bytes, ext: str, expected=None):
    path = TMP / f"img{ext}"
    path.write_bytes(data)
    return typed_or_valid(load_image, path, expected)


@settings(max_examples=examples(60))
@given(data=st.binary(max_size=4096), ext=st.sampled_from(EXTS + [".raw.png", ""]))
def test_random_bytes(data, ext):
    with MemoryBound():
        _check_frame(_load(data, ext), data[:16])
        out = typed_or_valid(header_size, data)
        assert out is None or isinstance(out, ImageError | tuple)


@settings(max_examples=examples(80))
@given(enc=encoded(), data=st.data())
def test_valid_files_truncated_or_corrupted(enc, data):
    ext, good = enc
    bad = data.draw(mutated_bytes(good))
    with MemoryBound():
        _check_frame(_load(good, ext), ext)
        _check_frame(_load(bad, ext), ext)
        fmt = sniff_format(bad)
        if fmt is not None:    # the service's checks, then its decode for a 64 x 48 camera
            err = typed_or_valid(check_encoded, bad, fmt)
            if not isinstance(err, ImageError):
                _check_frame(typed_or_valid(decode_image, bad, fmt, None, (64, 48)), fmt)


def _chunk(t: bytes, d: bytes) -> bytes:
    return struct.pack(">I", len(d)) + t + d + struct.pack(">I", zlib.crc32(t + d))


@st.composite
def extreme_headers(draw):
    """PNG / JPEG / TIFF files whose header claims any size, depth or layout, with a little
    compressed data after it."""
    w, h = (draw(st.one_of(st.integers(0, 64), st.integers(0, 2 ** 32 - 1))) for _ in "wh")
    kind = draw(st.sampled_from(["png", "jpeg", "tiff"]))
    if kind == "png":
        depth = draw(st.sampled_from([1, 2, 4, 8, 16, 0, 3, 255]))
        colour = draw(st.sampled_from([0, 2, 3, 4, 6, 1, 7]))
        ihdr = struct.pack(">IIBBBBB", w, h, depth, colour, 0, 0, 0)
        z = zlib.compress(bytes(draw(st.integers(0, 5000))))
        return (b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", ihdr) + _chunk(b"IDAT", z)
                + _chunk(b"IEND", b""))
    if kind == "jpeg":
        ok, buf = cv2.imencode(".jpg", np.zeros((16, 16), np.uint8))
        b = bytearray(buf.tobytes())
        i = b.index(b"\xff\xc0")
        b[i + 5:i + 9] = struct.pack(">HH", h % 65536, w % 65536)
        return bytes(b)
    ok, buf = cv2.imencode(".tiff", np.zeros((16, 16), np.uint8))
    b = bytearray(buf.tobytes())
    ifd = struct.unpack("<I", b[4:8])[0]
    n = struct.unpack("<H", b[ifd:ifd + 2])[0]
    for k in range(n):
        e = ifd + 2 + 12 * k
        tag = struct.unpack("<H", b[e:e + 2])[0]
        if tag in (256, 257, 258, 277):
            v = {256: w, 257: h}.get(tag, draw(st.integers(0, 2 ** 32 - 1)))
            b[e + 2:e + 12] = struct.pack("<HII", 4, 1, v)
    return bytes(b)


@settings(max_examples=examples(60))
@given(data=extreme_headers())
def test_headers_claiming_extreme_sizes_are_refused_before_decoding(data):
    with MemoryBound():
        out = _load(data, ".img")
        _check_frame(out, data[:32])
        size = typed_or_valid(check_header, data)
        if isinstance(size, tuple):      # passed the header: small enough to decode
            assert size[0] * size[1] <= 1 << 26


@settings(max_examples=examples(80))
@given(w=st.one_of(st.integers(-3, 80), st.integers(-2 ** 40, 2 ** 40)),
       h=st.one_of(st.integers(-3, 80), st.integers(-2 ** 40, 2 ** 40)),
       n=st.integers(0, 20000), fmt=st.sampled_from(sorted(PIXEL_FORMATS) + ["Mono9", "", "x"]))
def test_raw_buffers_of_every_pixel_format(w, h, n, fmt):
    buf = bytes(np.random.default_rng(n).integers(0, 256, n, dtype=np.uint8))
    with MemoryBound():
        out = typed_or_valid(frame_from_buffer, buf, w, h, pixel_format=fmt)
        if isinstance(out, np.ndarray):
            assert out.shape == (h, w) and out.dtype == np.uint8


@settings(max_examples=examples(60))
@given(side=st.one_of(mutated({"width": 40, "height": 32, "pixel_format": "Mono12p"}),
                      json_trees), n=st.integers(0, 4000), as_text=st.booleans())
def test_raw_files_with_any_sidecar(side, n, as_text):
    path = TMP / "frame.raw"
    path.write_bytes(bytes(n))
    Path(str(path) + ".json").write_text(json.dumps(side) if not as_text else str(side))
    with MemoryBound():
        out = typed_or_valid(read_raw, path)
        if isinstance(out, np.ndarray):
            assert out.dtype == np.uint8 and out.ndim == 2


@settings(max_examples=examples(60))
@given(spec=st.one_of(st.text(max_size=30), st.from_regex(r"\s*-?\d{1,30}\s*[xX*]\s*-?\d{1,30}")))
def test_raw_size_specs(spec):
    out = typed_or_valid(parse_raw_size, spec)
    if isinstance(out, tuple):
        assert all(isinstance(v, int) and v >= 1 for v in out)


def test_load_frame_checks_the_camera_size_from_the_header():
    """A camera-sized check before decoding: the header's size against the camera's."""
    cam = PinholeCamera(100, 100, 31.5, 23.5, (64, 48))
    ok, buf = cv2.imencode(".png", np.zeros((48, 64), np.uint8))
    assert _load(buf.tobytes(), ".png", cam.image_size_px).shape == (48, 64)
    err = _load(buf.tobytes(), ".png", (65, 48))
    assert isinstance(err, ImageError) and "64 x 48 px but the camera" in str(err)
