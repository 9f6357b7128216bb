"""Tools to run the real service and load it: a reduced-resolution cell for tests, rendered
images, the service as a subprocess on a free loopback port, and a load run of concurrent
clients (``tests/test_service_live.py``, ``benchmarks/service_load.py``).

Every request goes to 127.0.0.1 only, every loop is bounded in count and time.

Convention:
    A reduced camera of factor ``f`` is the Table 1 camera with ``f x f`` pixels binned: pixel
    size times ``f``, principal point ``(c + 0.5) / f - 0.5`` (pixel (0, 0) is the centre of the
    top-left pixel), the same focal length and division coefficient (metric). Latencies in
    seconds; ``p50`` / ``p95`` are percentiles of the answered (200) attempts.
"""

from __future__ import annotations

import asyncio
import json
import os
import signal
import socket
import subprocess
import sys
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = ["reduced_camera_dict", "write_cell", "render_images", "ServerProcess",
           "LoadResult", "run_load", "free_port"]


def reduced_camera_dict(factor: int = 4) -> dict:
    """The Table 1 camera binned ``factor x factor`` (module doc), as a camera-file object."""
    from ..geometry.camera import default_camera

    d = default_camera("table1").to_dict()
    w, h = d["image_size_px"]
    cx, cy = d["principal_point_px"]
    return d | {"name": f"{d['name']}, binned {factor}x{factor}",
                "image_size_px": [w // factor, h // factor],
                "pixel_size_m": [p * factor for p in d["pixel_size_m"]],
                "principal_point_px": [(cx + 0.5) / factor - 0.5, (cy + 0.5) / factor - 0.5]}


def write_cell(folder, factor: int = 4, token: str | None = None, handeye: dict | None = None,
               method: str | None = None, edge_break_mm: float | None = 0.0, **service) -> Path:
    """A cell file in ``folder`` with the camera binned by ``factor`` (1: the bundled Table 1
    camera), data in ``folder/data``, and ``service`` settings; with ``token`` a token file,
    with ``handeye`` (a hand-eye object, PROTOCOL.md) a hand-eye file. ``method`` defaults to
    ``dm+b`` at full resolution and ``dm+`` on a binned camera (whose 1-2 px per mm cannot
    resolve the band of a broken edge). ``edge_break_mm``: the holder's break for the corner
    methods' verdict (default 0: :func:`render_images` draws sharp edges; None leaves it
    unknown)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    camera = "table1"
    if factor != 1:
        (folder / "camera.json").write_text(json.dumps(reduced_camera_dict(factor)))
        camera = "camera.json"
    service = {"data_dir": str(folder / "data")} | service
    if token is not None:
        (folder / "token.txt").write_text(token + "\n")
        service["token_file"] = "token.txt"
    method = method or ("dm+b" if factor == 1 else "dm+")
    lines = [f'name = "test cell, factor {factor}"', f'camera = "{camera}"',
             f'method = "{method}"']
    if handeye is not None:
        (folder / "handeye.json").write_text(json.dumps(handeye))
        lines.append('handeye = "handeye.json"')
    if edge_break_mm is not None:
        lines += ["", "[tolerances]", f"edge_break_mm = {float(edge_break_mm)!r}"]
    lines += ["", "[service]"]
    lines += [f"{k} = {json.dumps(v)}" for k, v in service.items()]
    path = folder / "cell.toml"
    path.write_text("\n".join(lines) + "\n")
    return path


def render_images(camera, n: int, seed: int = 0) -> list[bytes]:
    """``n`` PNG images of the holder at poses drawn in the rig's working range (+-5 deg,
    +-10 mm around the nominal pose), preset ``easy``."""
    import cv2

    from ..geometry.pose import Pose
    from ..render.analytic import render_holder

    rng = np.random.default_rng(seed)
    out = []
    for k in range(n):
        a, b, g = rng.uniform(-5, 5, 3)
        x, y, z = rng.uniform(-10, 10, 3)
        r = render_holder(Pose.from_euler(a, b, g, x, y, 600 + z), camera, None, "easy",
                          seed=seed + k)
        ok, buf = cv2.imencode(".png", r.image)
        out.append(buf.tobytes())
    return out


def free_port() -> int:
    """A free TCP port on 127.0.0.1 (released before the server binds it)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class ServerProcess:
    """``cutterpose serve`` as a subprocess on 127.0.0.1 and a free port.

    Parameters
    ----------
    cell : the cell file.
    token : put in ``CUTTERPOSE_TOKEN`` (None: the cell's token file).
    log_path : where stdout / stderr go.
    log_level : the server's (``info`` also logs the closed connections and refusals).
    """

    def __init__(self, cell, token: str | None = None, log_path=None, workers: int | None = None,
                 log_level: str = "warning"):
        self.cell, self.token, self.workers = Path(cell), token, workers
        self.log_level = log_level
        self.log_path = Path(log_path) if log_path else Path(cell).with_suffix(".log")
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.proc: subprocess.Popen | None = None
        self.worker_pids: set[int] = set()

    def start(self, timeout_s: float = 90.0) -> ServerProcess:
        import httpx

        env = dict(os.environ)
        env.pop("CUTTERPOSE_DATA_DIR", None)
        env.pop("CUTTERPOSE_TOKEN", None)  # else it would win over the cell's token file
        if self.token is not None:
            env["CUTTERPOSE_TOKEN"] = self.token
        cmd = [sys.executable, "-m", "cutterpose.cli", "serve", "--config", str(self.cell),
               "--port", str(self.port), "--log-level", self.log_level]
        if self.workers:
            cmd += ["--workers", str(self.workers)]
        self._log = open(self.log_path, "ab")
        self.proc = subprocess.Popen(cmd, stdout=self._log, stderr=subprocess.STDOUT, env=env)
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            if self.proc.poll() is not None:
                raise RuntimeError(f"server exited with {self.proc.returncode}: "
                                   f"{self.log_path.read_text()[-2000:]}")
            try:
                r = httpx.get(self.url + "/ready", timeout=2)
                if r.status_code == 200:
                    self.worker_pids |= {w["pid"] for w in r.json()["workers"]}
                    return self
            except httpx.TransportError:
                pass
            time.sleep(0.1)
        self.stop()
        raise RuntimeError(f"server not ready within {timeout_s} s")

    def ready(self) -> dict:
        import httpx

        r = httpx.get(self.url + "/ready", timeout=5).json()
        self.worker_pids |= {w["pid"] for w in r["workers"] if w["pid"]}
        return r

    def kill(self) -> None:
        """SIGKILL the server process (its workers see their pipe close and exit)."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGKILL)
            self.proc.wait(10)

    def stop(self, timeout_s: float = 20.0) -> None:
        """SIGTERM (graceful), then SIGKILL; then make sure no worker it started lives on."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10)
        self.reap_workers()
        if getattr(self, "_log", None):
            self._log.close()

    def reap_workers(self, timeout_s: float = 10.0) -> list[int]:
        """Wait for the workers this server started to exit; SIGKILL (by pid) any left.
        Returns the pids that had to be killed."""
        end = time.monotonic() + timeout_s
        left = [p for p in self.worker_pids if _alive(p)]
        while left and time.monotonic() < end:
            time.sleep(0.1)
            left = [p for p in left if _alive(p)]
        for p in left:
            try:
                os.kill(p, signal.SIGKILL)
            except ProcessLookupError:
                pass
        return left

    def __enter__(self) -> ServerProcess:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split(") ")[-1][:1] not in ("Z", "X")
    except OSError:
        return False


