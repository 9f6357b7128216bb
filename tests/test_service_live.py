"""The real service (uvicorn subprocess on 127.0.0.1): load, faults, streaming limits and a
bounded property-based run of its OpenAPI schema (issue 12).

The cell is the Table 1 camera binned 4 x 4 (1028 x 752 px), so that 500 measurements fit the
test machine's two cores; the full-size figures are in docs/RESULTS.md
(benchmarks/service_load.py).
"""

import json
import os
import select
import signal
import socket
import sqlite3
import threading
import time
from concurrent.futures import ThreadPoolExecutor

import httpx
import numpy as np
import pytest
import schemathesis
from hypothesis import HealthCheck, given, settings
from hypothesis.errors import Unsatisfiable
from schemathesis import GenerationMode
from schemathesis.checks import (
    content_type_conformance,
    not_a_server_error,
    response_schema_conformance,
    status_code_conformance,
)

from cutterpose.client import Client, ServiceError
from cutterpose.geometry.camera import camera_from_dict
from cutterpose.service.loadtest import (
    ServerProcess,
    reduced_camera_dict,
    render_images,
    run_load,
    write_cell,
)
from cutterpose.service.store import DB_NAME

TOKEN = "live-test-token-4f1c"
AUTH = {"Authorization": f"Bearer {TOKEN}"}


@pytest.fixture(scope="module")
def images():
    return render_images(camera_from_dict(reduced_camera_dict(4)), 5, seed=3)


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    """One worker, the token from the cell's token file."""
    cell = write_cell(tmp_path_factory.mktemp("live"), factor=4, token=TOKEN, workers=1)
    with ServerProcess(cell) as s:
        yield s
    assert s.reap_workers() == []  # every worker it started has exited by itself


def _post(url, body, **params):
    return httpx.post(url + "/v1/measurements", content=body, params=params, timeout=60,
                      headers=AUTH | {"Content-Type": "image/png"})


def test_client_round_trip(server, images, tmp_path):
    path = tmp_path / "a.png"
    path.write_bytes(images[0])
    with Client(server.url, token=TOKEN) as c:
        assert c.ready()
        a = c.measure(path, flange_pose=[850, -120, 1430, 0, 0, 0, 1], request_id="client-1")
        again = c.measure(images[0], content_type="image/png", request_id="client-1",
                          flange_pose=[850, -120, 1430, 0, 0, 0, 1])
        assert again == a and c.get(a["id"]) == a
        import cv2
        grey = cv2.imdecode(np.frombuffer(images[0], np.uint8), cv2.IMREAD_GRAYSCALE)
        raw = c.measure(grey)
        assert raw["measurement"]["pose"] == a["measurement"]["pose"] and raw["id"] != a["id"]
        assert a["id"] in [m["id"] for m in c.since(a["created_at"])]
        assert c.overlay(a["id"])[:4] == b"\x89PNG"
        with pytest.raises(ServiceError) as e:
            c.measure(b"not an image", content_type="image/png")
        assert e.value.status == 422 and e.value.error == "image_unusable"
    with Client(server.url, token="wrong") as c, pytest.raises(ServiceError) as e:
        c.measure(path)
    assert e.value.status == 401


def test_client_tracks_an_approach(server, images):
    """Client.track: the frames of a session answered in order (the first measured in full,
    the next from it), raw arrays and PNG bytes; closed by the with block."""
    import cv2

    grey = cv2.imdecode(np.frombuffer(images[1], np.uint8), cv2.IMREAD_GRAYSCALE)
    with Client(server.url, token=TOKEN) as c:
        with c.track(filter=False) as t:
            a = t.frame(images[1], content_type="image/png")
            b = t.frame(grey, flange_pose=[850, -120, 1430, 0, 0, 0, 1])
            assert (a["mode"], b["mode"]) == ("full", "track"), (a, b)
            assert (a["frame"], b["frame"]) == (0, 1) and a["filtered_pose"] is None
            assert abs(a["pose"]["Z_mm"] - b["pose"]["Z_mm"]) < 1.0
            # no hand-eye file in this cell: the base frame says why it is missing
            assert b["robot"] == {"available": False,
                                  "reason": "the cell file names no hand-eye file"}
            assert t.status()["frames"] == 2
        with pytest.raises(ServiceError) as e:
            t.frame(grey)
        assert e.value.status == 404
        t.close()   # closed twice: nothing to do


