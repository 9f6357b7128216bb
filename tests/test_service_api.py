"""The service's HTTP API in-process (FastAPI TestClient, real worker processes): answers equal
the record, idempotency, and malformed input always a typed 4xx (issue 12)."""

import base64
import json
import struct
import time
import warnings
import zlib

import cv2
import numpy as np
import pytest

from cutterpose.geometry.pose import Pose
from cutterpose.render.analytic import render_holder
from cutterpose.service.app import create_app
from cutterpose.service.config import load_cell
from cutterpose.service.loadtest import write_cell
from cutterpose.service.store import Store

with warnings.catch_warnings():  # starlette's notice about httpx 2, not ours to act on
    warnings.simplefilter("ignore")
    from starlette.testclient import TestClient

TOKEN = "test-token-0123456789"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
TRUTH = Pose.from_euler(2.0, -3.0, 4.0, 8.0, -6.0, 612.0)


#: hand-eye of the test cell: camera 100 mm ahead of the flange, turned 90 deg about z
T_FLANGE_CAM = np.array([[0.0, -1, 0, 100], [1, 0, 0, 0], [0, 0, 1, 50], [0, 0, 0, 1]])
HANDEYE = {"T_flange_cam": T_FLANGE_CAM.tolist(), "T_base_plate": np.eye(4).tolist(),
           "covariance": np.diag([0.05 ** 2] * 3 + [1e-4 ** 2] * 3).tolist()}


@pytest.fixture(scope="module")
def service(tmp_path_factory):
    folder = tmp_path_factory.mktemp("svc")
    cell = load_cell(write_cell(folder, factor=4, workers=1, max_body_mb=8, handeye=HANDEYE),
                     env={"CUTTERPOSE_TOKEN": TOKEN})
    img = render_holder(TRUTH, cell.camera, None, "easy", seed=7).image
    with TestClient(create_app(cell)) as client:
        yield client, cell, img


def _png(img) -> bytes:
    return cv2.imencode(".png", img)[1].tobytes()


def _post(client, body, ctype="image/png", params=None, headers=AUTH):
    return client.post("/v1/measurements", content=body, params=params or {},
                       headers=headers | ({"Content-Type": ctype} if ctype else {}))


def _count(client) -> int:
    return client.app.state.store.count()


def _measured(client) -> float:
    """Measurements run by the workers so far."""
    reg = client.app.state.metrics.registry
    return reg.get_sample_value("cutterpose_measure_duration_seconds_count")


def test_png_measured_and_stored_as_answered(service):
    client, cell, img = service
    r = _post(client, _png(img), params={"flange_pose": "850,-120.5,1430,0,0,0.7071068,0.7071068",
                                         "request_id": "t-png-1"})
    assert r.status_code == 200, r.text
    rec = r.json()
    pose = rec["measurement"]["pose"]
    est = Pose(np.array(pose["R_cam_holder"]), np.array(pose["t_cam_holder_mm"]))
    err = est.dof - TRUTH.dof
    assert np.all(np.abs(err[:3]) < 0.5) and np.all(np.abs(err[3:]) < 2.0), err
    assert rec["flange_pose"][:3] == [850.0, -120.5, 1430.0]
    # the base frame (cutterpose.robot.locate): T_base_holder = T_base_flange T_flange_cam
    # T_cam_holder, and the verdict rests on the grasp check
    robot = rec["robot"]
    assert robot["available"] is True and rec["verdict_basis"] == "grasp_check"
    T_base_flange = np.eye(4)
    T_base_flange[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]  # the quaternion sent
    T_base_flange[:3, 3] = [850.0, -120.5, 1430.0]
    T_cam_holder = np.eye(4)
    T_cam_holder[:3, :3], T_cam_holder[:3, 3] = pose["R_cam_holder"], pose["t_cam_holder_mm"]
    assert np.allclose(robot["T_base_holder"], T_base_flange @ T_FLANGE_CAM @ T_cam_holder,
                       atol=1e-5)
    assert robot["grasp"]["verdict"] in ("grasp", "retake")
    assert rec["verdict"] == robot["grasp"]["verdict"]
    assert rec["ok"] == (rec["measurement"]["quality"]["ok"]
                         and robot["grasp"]["verdict"] == "grasp")
    assert abs(np.linalg.norm(rec["flange_pose"][3:]) - 1) < 1e-12
    assert rec["image"]["width_px"] == 1028 and rec["image"]["format"] == "png"
    assert client.get(f"/v1/measurements/{rec['id']}", headers=AUTH).json() == rec
    assert client.app.state.store.get(rec["id"]) == rec
    got = client.get(f"/v1/measurements/{rec['id']}/image", headers=AUTH)
    assert got.status_code == 200 and got.content == _png(img)
    ov = client.get(f"/v1/measurements/{rec['id']}/overlay.png", headers=AUTH)
    assert ov.status_code == 200 and ov.content[:8] == b"\x89PNG\r\n\x1a\n"
    assert cv2.imdecode(np.frombuffer(ov.content, np.uint8), cv2.IMREAD_COLOR).shape[2] == 3


