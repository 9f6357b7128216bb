"""Tracking sessions over HTTP (``/v1/tracks``): a rendered approach answered frame by frame,
in order, with the base frame; sessions closed, expired and limited; bad frames typed 4xx."""

import time
import warnings

import cv2
import numpy as np
import pytest

from cutterpose.geometry.pose import Pose
from cutterpose.render.analytic import render_holder
from cutterpose.service.app import create_app
from cutterpose.service.config import load_cell
from cutterpose.service.loadtest import write_cell

with warnings.catch_warnings():  # starlette's notice about httpx 2, not ours to act on
    warnings.simplefilter("ignore")
    from starlette.testclient import TestClient

TOKEN = "test-token-tracks-0123"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
T_FLANGE_CAM = np.array([[0.0, -1, 0, 100], [1, 0, 0, 0], [0, 0, 1, 50], [0, 0, 0, 1]])
HANDEYE = {"T_flange_cam": T_FLANGE_CAM.tolist(), "T_base_plate": np.eye(4).tolist(),
           "covariance": np.diag([0.05 ** 2] * 3 + [1e-4 ** 2] * 3).tolist()}
FLANGE = "850,-120.5,1430,0,0,0.7071068,0.7071068"
#: an approach: 4 frames 2 mm apart (the binned test camera)
POSES = [Pose.from_euler(2.0, -3.0, 4.0, 8.0, -6.0, 640.0 - 2.0 * k) for k in range(4)]


@pytest.fixture(scope="module")
def service(tmp_path_factory):
    folder = tmp_path_factory.mktemp("svc_tracks")
    cell = load_cell(write_cell(folder, factor=4, workers=1, max_tracks=2, track_idle_s=30,
                                handeye=HANDEYE), env={"CUTTERPOSE_TOKEN": TOKEN})
    frames = [render_holder(p, cell.camera, None, "easy", seed=7, noise_seed=k).image
              for k, p in enumerate(POSES)]
    with TestClient(create_app(cell)) as client:
        yield client, cell, frames


def _png(img) -> bytes:
    return cv2.imencode(".png", img)[1].tobytes()


def _open(client, **body):
    return client.post("/v1/tracks", json=body, headers=AUTH)


def _frame(client, tid, body, ctype="image/png", params=None):
    return client.post(f"/v1/tracks/{tid}/frames", content=body, params=params or {},
                       headers=AUTH | {"Content-Type": ctype})


def test_an_approach_is_tracked_frame_by_frame_with_the_base_frame(service):
    client, cell, frames = service
    r = _open(client)
    assert r.status_code == 201, r.text
    info = r.json()
    tid = info["id"]
    assert info["frames"] == 0 and info["method"] == cell.method and info["filter"] is True
    answers = []
    for k, img in enumerate(frames):
        # the first as PNG, the others raw 8-bit as a GigE camera delivers them
        if k == 0:
            r = _frame(client, tid, _png(img), params={"flange_pose": FLANGE})
        else:
            h, w = img.shape
            r = _frame(client, tid, img.tobytes(), "application/octet-stream",
                       {"width": w, "height": h, "flange_pose": FLANGE})
        assert r.status_code == 200, r.text
        answers.append(r.json())
    assert [a["mode"] for a in answers] == ["full", "track", "track", "track"], \
        [(a["mode"], a["fallback_reason"]) for a in answers]
    assert [a["frame"] for a in answers] == [0, 1, 2, 3]
    for a, truth in zip(answers, POSES):
        assert a["track_id"] == tid and a["ok"] is True
        p = a["pose"]
        est = Pose(np.array(p["R_cam_holder"]), np.array(p["t_cam_holder_mm"]))
        err = est.dof - truth.dof
        assert np.all(np.abs(err[:3]) < 0.5) and np.all(np.abs(err[3:]) < 2.0), err
        assert a["filtered_pose"] is not None
        # the base frame: T_base_holder = T_base_flange T_flange_cam T_cam_holder
        robot = a["robot"]
        assert robot["available"] is True, robot
        T = np.array(robot["T_base_flange"]) @ T_FLANGE_CAM @ est.matrix
        np.testing.assert_allclose(np.array(robot["T_base_holder"]), T, atol=1e-6)
        assert {"decode_ms", "wait_ms", "track_ms", "total_ms"} <= set(a["timings_ms"])
    info = client.get(f"/v1/tracks/{tid}", headers=AUTH).json()
    assert info["frames"] == 4 and info["last_mode"] == "track"
    assert client.delete(f"/v1/tracks/{tid}", headers=AUTH).status_code == 204
    assert client.get(f"/v1/tracks/{tid}", headers=AUTH).status_code == 404
    r = _frame(client, tid, _png(frames[0]))
    assert r.status_code == 404 and r.json()["error"] == "not_found"