def _measured(url) -> float:
    text = httpx.get(url + "/metrics", headers=AUTH).text
    return float(next(line.split()[1] for line in text.splitlines()
                      if line.startswith("cutterpose_measure_duration_seconds_count")))


def test_concurrent_repeats_of_one_request_measure_once(server, images):
    """A client retrying while its first try is still being measured gets the same answer,
    and the picture is measured and stored once."""
    m0 = _measured(server.url)
    with ThreadPoolExecutor(4) as ex:
        rs = list(ex.map(lambda _: _post(server.url, images[1], request_id="same-1"), range(4)))
    assert [r.status_code for r in rs] == [200] * 4
    assert all(r.json() == rs[0].json() for r in rs)
    assert _measured(server.url) == m0 + 1
    con = sqlite3.connect(server.cell.parent / "data" / DB_NAME)
    n = con.execute("SELECT COUNT(*) FROM measurements WHERE request_id = 'same-1'").fetchone()
    con.close()
    assert n[0] == 1


def _property_run(op, mode, checks, statuses):
    @settings(max_examples=8, deadline=None, derandomize=True, database=None,
              suppress_health_check=list(HealthCheck))
    @given(case=op.as_strategy(generation_mode=mode))
    def run(case):
        r = case.call_and_validate(headers=AUTH, timeout=60, checks=checks)
        statuses.append(r.status_code)

    run()


def test_schema_property_run_finds_no_server_error(server):
    """Requests generated from the OpenAPI schema, valid and invalid (schemathesis, bounded,
    derandomised): never a 5xx; valid ones answered as documented."""
    schema = schemathesis.openapi.from_url(server.url + "/openapi.json")
    full = [not_a_server_error, status_code_conformance, content_type_conformance,
            response_schema_conformance]
    statuses = []
    for result in schema.get_all_operations():
        op = result.ok()
        _property_run(op, GenerationMode.POSITIVE, full, statuses)
        try:
            _property_run(op, GenerationMode.NEGATIVE, [not_a_server_error], statuses)
        except Unsatisfiable:
            assert not op.path_parameters and not op.query  # nothing to get wrong (/health)
    assert len(statuses) >= 50 and max(statuses) < 500
    assert {200, 422} <= set(statuses)  # both valid answers and refusals were produced