def test_raw_json_tiff_bodies_give_the_png_answer(service):
    client, cell, img = service
    ref = _post(client, _png(img)).json()["measurement"]["pose"]
    h, w = img.shape
    raw = _post(client, img.tobytes(), "application/octet-stream",
                {"width": w, "height": h})
    tif = _post(client, cv2.imencode(".tiff", img)[1].tobytes(), "image/tiff")
    js = client.post("/v1/measurements", headers=AUTH, json={
        "image_base64": base64.b64encode(_png(img)).decode(), "format": "png",
        "flange_pose": [1, 2, 3, 0, 0, 0, 1]})
    for r in (raw, tif, js):
        assert r.status_code == 200, r.text
        assert r.json()["measurement"]["pose"] == ref  # same pixels, same pose
    assert js.json()["flange_pose"] == [1, 2, 3, 0, 0, 0, 1]
    assert js.json()["robot"]["available"] is True
    no_flange = raw.json()
    assert no_flange["robot"] == {"available": False, "reason": "no flange pose in the request"}
    assert no_flange["verdict_basis"] == "camera_quality"
    assert no_flange["verdict"] == ("grasp" if no_flange["measurement"]["quality"]["ok"]
                                    else "retake")
    jpg = _post(client, cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 95])[1].tobytes(),
                "image/jpeg")
    assert jpg.status_code == 200
    assert abs(jpg.json()["measurement"]["pose"]["Z_mm"] - ref["Z_mm"]) < 1.0


def test_request_id_replays_the_first_answer(service):
    client, cell, img = service
    body = _png(img)
    n0 = _count(client)
    a = _post(client, body, params={"request_id": "retry-me"})
    b = _post(client, body, params={"request_id": "retry-me"})
    assert a.status_code == b.status_code == 200
    assert a.json() == b.json() and b.headers.get("idempotent-replay") == "true"
    assert _count(client) == n0 + 1
    c = _post(client, body, params={"request_id": "retry-me", "flange_pose": "0,0,0,0,0,0,1"})
    assert c.status_code == 409 and c.json()["error"] == "conflict"
    assert _count(client) == n0 + 1


def _png_claiming(w, h) -> bytes:
    """A tiny PNG whose header claims w x h pixels (a decompression bomb's header)."""
    ihdr = struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0)

    def chunk(kind, data):
        return (struct.pack(">I", len(data)) + kind + data
                + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF))
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\0" * 64))
            + chunk(b"IEND", b""))


