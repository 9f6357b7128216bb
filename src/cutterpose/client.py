"""A small Python client of the measurement service (``cutterpose serve``, docs/service.md).

>>> from cutterpose.client import Client
>>> with Client("http://127.0.0.1:8000") as c:          # token from CUTTERPOSE_TOKEN
...     rec = c.measure("holder.png", flange_pose=[850, -120, 1430, 0, 0, 0, 1])
...     rec["verdict"], rec["measurement"]["pose"]["Z_mm"]

Tracking an approach (``/v1/tracks``): frames in order, one answer each, not stored:

>>> with Client() as c, c.track() as t:                  # doctest: +SKIP
...     for frame, flange in camera_and_robot():            # 2-D uint8 frames, sent raw
...         r = t.frame(frame, flange_pose=flange)
...         r["mode"], r["robot"]["T_base_holder"]

Every measurement carries a request id (a fresh UUID unless given), so a retry after a
connection error or a ``503`` (honouring ``Retry-After``) can never measure or store the same
picture twice: the service answers a repeated id with its first answer.

Convention:
    Flange poses ``T_base_flange`` as the PROTOCOL pose row ``x_mm, y_mm, z_mm, qx, qy, qz, qw``;
    the answer as the service's ``MeasurementRecord`` (cutterpose.service.models).
"""

from __future__ import annotations

import os
import time
import uuid
from pathlib import Path

import numpy as np

from .errors import CutterposeError

__all__ = ["Client", "Track", "ServiceError"]

_CONTENT_TYPES = {".png": "image/png", ".tif": "image/tiff", ".tiff": "image/tiff",
                  ".jpg": "image/jpeg", ".jpeg": "image/jpeg"}


class ServiceError(CutterposeError):
    """The service answered an error: ``status`` (HTTP), ``error`` (its code), the message."""

    def __init__(self, status: int, error: str, message: str):
        super().__init__(f"{status} {error}: {message}")
        self.status, self.error = status, error


class Client:
    """Client of one service.

    Parameters
    ----------
    base_url : e.g. ``http://127.0.0.1:8000`` (``https://`` with TLS).
    token : bearer token (default: the environment variable ``CUTTERPOSE_TOKEN``).
    timeout_s : per HTTP request.
    retries : attempts after a 503 or a connection error (same request id each time).
    verify : TLS verification: True, False, or a CA bundle path.
    """

    def __init__(self, base_url: str = "http://127.0.0.1:8000", token: str | None = None,
                 timeout_s: float = 60.0, retries: int = 5, verify=True):
        try:
            import httpx
        except ImportError as e:  # pragma: no cover - depends on the environment
            raise CutterposeError("the client needs httpx: pip install 'cutterpose[service]'"
                                  ) from e
        self._httpx = httpx
        token = token or os.environ.get("CUTTERPOSE_TOKEN")
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        self.retries = retries
        self._http = httpx.Client(base_url=base_url, headers=headers, timeout=timeout_s,
                                  verify=verify)

    def close(self) -> None:
        self._http.close()

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- measurements --------------------------------------------------------------------
    def measure(self, image, flange_pose=None, request_id: str | None = None,
                content_type: str | None = None, holder: str | None = None) -> dict:
        """Measure one image; returns the stored record (``MeasurementRecord``).

        Parameters
        ----------
        image : a file path (PNG/TIFF/JPEG by extension), encoded bytes (give
            ``content_type``), or a 2-D ``uint8`` array (sent raw).
        flange_pose : ``T_base_flange`` as 7 numbers (PROTOCOL pose row), or None.
        request_id : the idempotency key (default: a fresh UUID, kept across retries).

        Raises
        ------
        ServiceError
            Any error answer (after the retries for 503).
        """
        params = {"request_id": request_id or uuid.uuid4().hex}
        body, ctype, size = _body(image, content_type)
        params |= size
        if flange_pose is not None:
            params["flange_pose"] = _pose_row(flange_pose)
        if holder is not None:
            params["holder"] = holder
        return self._request("POST", "/v1/measurements", params=params, content=body,
                             headers={"Content-Type": ctype}).json()

    def get(self, measurement_id: str) -> dict:
        """A stored measurement."""
        return self._request("GET", f"/v1/measurements/{measurement_id}").json()

    def since(self, since: str | None = None, limit: int = 100) -> list[dict]:
        """Stored measurements from ``since`` (ISO 8601) on, oldest first."""
        params = {"limit": limit} | ({"since": since} if since else {})
        return self._request("GET", "/v1/measurements", params=params).json()["measurements"]

    def overlay(self, measurement_id: str) -> bytes:
        """The overlay PNG of a stored measurement."""
        return self._request("GET", f"/v1/measurements/{measurement_id}/overlay.png").content

    # -- tracking ------------------------------------------------------------------------
    def track(self, holder: str | None = None, filter: bool = True,
              anchor_lag: int | None = None) -> Track:
        """Open a tracking session for one approach (``POST /v1/tracks``); close it with
        :meth:`Track.close` or a ``with`` block."""
        body = {"filter": filter} | ({"holder": holder} if holder else {}) | (
            {} if anchor_lag is None else {"anchor_lag": anchor_lag})
        return Track(self, self._request("POST", "/v1/tracks", json=body).json())

    def ready(self) -> bool:
        """Workers up and cell loaded."""
        try:
            return self._http.get("/ready").status_code == 200
        except self._httpx.TransportError:
            return False

    # -- plumbing ------------------------------------------------------------------------
    def _request(self, method: str, url: str, retry: bool = True, **kw):
        httpx = self._httpx
        for attempt in range(self.retries + 1):
            last = attempt == self.retries or not retry
            try:
                r = self._http.request(method, url, **kw)
            except httpx.TransportError as e:
                if last:
                    raise ServiceError(0, "connection", str(e)) from e
                time.sleep(min(0.2 * 2 ** attempt, 5.0))
                continue
            if r.status_code == 503 and not last:
                time.sleep(_retry_after(r))
                continue
            if r.status_code >= 400:
                try:
                    b = r.json()
                    err, msg = b.get("error", "error"), b.get("message", r.text)
                except ValueError:
                    err, msg = "error", r.text
                raise ServiceError(r.status_code, err, msg)
            return r
        raise AssertionError("unreachable")  # pragma: no cover


