"""The CLI on the inputs of issue 32: each a one-line typed error with exit 2, within a second
and under 200 MB, measured in a fresh interpreter (peak RSS growth by ``resource.getrusage``
around the command, after the imports); and a refused measurement says so first and prints no
pose as if it were good."""

import json
import struct
import subprocess
import sys
import zlib

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from cutterpose.cli import app
from cutterpose.geometry.camera import PinholeCamera, camera_from_dict
from cutterpose.geometry.camera_files import load_camera, save_camera
from cutterpose.geometry.pose import Pose
from cutterpose.render.analytic import render_holder
from cutterpose.service.loadtest import reduced_camera_dict

#: run in a subprocess: each command's seconds and the peak RSS growth since the imports (an
#: upper bound of each command's own), its exit code and output
PROBE = r"""
import json, resource, sys, time
from typer.testing import CliRunner
from cutterpose.cli import app
runner = CliRunner()
runner.invoke(app, ["measure", "/nonexistent.png"])          # the imports, once
import cutterpose.pipeline, cutterpose.robot, cutterpose.calibration.handeye  # noqa
base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
out = {}
for name, args in json.loads(sys.argv[1]).items():
    t0 = time.perf_counter()
    r = runner.invoke(app, args)
    dt = time.perf_counter() - t0
    grow = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - base
    out[name] = {"code": r.exit_code, "out": r.output, "s": dt, "mb": grow / 1024}
print(json.dumps(out))
"""


def _png(w: int, h: int) -> bytes:
    """A grey PNG of ``w x h`` whose pixels are all zero (a 30000 x 30000 one is 875 KB: the
    decompression bomb of the issue). Made fast: after a full flush deflate restarts its
    dictionary, so equal blocks of rows compress to equal bytes, written once and repeated."""
    def chunk(t, d):
        return struct.pack(">I", len(d)) + t + d + struct.pack(">I", zlib.crc32(t + d))

    rows = b"\x00" + bytes(w)
    per = max(1, min(h, 2 ** 22 // (w + 1)))
    block = rows * per
    co = zlib.compressobj(9)
    first = co.compress(block) + co.flush(zlib.Z_FULL_FLUSH)
    again = co.compress(block) + co.flush(zlib.Z_FULL_FLUSH)
    n, rest = divmod(h, per)
    adler = 1
    for _ in range(n):
        adler = zlib.adler32(block, adler)
    tail = zlib.compressobj(9, zlib.DEFLATED, -15)      # raw deflate: the last rows
    z = (first + again * (n - 1) + tail.compress(rows * rest) + tail.flush()
         + struct.pack(">I", zlib.adler32(rows * rest, adler)))
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0))
            + chunk(b"IDAT", z) + chunk(b"IEND", b""))


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    d = tmp_path_factory.mktemp("hostile_cli")
    (d / "2x2.png").write_bytes(_png(2, 2))
    (d / "1x10000.png").write_bytes(_png(1, 10000))
    (d / "10000x1.png").write_bytes(_png(10000, 1))
    (d / "bomb.png").write_bytes(_png(30000, 30000))
    ok, webp = cv2.imencode(".webp", np.zeros((8400, 8400), np.uint8))
    (d / "bomb.webp").write_bytes(webp.tobytes())       # 71 Mpx, past the 67 Mpx budget
    (d / "2x2.raw").write_bytes(bytes(4))
    save_camera(PinholeCamera(10, 10, 0.5, 0.5, (2, 2)), d / "tiny_cam.json")
    (d / "ragged.csv").write_text("# convention: xyz_quat\n# length_unit: mm\n"
                                  "0,0,600,0,0,0,1\n0,0,610,0,0\n")
    return d


CASES = {
    "2x2 PNG": (["measure", "{d}/2x2.png"], "2 x 2 px"),
    "1x10000 PNG": (["measure", "{d}/1x10000.png"], "1 x 10000 px"),
    "10000x1 PNG": (["measure", "{d}/10000x1.png"], "10000 x 1 px"),
    "30000^2 PNG bomb": (["measure", "{d}/bomb.png"], "30000 x 30000 px"),
    "8400^2 WebP": (["measure", "{d}/bomb.webp"], "Mpx"),
    "2x2 raw frame": (["measure", "{d}/2x2.raw", "--raw", "2x2"], "2 x 2 px"),
    "2x2 camera": (["measure", "{d}/2x2.raw", "--raw", "2x2", "--camera", "{d}/tiny_cam.json"],
                   "at least 32 px"),
    "ragged pose file": (["handeye", "{d}/2x2.png", "--poses", "{d}/ragged.csv", "--out",
                          "{d}/he.json"], "ragged"),
}


@pytest.fixture(scope="module")
def probed(inputs):
    cases = {k: [a.format(d=inputs) for a in args] for k, (args, _) in CASES.items()}
    p = subprocess.run([sys.executable, "-c", PROBE, json.dumps(cases)], capture_output=True,
                       text=True, timeout=300)
    assert p.returncode == 0, p.stderr[-2000:]
    return json.loads(p.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("case", list(CASES))
def test_each_case_is_a_one_line_error_within_a_second_and_200_mb(probed, case):
    res = probed[case]
    words = CASES[case][1]
    out = res["out"].strip()
    assert res["code"] == 2, out
    assert "Traceback" not in out and out.startswith("error: ") and words in out, out
    assert len(out.splitlines()) == 1, out
    assert res["s"] < 1.0 and res["mb"] < 200, res
    print(f"\n{case}: exit 2 in {res['s'] * 1e3:.0f} ms, +{res['mb']:.0f} MB: {out[:120]}")


def test_a_refused_measurement_says_so_first_and_prints_no_pose(tmp_path):
    """dm+ on an edge whose break is not known is refused (exit 3): the first line is
    'REFUSED: reason', no pose line follows; with the break given (0: sharp, as rendered) it
    is accepted: 'ACCEPTED', then the pose. (The Table 1 camera binned 4x4, for speed.)"""
    save_camera(camera_from_dict(reduced_camera_dict(4)), tmp_path / "cam.json")
    cam = load_camera(tmp_path / "cam.json")
    img = render_holder(Pose.from_euler(2, -3, 4, 8, -6, 612), cam, None, "easy", seed=7).image
    cv2.imwrite(str(tmp_path / "h.png"), img)
    args = ["measure", str(tmp_path / "h.png"), "--camera", str(tmp_path / "cam.json"),
            "--method", "dm+"]
    runner = CliRunner()
    refused = runner.invoke(app, args)
    assert refused.exit_code == 3, refused.output
    lines = refused.stdout.strip().splitlines()
    assert lines[0].startswith("REFUSED: ") and len(lines[0]) > len("REFUSED: ") + 5
    assert not any(ln.startswith(("alpha", "X ")) for ln in lines), lines
    accepted = runner.invoke(app, [*args, "--edge-break-mm", "0"])
    assert accepted.exit_code == 0, accepted.output
    lines = accepted.stdout.strip().splitlines()
    assert lines[0] == "ACCEPTED" and lines[1].startswith("alpha") and lines[2].startswith("X")