def test_bad_frames_and_requests_are_typed_4xx(service):
    client, cell, frames = service
    tid = _open(client).json()["id"]
    try:
        img = frames[0]
        bad = {
            "json body": _frame(client, tid, b"{}", "application/json"),
            "raw without size": _frame(client, tid, img.tobytes(), "application/octet-stream"),
            "raw wrong size": _frame(client, tid, img.tobytes()[:-10],
                                     "application/octet-stream",
                                     {"width": img.shape[1], "height": img.shape[0]}),
            "truncated png": _frame(client, tid, _png(img)[:-40]),
            "small png": _frame(client, tid, _png(img[::2, ::2])),
            "flange pose": _frame(client, tid, _png(img), params={"flange_pose": "1,2,3"}),
            "empty": _frame(client, tid, b""),
            "frame time": _frame(client, tid, _png(img), params={"t_s": "soon"}),
            "frame id": _frame(client, tid, _png(img), params={"frame_id": -3}),
        }
        codes = {k: (r.status_code, r.json()["error"]) for k, r in bad.items()}
        assert codes == {"json body": (415, "unsupported_media_type"),
                         "raw without size": (422, "validation_error"),
                         "raw wrong size": (422, "image_unusable"),
                         "truncated png": (422, "image_unusable"),
                         "small png": (422, "image_unusable"),
                         "flange pose": (422, "bad_flange_pose"),
                         "empty": (400, "empty_body"),
                         "frame time": (422, "validation_error"),
                         "frame id": (422, "validation_error")}, codes
        # none of them reached the tracker
        assert client.get(f"/v1/tracks/{tid}", headers=AUTH).json()["frames"] == 0
        assert _open(client, holder="nope").status_code == 422
        assert _open(client, anchor_lag=-1).status_code == 422
        assert client.get("/v1/tracks/" + "0" * 32, headers=AUTH).status_code == 404
        assert client.get("/v1/tracks/xyz", headers=AUTH).status_code == 422
        assert client.post("/v1/tracks", json={}).status_code == 401
        assert _frame(client, tid, _png(img)).status_code == 200   # the session still works
        # a frame time after frames without: the tracker refuses it, typed
        r = _frame(client, tid, _png(frames[1]), params={"t_s": 0.1})
        assert (r.status_code, r.json()["error"]) == (422, "bad_input"), r.text
        assert "t_s" in r.json()["message"], r.text
    finally:
        client.delete(f"/v1/tracks/{tid}", headers=AUTH)
    # a session whose frames all carry their times and numbers (a client sending the newest
    # frame): the answers carry the camera's numbers
    tid = _open(client).json()["id"]
    try:
        outs = [_frame(client, tid, _png(f), params={"t_s": 0.1 * k, "frame_id": 100 + k}).json()
                for k, f in zip((0, 1, 3), (frames[0], frames[1], frames[3]))]
        assert [o["mode"] for o in outs] == ["full", "track", "track"], outs
        assert [(o["frame"], o["frame_id"]) for o in outs] == [(0, 100), (1, 101), (2, 103)]
    finally:
        client.delete(f"/v1/tracks/{tid}", headers=AUTH)


def test_sessions_are_limited_and_idle_ones_expire(service):
    client, cell, frames = service
    tracks = client.app.state.tracks
    ids = [_open(client).json()["id"] for _ in range(2)]          # max_tracks = 2
    r = _open(client)
    assert r.status_code == 429 and r.json()["error"] == "too_many_tracks"
    assert "Retry-After" in r.headers
    # one idles past track_idle_s: it is closed, and a new session fits
    tracks._sessions[ids[0]].last_used = time.monotonic() - 31.0
    r = _open(client)
    assert r.status_code == 201, r.text
    assert client.get(f"/v1/tracks/{ids[0]}", headers=AUTH).status_code == 404
    for tid in (ids[1], r.json()["id"]):
        assert client.delete(f"/v1/tracks/{tid}", headers=AUTH).status_code == 204
    assert len(tracks) == 0
