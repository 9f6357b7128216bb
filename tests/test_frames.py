"""Raw 8-bit frames (issue 13, item 1): measured without any decode, wrong sizes refused."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from cutterpose.cli import app
from cutterpose.errors import ImageError, InputError
from cutterpose.frames import frame_from_buffer, load_frame, parse_raw_size, read_raw
from cutterpose.geometry.camera_files import save_camera
from cutterpose.geometry.holder import default_holder
from cutterpose.geometry.pose import Pose
from cutterpose.pipeline import QualityLimits, measure
from cutterpose.render.analytic import render_holder
from test_features import small_camera

runner = CliRunner()
CAM = small_camera()
SHARP = QualityLimits(edge_break_mm=0.0)


@pytest.fixture(scope="module")
def frame(tmp_path_factory):
    d = tmp_path_factory.mktemp("raw")
    img = render_holder(Pose.from_euler(2, -1, 3, 5, -4, 607), CAM, default_holder(), "easy",
                        seed=4).image
    h, w = img.shape
    cv2.imwrite(str(d / "f.png"), img)
    (d / "f.raw").write_bytes(img.tobytes())
    (d / "f.raw.json").write_text(json.dumps({"width": w, "height": h,
                                              "pixel_format": "Mono8"}))
    (d / "nosidecar.bin").write_bytes(img.tobytes())
    (d / "short.raw").write_bytes(img.tobytes()[:-1])
    save_camera(CAM, d / "cam.json")
    return d, img


def test_buffer_is_viewed_not_copied_or_decoded(frame):
    _, img = frame
    h, w = img.shape
    buf = bytearray(img.tobytes())
    a = frame_from_buffer(buf, w, h)
    assert a.shape == (h, w) and a.dtype == np.uint8
    assert np.shares_memory(a, np.frombuffer(buf, np.uint8))
    np.testing.assert_array_equal(a, img)


def test_measure_on_bytes_equals_measure_on_png(frame):
    d, img = frame
    # the reduced test camera cannot resolve a broken edge's band: the corner method
    # (and the analytic renderer's edge is sharp: declared, no break in the verdict)
    m_png = measure(d / "f.png", CAM, method="dm+", limits=SHARP)
    m_raw = measure(img.tobytes(), CAM, method="dm+", limits=SHARP)  # of the camera's size
    m_file = measure(d / "f.raw", CAM, method="dm+", limits=SHARP)   # size from the sidecar
    assert m_png.ok, m_png.quality.reason
    for m in (m_raw, m_file):
        assert m.ok
        np.testing.assert_array_equal(m.pose.dof, m_png.pose.dof)


def test_wrong_sizes_are_typed_errors(frame):
    d, img = frame
    h, w = img.shape
    with pytest.raises(ImageError, match="needs"):
        frame_from_buffer(img.tobytes(), w + 1, h)
    with pytest.raises(ImageError, match="16-bit"):
        frame_from_buffer(img.astype(np.uint16).tobytes(), w, h)
    with pytest.raises(ImageError, match="bytes but"):
        measure(img.tobytes()[:-10], CAM)
    with pytest.raises(ImageError, match="bytes but"):
        read_raw(d / "short.raw", w, h)
    with pytest.raises(ImageError, match="unknown size"):
        load_frame(d / "short.raw")
    with pytest.raises(InputError):
        parse_raw_size("4112 by 3008")
    assert parse_raw_size("4112x3008") == (4112, 3008)


def test_cli_measure_raw(frame):
    d, img = frame
    h, w = img.shape
    r = runner.invoke(app, ["measure", str(d / "nosidecar.bin"), "--raw", f"{w}x{h}",
                            "--camera", str(d / "cam.json"), "--json", "--method", "dm+",
                            "--edge-break-mm", "0"])
    assert r.exit_code == 0, r.output
    got = json.loads(r.output)
    ref = measure(d / "f.png", CAM, method="dm+", limits=SHARP)
    dof = [got["pose"][k] for k in ("alpha_deg", "beta_deg", "gamma_deg", "X_mm", "Y_mm",
                                     "Z_mm")]
    np.testing.assert_allclose(dof, ref.pose.dof, rtol=0, atol=1e-9)
    assert "load" in got["timings_ms"]
    r = runner.invoke(app, ["measure", str(d / "f.raw"), "--camera", str(d / "cam.json"),
                            "--method", "dm+", "--edge-break-mm", "0"])
    assert r.exit_code == 0, r.output
    r = runner.invoke(app, ["measure", str(d / "nosidecar.bin"), "--raw", f"{w}x{h + 1}",
                            "--camera", str(d / "cam.json")])
    assert r.exit_code == 2 and "bytes but" in r.output and "Traceback" not in r.output


@pytest.mark.parametrize("bits", [10, 12, 16])
def test_a_16_bit_file_of_any_depth_is_measured_as_its_8_bit_frame(frame, tmp_path, bits):
    """A Mono10/12 frame saved LSB-aligned in a 16-bit PNG (0..2^bits - 1) and a full 16-bit
    one give the 8-bit frame's pixels and pose; before, the 12-bit one read as black."""
    d, img = frame
    wide = (img.astype(np.uint16) << (bits - 8)) | np.uint16((1 << (bits - 8)) - 1)
    cv2.imwrite(str(tmp_path / "f16.png"), wide)
    grey = load_frame(tmp_path / "f16.png")
    np.testing.assert_array_equal(grey, img)
    m8 = measure(img, CAM, limits=SHARP, method="dm+")
    m16 = measure(tmp_path / "f16.png", CAM, limits=SHARP, method="dm+")
    assert m16.ok, m16.quality.reason
    np.testing.assert_array_equal(m16.pose.dof, m8.pose.dof)