def _hwm_kb(pid: int) -> int:
    with open(f"/proc/{pid}/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("VmHWM"))


def test_streamed_200mb_body_is_413_and_never_held(server):
    """A chunked 200 MB upload (no Content-Length) is refused once it passes 64 MB; the
    service's peak memory grows by far less than the body."""
    hwm0 = _hwm_kb(server.proc.pid)
    s = socket.create_connection(("127.0.0.1", server.port), timeout=10)
    s.sendall((f"POST /v1/measurements HTTP/1.1\r\nHost: 127.0.0.1\r\nAuthorization: Bearer "
               f"{TOKEN}\r\nContent-Type: image/png\r\nTransfer-Encoding: chunked\r\n\r\n"
               ).encode())
    size = 2 ** 20
    chunk = b"%x\r\n" % size + bytes(size) + b"\r\n"
    sent = 0
    try:
        while sent < 200 * size and not select.select([s], [], [], 0)[0]:
            s.sendall(chunk)
            sent += size
    except OSError:
        pass  # the service closed the connection after answering
    data = b""
    while b"\r\n\r\n" not in data:
        part = s.recv(65536)
        if not part:
            break
        data += part
    s.close()
    assert data.split()[1] == b"413", data[:200]
    assert sent < 200 * size            # it did not wait for the whole body
    assert _hwm_kb(server.proc.pid) - hwm0 < 150 * 1024
    assert _post(server.url, b"").status_code == 400  # and it goes on


def _post_into(out, url, body):
    out["r"] = _post(url, body)


def test_killed_worker_fails_its_request_only(server, images):
    """SIGKILL the worker (by pid) while it measures: that request gets a typed error, the
    worker is replaced, the next requests succeed."""
    hit = None
    for attempt in range(10):
        out = {}
        t = threading.Thread(target=_post_into, args=(out, server.url, images[attempt % 5]))
        t.start()
        killed = None
        end = time.monotonic() + 30
        while t.is_alive() and killed is None and time.monotonic() < end:
            w = server.ready()["workers"][0]
            if w["busy"]:
                os.kill(w["pid"], signal.SIGKILL)
                killed = w["pid"]
            time.sleep(0.002)
        t.join(60)
        if killed is not None and out["r"].status_code != 200:
            hit = (killed, out["r"])
            break
    assert hit is not None, "the worker was never caught busy"
    pid, r = hit
    print(f"\nworker {pid} killed on attempt {attempt + 1}: {r.status_code} {r.json()}")
    assert r.status_code == 500
    assert r.json()["error"] == "worker_crashed" and str(pid) in r.json()["message"]
    for img in images[:3]:
        assert _post(server.url, img).status_code == 200
    ready = server.ready()
    assert ready["ready"] and ready["workers"][0]["pid"] != pid
    assert ready["workers"][0]["restarts"] >= 1


def _db_records(folder) -> dict:
    con = sqlite3.connect(folder / "data" / DB_NAME)
    try:
        assert con.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
        return {rid: (mid, json.loads(rec)) for rid, mid, rec in
                con.execute("SELECT request_id, id, record FROM measurements")}
    finally:
        con.close()


def test_load_100_clients_500_measurements(tmp_path, images):
    """100 concurrent clients, 500 measurements: every one answered (200, or 503 and a
    successful retry), each 200 stored once with the same answer."""
    cell = write_cell(tmp_path, factor=4, token=TOKEN)  # one worker per core, queue 32
    with ServerProcess(cell) as s:
        res = run_load(s.url, TOKEN, images, n_clients=100, n_total=500, timeout_s=300)
        metrics = httpx.get(s.url + "/metrics", headers=AUTH).text
    assert res.errors == []
    assert len(res.answers) == 500
    assert res.refusals_503 > 0          # the queue bound was reached and retried through
    assert 'cutterpose_refusals_total{reason="queue_full"}' in metrics
    stored = _db_records(tmp_path)
    assert set(stored) == set(res.answers)              # nothing lost, nothing extra
    assert len({mid for mid, _ in stored.values()}) == 500  # nothing duplicated
    for rid, answer in res.answers.items():
        assert stored[rid] == (answer["id"], answer)     # stored as answered
    assert all(a["ok"] for a in res.answers.values())
    print("\nload (4x4-binned Table 1 camera):", json.dumps(res.summary()))


def test_sigkill_and_restart_loses_no_answer(tmp_path, images):
    cell = write_cell(tmp_path, factor=4, token=TOKEN)
    s = ServerProcess(cell).start()
    answered, lock = {}, threading.Lock()

    def one(k):
        rid = f"kill-{k}"
        try:
            r = _post(s.url, images[k % 5], request_id=rid)
        except httpx.TransportError:
            return
        if r.status_code == 200:
            with lock:
                answered[rid] = r.json()

    with ThreadPoolExecutor(8) as ex:
        futs = [ex.submit(one, k) for k in range(60)]
        end = time.monotonic() + 120
        while len(answered) < 12 and time.monotonic() < end:
            time.sleep(0.01)
        s.kill()
        for f in futs:
            f.result()
    assert 12 <= len(answered) < 60
    print(f"\nSIGKILL after {len(answered)} of 60 answered")
    assert s.reap_workers() == []        # the workers exit when the service is killed
    stored = _db_records(tmp_path)       # integrity_check ok
    assert all(stored[rid] == (a["id"], a) for rid, a in answered.items())
    with ServerProcess(cell) as s2:      # restarted on the same data
        for a in answered.values():
            r = httpx.get(f"{s2.url}/v1/measurements/{a['id']}", headers=AUTH)
            assert r.status_code == 200 and r.json() == a
        rid, a = next(iter(answered.items()))
        k = int(rid.split("-")[1])
        replay = _post(s2.url, images[k % 5], request_id=rid)
        assert replay.json() == a and replay.headers["idempotent-replay"] == "true"
