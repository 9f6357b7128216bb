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