def test_a_dark_16_bit_frame_is_still_black():
    """Noise under a lens cap stays black in a 16-bit container (its depth is 8 bits)."""
    from cutterpose.image.preprocessing import as_grey_u8, check_image

    rng = np.random.default_rng(1)
    cap = rng.integers(0, 12, (CAM.image_size_px[1], CAM.image_size_px[0])).astype(np.uint16)
    with pytest.raises(ImageError, match="black"):
        check_image(as_grey_u8(cap), CAM)


def _wide_formats(img, rng):
    """The 8-bit frame as 12-bit pixels (random low bits) in Mono12, Mono12Packed and
    Mono12p, packed as GigE Vision 2.0 and PFNC 2.1 describe them."""
    p = (img.astype(np.uint16) << 4) | rng.integers(0, 16, img.shape, dtype=np.uint16)
    p0, p1 = p.reshape(-1)[0::2], p.reshape(-1)[1::2]
    gev = np.stack([p0 >> 4, (p0 & 0xF) | ((p1 & 0xF) << 4), p1 >> 4], axis=1)
    pfnc = np.stack([p0 & 0xFF, (p0 >> 8) | ((p1 & 0xF) << 4), p1 >> 4], axis=1)
    return {"Mono12": p.astype("<u2").tobytes(),
            "Mono12Packed": gev.astype(np.uint8).tobytes(),
            "Mono12p": pfnc.astype(np.uint8).tobytes()}


@pytest.mark.parametrize("fmt", ["Mono12", "Mono12Packed", "Mono12p"])
def test_wide_raw_formats_give_the_8_bit_frame(frame, tmp_path, fmt):
    """A camera set to 12 bits: the buffer, the file with a sidecar and the CLI's --raw
    --pixel-format all give the 8-bit frame (each pixel's top 8 bits) and its pose."""
    d, img = frame
    h, w = img.shape
    data = _wide_formats(img, np.random.default_rng(3))[fmt]
    np.testing.assert_array_equal(frame_from_buffer(data, w, h, pixel_format=fmt), img)
    (tmp_path / "f.raw").write_bytes(data)
    (tmp_path / "f.raw.json").write_text(json.dumps({"width": w, "height": h,
                                                     "pixel_format": fmt}))
    np.testing.assert_array_equal(load_frame(tmp_path / "f.raw"), img)
    (tmp_path / "g.bin").write_bytes(data)
    res = runner.invoke(app, ["measure", str(tmp_path / "g.bin"), "--raw", f"{w}x{h}",
                              "--pixel-format", fmt, "--camera", str(d / "cam.json"),
                              "--method", "dm+", "--edge-break-mm", "0", "--json"])
    png = runner.invoke(app, ["measure", str(d / "f.png"), "--camera", str(d / "cam.json"),
                              "--method", "dm+", "--edge-break-mm", "0", "--json"])
    assert res.exit_code == 0 and png.exit_code == 0, res.output + png.output
    assert json.loads(res.output)["pose"] == json.loads(png.output)["pose"]


def test_wide_raw_format_errors_are_typed(frame, tmp_path):
    d, img = frame
    h, w = img.shape
    data = _wide_formats(img, np.random.default_rng(4))
    with pytest.raises(ImageError, match="packed 12-bit"):
        frame_from_buffer(data["Mono12Packed"], w, h)          # read as Mono8: 1.5x the bytes
    with pytest.raises(ImageError, match="Mono12Packed needs"):
        frame_from_buffer(data["Mono12"], w, h, pixel_format="Mono12Packed")
    with pytest.raises(ImageError, match="even number of pixels"):
        frame_from_buffer(b"\0" * 3, 1, 1, pixel_format="Mono12p")
    with pytest.raises(ImageError, match="not read"):
        frame_from_buffer(data["Mono12"], w, h, pixel_format="BayerRG12")
    (tmp_path / "f.raw").write_bytes(data["Mono12"])
    (tmp_path / "f.raw.json").write_text(json.dumps({"width": w, "height": h,
                                                     "pixel_format": "RGB8"}))
    with pytest.raises(ImageError, match="pixel_format"):
        load_frame(tmp_path / "f.raw")