@dataclass
class LoadResult:
    """What a load run saw."""

    answers: dict = field(default_factory=dict)     #: request id -> 200 answer (dict)
    errors: list = field(default_factory=list)      #: (request id, status or exception text)
    latencies_s: list = field(default_factory=list)  #: per answered (200) attempt
    end_to_end_s: list = field(default_factory=list)  #: first attempt to 200, retries included
    refusals_503: int = 0
    wall_s: float = 0.0

    def summary(self) -> dict:
        lat = np.asarray(self.latencies_s) if self.latencies_s else np.full(1, np.nan)
        e2e = np.asarray(self.end_to_end_s) if self.end_to_end_s else np.full(1, np.nan)
        return {"answered": len(self.answers), "errors": len(self.errors),
                "refusals_503": self.refusals_503, "wall_s": round(self.wall_s, 2),
                "throughput_per_s": round(len(self.answers) / self.wall_s, 2)
                if self.wall_s else None,
                "latency_p50_ms": round(float(np.percentile(lat, 50)) * 1e3, 1),
                "latency_p95_ms": round(float(np.percentile(lat, 95)) * 1e3, 1),
                "end_to_end_p50_ms": round(float(np.percentile(e2e, 50)) * 1e3, 1),
                "end_to_end_p95_ms": round(float(np.percentile(e2e, 95)) * 1e3, 1)}


def run_load(url: str, token: str, images: list[bytes], n_clients: int = 100,
             n_total: int = 500, timeout_s: float = 600.0, max_attempts: int = 200
             ) -> LoadResult:
    """``n_clients`` concurrent clients (one connection each) send ``n_total`` measurements
    in all (image ``k % len(images)`` for request ``k``), each with its own request id; a
    ``503`` is retried after its ``Retry-After`` with the same id. Bounded: ``max_attempts``
    per request, ``timeout_s`` in all."""
    import httpx

    res = LoadResult()
    headers = {"Authorization": f"Bearer {token}", "Content-Type": "image/png"}
    jobs = list(range(n_total))

    async def client(k0: int):
        async with httpx.AsyncClient(base_url=url, headers=headers, timeout=120) as c:
            for k in jobs[k0::n_clients]:
                rid = f"load-{k}-{uuid.uuid4().hex[:8]}"
                first = time.perf_counter()
                for _ in range(max_attempts):
                    t0 = time.perf_counter()
                    try:
                        r = await c.post("/v1/measurements", params={"request_id": rid},
                                         content=images[k % len(images)])
                    except httpx.TransportError as e:
                        res.errors.append((rid, f"{type(e).__name__}: {e}"))
                        break
                    if r.status_code == 503:
                        res.refusals_503 += 1
                        await asyncio.sleep(min(float(r.headers.get("Retry-After", 1)), 60.0))
                        continue
                    if r.status_code == 200:
                        now = time.perf_counter()
                        res.latencies_s.append(now - t0)
                        res.end_to_end_s.append(now - first)
                        res.answers[rid] = r.json()
                    else:
                        res.errors.append((rid, r.status_code, r.text[:200]))
                    break
                else:
                    res.errors.append((rid, "503 on every attempt"))

    async def main():
        await asyncio.wait_for(asyncio.gather(*(client(i) for i in range(n_clients))),
                               timeout_s)

    t0 = time.perf_counter()
    asyncio.run(main())
    res.wall_s = time.perf_counter() - t0
    return res
