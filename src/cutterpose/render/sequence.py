"""Approach sequences: the camera on the robot moving towards the holder, one image per frame.

The camera goes from ``z_start_mm`` (~900 mm) to ``z_end_mm`` (~600 mm, the working distance)
in ``n_frames`` frames at constant velocity, while the lateral offset and the tilt shrink
linearly (the robot lining up with the holder). Every frame is rendered by an *engine*
(:data:`ENGINES`; ``analytic``, :func:`cutterpose.render.analytic.render_holder`, for now; a
physically based field renderer plugs in under its own name with the same signature) with the
same surface (``seed``) and fresh sensor noise per frame. The camera's auto exposure keeps the
face's grey level: the light's ``light_dn`` is scaled by ``(Z / 600 mm)^2`` (the inverse-square
fall-off of the light at the camera).

Test events: ``drop`` removes frames (the sequence skips them, as a lost GigE frame) and
``jump_at`` shifts every pose from that frame on by ``jump_mm`` (a sudden move of the robot).

Convention:
    Poses ``T_cam_holder`` (:mod:`cutterpose.geometry.pose`). The output folder is an image set
    (PROTOCOL.md, "Image set") with a ``"sequence"`` block: the frame index of every image
    before drops, the dropped frames and the jump.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path

import cv2
import numpy as np

from ..errors import InputError
from ..geometry.camera import Camera, default_camera
from ..geometry.holder import Holder, default_holder
from ..geometry.pose import Pose
from .analytic import D_REF_MM, RenderSettings, preset, render_holder

__all__ = ["ENGINES", "engine", "approach_poses", "render_sequence"]


def _pbr_engine(*args, **kwargs):
    """The field renderer (``render/pbr.py``), when it is there."""
    try:
        from . import pbr  # type: ignore[attr-defined]
    except ImportError:
        raise InputError("render engine 'pbr' is not available in this build (render/pbr.py "
                         "missing)") from None
    fn = getattr(pbr, "render_holder", None)
    if fn is None:
        raise InputError("render engine 'pbr': render/pbr.py has no render_holder(pose, camera, "
                         "holder, settings, seed, noise_seed)")
    return fn(*args, **kwargs)


#: name -> ``render(pose, camera, holder, settings, seed=, noise_seed=) -> Rendered``
ENGINES: dict[str, Callable] = {"analytic": render_holder, "pbr": _pbr_engine}


def engine(name: str) -> Callable:
    try:
        return ENGINES[name]
    except KeyError:
        raise InputError(f"unknown render engine {name!r}; choose one of "
                         f"{', '.join(ENGINES)}") from None


def approach_poses(n_frames: int = 60, z_start_mm: float = 900.0, z_end_mm: float = 600.0,
                   start_dof: tuple = (4.0, -3.0, 2.5, 30.0, -20.0),
                   end_dof: tuple = (1.0, -0.5, 0.5, 6.0, -4.0),
                   drop: tuple = (), jump_at: int | None = None,
                   jump_mm: tuple = (30.0, 0.0, 0.0)) -> tuple[list[Pose], list[int]]:
    """The poses of an approach and the frame index of each (drops removed).

    ``start_dof`` / ``end_dof``: (alpha, beta, gamma [deg], X, Y [mm]) at the first and last
    frame, linear in between, as Z.
    """
    if n_frames < 2:
        raise InputError(f"an approach needs at least 2 frames, got {n_frames}")
    if min(z_start_mm, z_end_mm) <= 0:
        raise InputError("z_start_mm and z_end_mm must be positive")
    f = np.linspace(0.0, 1.0, n_frames)
    s, e = np.asarray(start_dof, float), np.asarray(end_dof, float)
    dof = s[None, :] + f[:, None] * (e - s)[None, :]
    z = z_start_mm + f * (z_end_mm - z_start_mm)
    bad = [d for d in drop if not 0 <= d < n_frames]
    if bad:
        raise InputError(f"dropped frames {bad} are not in 0..{n_frames - 1}")
    poses, index = [], []
    for k in range(n_frames):
        if k in drop:
            continue
        t = np.array([dof[k, 3], dof[k, 4], z[k]])
        if jump_at is not None and k >= jump_at:
            t = t + np.asarray(jump_mm, float)
        poses.append(Pose.from_euler(dof[k, 0], dof[k, 1], dof[k, 2], *t))
        index.append(k)
    return poses, index


def _frame(args):
    """Render one frame (a job of :func:`cutterpose.parallel.run_jobs`): (entry, PNG bytes)."""
    i, k, pose, camera, holder, settings, eng, seed = args
    s = settings.with_(light_dn=settings.light_dn * (float(pose.t_mm[2]) / D_REF_MM) ** 2)
    noise = int(np.random.SeedSequence([seed, 1, k]).generate_state(1)[0])
    r = engine(eng)(pose, camera, holder, s, seed=seed, noise_seed=noise)
    name = f"frame_{i:04d}.png"
    ok, png = cv2.imencode(".png", r.image)
    if not ok:  # pragma: no cover
        raise InputError(f"could not encode {name}")
    entry = r.truth_dict(name) | {"frame": int(k)}
    return entry, png.tobytes()


def render_sequence(out_dir, n_frames: int = 60, z_start_mm: float = 900.0,
                    z_end_mm: float = 600.0, camera: Camera | None = None,
                    holder: Holder | None = None, settings: RenderSettings | str = "easy",
                    seed: int = 0, engine_name: str = "analytic", drop: tuple = (),
                    jump_at: int | None = None, jump_mm: tuple = (30.0, 0.0, 0.0),
                    workers: int = 1, scheduler=None, progress=None) -> Path:
    """Render an approach (module doc) into ``out_dir`` with its ``truth.json``; returns the
    path of ``truth.json``. ``progress(done, total)`` after each frame."""
    from ..parallel import run_jobs

    camera = default_camera("table1") if camera is None else camera
    holder = default_holder() if holder is None else holder
    settings = preset(settings) if isinstance(settings, str) else settings
    engine(engine_name)
    poses, index = approach_poses(n_frames, z_start_mm, z_end_mm, drop=tuple(drop),
                                  jump_at=jump_at, jump_mm=jump_mm)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    jobs = [(i, k, p, camera, holder, settings, engine_name, int(seed))
            for i, (k, p) in enumerate(zip(index, poses))]
    done = [0]

    def write(i, result):
        entry, png = result
        (out / entry["file"]).write_bytes(png)
        done[0] += 1
        if progress is not None:
            progress(done[0], len(jobs))

    images = run_jobs(_frame, jobs, workers, scheduler, write, store=lambda r: r[0])
    doc = {"camera": camera.to_dict(), "holder": holder.to_dict(), "seed": int(seed),
           "presets": {settings.name: asdict(settings)},
           "sequence": {"n_frames": n_frames, "z_start_mm": z_start_mm, "z_end_mm": z_end_mm,
                        "engine": engine_name, "dropped": sorted(int(d) for d in drop),
                        "jump_at": jump_at, "jump_mm": list(jump_mm) if jump_at is not None
                        else None, "auto_exposure": "light_dn * (Z / 600 mm)^2"},
           "images": images}
    path = out / "truth.json"
    path.write_text(json.dumps(doc, indent=1))
    return path
