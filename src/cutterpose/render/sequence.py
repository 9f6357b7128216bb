"""Approach sequences: the camera on the robot moving towards the holder, one image per frame.

The camera goes from ``z_start_mm`` (~900 mm) to ``z_end_mm`` (~600 mm, the working distance)
in ``n_frames`` frames at constant velocity, while the lateral offset and the tilt shrink
linearly (the robot lining up with the holder). Every frame is rendered by an *engine*
(:data:`ENGINES`: ``analytic``, :func:`cutterpose.render.analytic.render_holder` with its
presets, or ``pbr``, the Mitsuba path tracer :func:`cutterpose.render.pbr.render_holder` with
the field presets ``sharp``/``new``/``worn``, extra ``[field]``) with the same surface
(``seed``: the same holder, cutter, slurry and textures) and fresh sensor noise (and Monte
Carlo samples) per frame. The camera's auto exposure keeps the
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
from .analytic import RenderSettings, auto_exposed, preset, render_holder

__all__ = ["ENGINES", "PRESET_LOOKUP", "engine", "engine_preset", "approach_poses",
           "render_sequence", "render_frame"]


def _pbr_module():
    """``render/pbr.py`` with Mitsuba importable, or a typed error saying what to install."""
    from . import pbr

    pbr.load_mitsuba()   # MitsubaMissingError (an InputError-like CutterposeError) if absent
    return pbr


def _pbr_engine(pose, camera, holder, settings, seed=0, noise_seed=None, spp=None):
    """The field renderer (:func:`cutterpose.render.pbr.render_holder`, Mitsuba 3; the
    optional extra ``[field]``)."""
    return _pbr_module().render_holder(pose, camera, holder, settings, seed=seed,
                                       noise_seed=noise_seed, spp=spp)


def _pbr_preset(name: str):
    from .pbr import field_preset

    return field_preset(name)


#: name -> ``render(pose, camera, holder, settings, seed=, noise_seed=) -> Rendered``
ENGINES: dict[str, Callable] = {"analytic": render_holder, "pbr": _pbr_engine}
#: name -> the engine's preset lookup (``analytic.preset``: RenderSettings, ``pbr``:
#: FieldPreset) and its default preset
PRESET_LOOKUP: dict[str, tuple[Callable, str]] = {"analytic": (preset, "easy"),
                                                  "pbr": (_pbr_preset, "new")}


def engine(name: str) -> Callable:
    try:
        return ENGINES[name]
    except KeyError:
        raise InputError(f"unknown render engine {name!r}; choose one of "
                         f"{', '.join(ENGINES)}") from None


def engine_preset(engine_name: str, name: str | None):
    """The render settings named ``name`` for ``engine_name`` (None: the engine's default)."""
    engine(engine_name)
    lookup, default = PRESET_LOOKUP[engine_name]
    return lookup(default if name is None else name)


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


def render_frame(args):
    """Render one frame (a job of :func:`cutterpose.parallel.run_jobs`): (entry, PNG bytes)."""
    i, k, pose, camera, holder, settings, eng, seed = args[:8]
    extra = args[8] if len(args) > 8 else {}
    s = settings.with_(light_dn=auto_exposed(settings.light_dn, pose))
    noise = int(np.random.SeedSequence([seed, 1, k]).generate_state(1)[0])
    r = engine(eng)(pose, camera, holder, s, seed=seed, noise_seed=noise, **extra)
    name = f"frame_{i:04d}.png"
    ok, png = cv2.imencode(".png", r.image)
    if not ok:  # pragma: no cover
        raise InputError(f"could not encode {name}")
    entry = r.truth_dict(name) | {"frame": int(k)}
    return entry, png.tobytes()


def render_sequence(out_dir, n_frames: int = 60, z_start_mm: float = 900.0,
                    z_end_mm: float = 600.0, camera: Camera | None = None,
                    holder: Holder | None = None, settings: RenderSettings | str | None = None,
                    seed: int = 0, engine_name: str = "analytic", drop: tuple = (),
                    jump_at: int | None = None, jump_mm: tuple = (30.0, 0.0, 0.0),
                    workers: int = 1, scheduler=None, progress=None,
                    spp: int | None = None) -> Path:
    """Render an approach (module doc) into ``out_dir`` with its ``truth.json``; returns the
    path of ``truth.json``. ``settings``: the engine's settings or preset name (None: the
    engine's default, ``easy`` / ``new``); ``spp``: pbr samples per pixel (None: the
    preset's). ``progress(done, total)`` after each frame.

    Raises
    ------
    InputError
        Unknown engine or preset; ``spp`` with the analytic engine; pbr in several local
        processes (Mitsuba uses every core itself).
    MitsubaMissingError
        ``engine_name="pbr"`` without Mitsuba 3 (the extra ``[field]``).
    """
    from ..parallel import run_jobs

    camera = default_camera("table1") if camera is None else camera
    holder = default_holder() if holder is None else holder
    if settings is None or isinstance(settings, str):
        settings = engine_preset(engine_name, settings)
    else:
        engine(engine_name)
    extra = {}
    if engine_name == "pbr":
        if workers > 1 and scheduler is None:
            raise InputError("the pbr engine renders in one process (Mitsuba uses every core "
                             "itself); use workers=1 or a cluster scheduler")
        _pbr_module()   # fail now, not in the first job, when Mitsuba is missing
        if spp is not None:
            extra["spp"] = int(spp)
    elif spp is not None:
        raise InputError("spp is a pbr option (the analytic engine does not sample)")
    poses, index = approach_poses(n_frames, z_start_mm, z_end_mm, drop=tuple(drop),
                                  jump_at=jump_at, jump_mm=jump_mm)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    jobs = [(i, k, p, camera, holder, settings, engine_name, int(seed), extra)
            for i, (k, p) in enumerate(zip(index, poses))]
    done = [0]

    def write(i, result):
        entry, png = result
        (out / entry["file"]).write_bytes(png)
        done[0] += 1
        if progress is not None:
            progress(done[0], len(jobs))

    images = run_jobs(render_frame, jobs, workers, scheduler, write, store=lambda r: r[0])
    doc = {"camera": camera.to_dict(), "holder": holder.to_dict(), "seed": int(seed),
           "presets": {settings.name: asdict(settings)},
           "sequence": {"n_frames": n_frames, "z_start_mm": z_start_mm, "z_end_mm": z_end_mm,
                        "engine": engine_name, "spp": extra.get("spp"),
                        "dropped": sorted(int(d) for d in drop),
                        "jump_at": jump_at, "jump_mm": list(jump_mm) if jump_at is not None
                        else None, "auto_exposure": "light_dn * (Z / 600 mm)^2"},
           "images": images}
    path = out / "truth.json"
    path.write_text(json.dumps(doc, indent=1))
    return path