def _malformed(img):
    png = _png(img)
    h, w = img.shape
    big = _png(cv2.resize(img, (w * 2, h * 2)))
    b64 = base64.b64encode(png).decode()
    return [
        ("truncated PNG", png[: len(png) // 2], "image/png", {}, 422, "image_unusable"),
        ("garbage as PNG", b"\x00garbage" * 100, "image/png", {}, 422, "image_unusable"),
        ("PNG head, garbage inside", png[:8] + b"\x07" * 5000 + png[-12:], "image/png", {},
         422, "image_unusable"),
        ("JPEG sent as PNG", cv2.imencode(".jpg", img)[1].tobytes(), "image/png", {}, 422,
         "image_unusable"),
        ("pixel bomb header", _png_claiming(100000, 100000), "image/png", {}, 422,
         "image_unusable"),
        ("wrong image size", big, "image/png", {}, 422, "image_unusable"),
        ("wrong content type", png, "text/plain", {}, 415, "unsupported_media_type"),
        ("no content type", png, None, {}, 415, "unsupported_media_type"),
        ("empty body", b"", "image/png", {}, 400, "empty_body"),
        ("raw without size", img.tobytes(), "application/octet-stream", {}, 422,
         "validation_error"),
        ("raw wrong length", img.tobytes()[:-1], "application/octet-stream",
         {"width": w, "height": h}, 422, "image_unusable"),
        ("raw wrong size", img.tobytes(), "application/octet-stream",
         {"width": h, "height": w}, 422, "image_unusable"),
        ("width for a PNG", png, "image/png", {"width": w}, 422, "validation_error"),
        ("negative width", img.tobytes(), "application/octet-stream",
         {"width": -1, "height": h}, 422, "validation_error"),
        ("flange 3 numbers", png, "image/png", {"flange_pose": "1,2,3"}, 422,
         "bad_flange_pose"),
        ("flange words", png, "image/png", {"flange_pose": "a,b,c,d,e,f,g"}, 422,
         "bad_flange_pose"),
        ("flange nan", png, "image/png", {"flange_pose": "nan,0,0,0,0,0,1"}, 422,
         "bad_flange_pose"),
        ("flange zero quaternion", png, "image/png", {"flange_pose": "0,0,0,0,0,0,0"}, 422,
         "bad_flange_pose"),
        ("flange in metres*1e6", png, "image/png", {"flange_pose": "1e9,0,0,0,0,0,1"}, 422,
         "bad_flange_pose"),
        ("bad request id", png, "image/png", {"request_id": "a b/../c"}, 422,
         "validation_error"),
        ("unknown holder", png, "image/png", {"holder": "nope"}, 422, "validation_error"),
        ("unknown parameter", png, "image/png", {"colour": "red"}, 422, "validation_error"),
        ("bad JSON", b'{"image_base64": ', "application/json", {}, 400, "bad_json"),
        ("JSON not an object", b"[1, 2]", "application/json", {}, 422, "validation_error"),
        ("JSON missing image", b'{"format": "png"}', "application/json", {}, 422,
         "validation_error"),
        ("JSON bad base64", json.dumps({"image_base64": "@@@", "format": "png"}).encode(),
         "application/json", {}, 422, "validation_error"),
        ("JSON bad format", json.dumps({"image_base64": b64, "format": "gif"}).encode(),
         "application/json", {}, 422, "validation_error"),
        ("JSON flange 6", json.dumps({"image_base64": b64, "format": "png",
                                      "flange_pose": [0, 0, 0, 0, 0, 1]}).encode(),
         "application/json", {}, 422, "bad_flange_pose"),
        ("JSON flange strings", json.dumps({"image_base64": b64, "format": "png",
                                            "flange_pose": ["x"] * 7}).encode(),
         "application/json", {}, 422, "validation_error"),
        ("JSON plus query", json.dumps({"image_base64": b64, "format": "png"}).encode(),
         "application/json", {"request_id": "x"}, 422, "validation_error"),
    ]


def test_malformed_input_is_a_typed_4xx_and_stores_nothing(service):
    client, cell, img = service
    n0 = _count(client)
    for name, body, ctype, params, status, error in _malformed(img):
        r = _post(client, body, ctype, params)
        assert r.status_code == status, (name, r.status_code, r.text)
        b = r.json()
        assert b["error"] == error and b["message"], (name, b)
        assert "Traceback" not in r.text and "\n" not in b["message"], name
    assert _count(client) == n0


@pytest.mark.parametrize("path, status", [
    ("/v1/measurements/not-an-id", 422), ("/v1/measurements/" + "0" * 32, 404),
    ("/v1/measurements/" + "0" * 32 + "/overlay.png", 404),
    ("/v1/measurements/" + "0" * 32 + "/image", 404),
    ("/v1/measurements?since=yesterday", 422), ("/v1/measurements?limit=0", 422),
    ("/v1/measurements?limit=100000", 422), ("/nowhere", 404)])
def test_bad_reads_are_typed(service, path, status):
    client, _, _ = service
    r = client.get(path, headers=AUTH)
    assert r.status_code == status and r.json()["error"] and r.json()["message"]


def test_body_over_the_limit_is_413_before_reading(service):
    client, cell, img = service
    n0 = _count(client)
    body = b"\x89PNG\r\n\x1a\n" + bytes(200 * 2 ** 20)  # 200 MB against the cell's 8 MB
    r = _post(client, body)
    assert r.status_code == 413 and r.json()["error"] == "too_large"
    # the same check while streaming (no Content-Length): a generator body
    r = client.post("/v1/measurements", headers=AUTH | {"Content-Type": "image/png"},
                    content=(bytes(2 ** 20) for _ in range(20)))
    assert r.status_code == 413 and r.json()["error"] == "too_large"
    assert _count(client) == n0


def test_without_the_token_401_and_nothing_measured_or_stored(service):
    client, cell, img = service
    n0, m0 = _count(client), _measured(client)
    for headers in ({}, {"Authorization": "Bearer wrong"}, {"Authorization": f"Basic {TOKEN}"},
                    {"Authorization": f"Bearer {TOKEN}x"}, {"Authorization": TOKEN}):
        r = _post(client, _png(img), headers=headers)
        assert r.status_code == 401 and r.json()["error"] == "unauthorized"
        assert r.headers["www-authenticate"] == "Bearer"
        # also with a broken body and parameters: the token is checked first
        r = _post(client, b"junk", "text/plain", {"flange_pose": "x"}, headers=headers)
        assert r.status_code == 401
        for path in ("/v1/measurements", "/metrics", "/v1/measurements/" + "0" * 32):
            assert client.get(path, headers=headers).status_code == 401
    assert _count(client) == n0 and _measured(client) == m0
    assert client.get("/health").status_code == 200  # liveness needs no token
    assert _post(client, _png(img)).status_code == 200  # the counters do see a measurement
    assert _count(client) == n0 + 1 and _measured(client) == m0 + 1


def test_since_lists_in_order(service):
    client, cell, img = service
    ids = [_post(client, _png(img)).json() for _ in range(2)]
    r = client.get("/v1/measurements", params={"since": ids[0]["created_at"]}, headers=AUTH)
    got = r.json()["measurements"]
    assert [g["id"] for g in got][:2] == [i["id"] for i in ids]
    assert r.json()["next_since"] == got[-1]["created_at"]
    z = ids[0]["created_at"].replace("+00:00", "Z")
    assert client.get("/v1/measurements", params={"since": z, "limit": 1},
                      headers=AUTH).json()["measurements"] == [ids[0]]
    later = client.get("/v1/measurements", params={"since": "2999-01-01T00:00:00"},
                       headers=AUTH).json()
    assert later == {"measurements": [], "next_since": None}


def test_health_ready_metrics(service):
    client, cell, img = service
    assert client.get("/health").json() == {"status": "alive"}
    ready = client.get("/ready").json()
    assert ready["ready"] and len(ready["workers"]) == 1 and ready["workers"][0]["pid"] > 0
    assert ready["cell"]["image_size_px"] == [1028, 752]
    _post(client, b"", "image/png")
    text = client.get("/metrics", headers=AUTH).text
    for name in ("cutterpose_http_requests_total",
                 "cutterpose_refusals_total{reason=\"empty_body\"}",
                 "cutterpose_http_request_duration_seconds_bucket", "cutterpose_queue_depth",
                 "cutterpose_workers_ready 1.0", "cutterpose_measure_duration_seconds_count"):
        assert name in text, name


def test_openapi_documents_units_frames_and_bodies(service):
    client, _, _ = service
    spec = client.get("/openapi.json").json()
    post = spec["paths"]["/v1/measurements"]["post"]
    assert set(post["requestBody"]["content"]) == {"image/png", "image/tiff", "image/jpeg",
                                                   "application/octet-stream",
                                                   "application/json"}
    assert {"401", "413", "415", "422", "503", "504"} <= set(post["responses"])
    schemas = spec["components"]["schemas"]
    assert "[mm]" in schemas["PoseOut"]["properties"]["t_cam_holder_mm"]["description"]
    assert "T_base_flange" in json.dumps(post["parameters"])
    assert "bearer" in json.dumps(spec["components"]["securitySchemes"]).lower()


def test_store_evicts_oldest_images_and_keeps_records(tmp_path):
    s = Store(tmp_path, image_cap_bytes=2500)
    for k in range(4):
        rec = {"id": f"{k:032x}", "k": k}
        row = {"id": rec["id"], "request_id": f"r{k}", "created_at": f"2025-01-0{k + 1}",
               "image_sha256": "x", "image_bytes": 1000, "image_format": "png", "ok": 1,
               "verdict": "grasp"}
        assert s.insert(rec, row, bytes([k]) * 1000, ".png") == rec
    assert [s.image(f"{k:032x}") is not None for k in range(4)] == [False, False, True, True]
    assert s.images_bytes == 2000 and len(list((tmp_path / "images").iterdir())) == 2
    assert [s.get(f"{k:032x}")["k"] for k in range(4)] == [0, 1, 2, 3]
    # the same request id again: the first answer, no second row
    dup = {"id": "f" * 32, "k": 99}
    assert s.insert(dup, {**row, "id": dup["id"]}, b"z" * 10, ".png") == {"id": row["id"],
                                                                         "k": 3}
    assert s.count() == 4 and s.integrity_check() == "ok"
    s.close()
    s2 = Store(tmp_path, image_cap_bytes=2500)   # reopened: the folder's state is known
    assert s2.images_bytes == 2000 and s2.since("2025-01-03", 10)[0]["k"] == 2
    s2.close()


def test_records_export_csv_and_json(service, tmp_path):
    import csv
    import io

    from typer.testing import CliRunner

    from cutterpose.cli import app

    client, cell, img = service
    rec = _post(client, _png(img), params={"flange_pose": "1,2,3,0,0,0,1"}).json()
    runner = CliRunner()
    r = runner.invoke(app, ["records", "export", "--data-dir", str(cell.service.data_dir),
                            "--since", rec["created_at"], "--format", "csv"])
    assert r.exit_code == 0, r.output
    rows = list(csv.DictReader(io.StringIO(r.stdout)))
    assert rows[0]["id"] == rec["id"]
    assert float(rows[0]["Z_mm"]) == rec["measurement"]["pose"]["Z_mm"]
    assert float(rows[0]["flange_x_mm"]) == 1.0 and rows[0]["verdict"] == "grasp"
    out = tmp_path / "r.json"
    r = runner.invoke(app, ["records", "export", "--data-dir", str(cell.service.data_dir),
                            "--since", rec["created_at"], "--format", "json", "--out", str(out)])
    assert r.exit_code == 0 and json.loads(out.read_text())[0] == rec
    r = runner.invoke(app, ["records", "export", "--data-dir", str(cell.service.data_dir),
                            "--since", "last tuesday"])
    assert r.exit_code != 0 and "ISO 8601" in r.output


def test_deadline_is_504_and_the_service_goes_on(tmp_path, service):
    """A deadline far shorter than a measurement (a 12-Mpx image: its decoding alone takes
    longer): 504, nothing stored; a job that ran a whole deadline has its worker replaced."""
    _, _, img = service
    big = _png(cv2.resize(img, (4112, 3008), interpolation=cv2.INTER_LINEAR))
    cell = load_cell(write_cell(tmp_path, factor=1, workers=1, deadline_s=0.02),
                     env={"CUTTERPOSE_TOKEN": TOKEN})
    with TestClient(create_app(cell)) as client:
        pool = client.app.state.pool
        assert pool.wait_ready(60)
        r = _post(client, big)
        assert r.status_code == 504 and r.json()["error"] == "deadline_exceeded"
        assert _count(client) == 0
        if "waiting in the queue" not in r.json()["message"]:   # it ran: stuck after 0.02 s
            end = time.monotonic() + 30
            while pool.restarts == 0 and time.monotonic() < end:
                time.sleep(0.01)
            assert pool.restarts == 1
        assert pool.wait_ready(60) and client.get("/ready").json()["ready"]