class Track:
    """A tracking session of the service (:meth:`Client.track`): ``id``, ``info`` (as
    opened)."""

    def __init__(self, client: Client, info: dict):
        self._client, self.info, self.id = client, info, info["id"]

    def frame(self, image, flange_pose=None, content_type: str | None = None) -> dict:
        """The next frame's answer (``TrackFrameOut``: mode, pose, std, robot, ...). Not
        retried: a frame sent twice would be tracked twice.

        Raises
        ------
        ServiceError
            Any error answer (404: the session was closed or expired).
        """
        body, ctype, params = _body(image, content_type)
        if flange_pose is not None:
            params["flange_pose"] = _pose_row(flange_pose)
        return self._client._request("POST", f"/v1/tracks/{self.id}/frames", retry=False,
                                     params=params, content=body,
                                     headers={"Content-Type": ctype}).json()

    def status(self) -> dict:
        """The session now (frames answered, last mode)."""
        return self._client._request("GET", f"/v1/tracks/{self.id}").json()

    def close(self) -> None:
        """Close the session (already closed or expired: nothing to do)."""
        try:
            self._client._request("DELETE", f"/v1/tracks/{self.id}")
        except ServiceError as e:
            if e.status != 404:
                raise

    def __enter__(self) -> Track:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _body(image, content_type: str | None) -> tuple[bytes, str, dict]:
    """(body, content type, raw size parameters) of an image: a file path, encoded bytes
    (with ``content_type``) or a 2-D ``uint8`` array (sent raw)."""
    if isinstance(image, np.ndarray):
        a = np.ascontiguousarray(image)
        if a.ndim != 2 or a.dtype != np.uint8:
            raise CutterposeError("an array image must be 2-D uint8 (grey)")
        return a.tobytes(), "application/octet-stream", {"width": a.shape[1],
                                                         "height": a.shape[0]}
    if isinstance(image, (bytes, bytearray)):
        if content_type is None:
            raise CutterposeError("bytes need content_type (image/png, image/tiff, "
                                  "image/jpeg)")
        return bytes(image), content_type, {}
    p = Path(image)
    ctype = content_type or _CONTENT_TYPES.get(p.suffix.lower())
    if ctype is None:
        raise CutterposeError(f"{p}: unknown image type (give content_type)")
    return p.read_bytes(), ctype, {}


def _pose_row(flange_pose) -> str:
    return ",".join(repr(float(x)) for x in flange_pose)


def _retry_after(r) -> float:
    try:
        return min(max(float(r.headers.get("Retry-After", "1")), 0.0), 30.0)
    except ValueError:
        return 1.0
