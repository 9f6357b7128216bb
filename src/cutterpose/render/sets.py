"""The set writers: ``count`` images at random poses into a folder with its ``truth.json``
(PROTOCOL.md, exchange formats), by the analytic renderer (:func:`render_set`, with a
difficulty mix, on local processes or a Dask cluster) or by the pbr renderer
(:func:`render_field_set`, resumable, several views of one holder)."""

from __future__ import annotations

import json
from dataclasses import asdict, replace
from pathlib import Path

import cv2
import numpy as np

from ..errors import InputError
from ..geometry.camera import Camera, default_camera
from ..geometry.holder import Holder, default_holder
from ..geometry.pose import Pose
from .analytic import render_holder
from .analytic_presets import PRESETS, preset
from .draws import auto_exposed, distance_doc, random_pose
from .pbr import render_field
from .pbr_presets import FieldPreset, field_preset

__all__ = ["DEFAULT_MIX", "render_set", "render_field_set"]

# ------------------------------------------------------------------------------------------
#: difficulty mix of ``render_set`` (preset name, weight)
DEFAULT_MIX = (("easy", 0.35), ("dim", 0.15), ("worn", 0.15), ("occluded", 0.1),
               ("blurred", 0.1), ("hard", 0.15))



def _set_item(args) -> tuple[dict, bytes]:
    """Render image ``i`` of a set; returns its ``truth.json`` entry and the PNG file's bytes
    (the caller writes it, so workers on other machines need no access to ``out_dir``)."""
    i, seed, camera, holder, names, p, max_angle_deg, max_shift_mm, given, distance_mm = args
    img_seed = int(np.random.SeedSequence([seed, i]).generate_state(1)[0])
    rng = np.random.default_rng(img_seed)
    pose = random_pose(rng, max_angle_deg, max_shift_mm, distance_mm)
    if given is not None:   # drawn all the same, so the rest of the image is the same set's
        pose = given
    name = names[int(rng.choice(len(names), p=p))]
    settings = PRESETS[name]
    if distance_mm is not None:
        settings = replace(settings, light_dn=auto_exposed(settings.light_dn, pose))
    r = render_holder(pose, camera, holder, settings, seed=img_seed)
    fname = f"img_{i:04d}.png"
    ok, png = cv2.imencode(".png", r.image)
    if not ok:  # pragma: no cover - PNG encoding of a uint8 image does not fail
        raise InputError(f"could not encode {fname}")
    return r.truth_dict(fname), png.tobytes()


def render_set(count: int, seed: int, out_dir, camera: Camera | None = None,
               holder: Holder | None = None, mix=DEFAULT_MIX, max_angle_deg: float = 10.0,
               max_shift_mm: float = 20.0, progress=None, workers: int = 1,
               scheduler=None, poses: list[Pose] | None = None,
               distance_mm: tuple[float, float] | None = None) -> Path:
    """Render ``count`` images at random poses into ``out_dir`` with its ``truth.json``.

    ``poses``: the ``T_cam_holder`` of each image instead (``count`` of them), e.g. a holder
    seen from the stations of a robot cell. ``distance_mm``: (near, far) depths drawn
    uniformly instead of 600 +- ``max_shift_mm``, the light auto-exposed
    (:func:`auto_exposed`).

    The difficulty of each image is drawn from ``mix`` (preset names and weights) and recorded
    under ``"difficulty"``; image ``i`` uses the seed ``SeedSequence([seed, i])``, so any image
    can be re-rendered alone and the set does not depend on where it was rendered (``workers``
    local processes or the Dask cluster at ``scheduler``, :mod:`cutterpose.parallel`).
    ``progress(done, count)`` is called after each image. Returns the path of ``truth.json``.
    """
    from ..parallel import run_jobs

    if count < 1:
        raise InputError(f"count must be >= 1, got {count}")
    camera = default_camera("table1") if camera is None else camera
    holder = default_holder() if holder is None else holder
    names = [m[0] for m in mix]
    for n in names:
        preset(n)
    p = np.array([m[1] for m in mix], float)
    p /= p.sum()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if poses is not None and len(poses) != count:
        raise InputError(f"{len(poses)} poses given for {count} images")
    jobs = [(i, seed, camera, holder, names, p, max_angle_deg, max_shift_mm,
             None if poses is None else poses[i], distance_mm) for i in range(count)]
    written = [0]

    def write(i, result):
        entry, png = result
        try:
            (out / entry["file"]).write_bytes(png)
        except OSError as e:
            raise InputError(f"{out}: could not write {entry['file']} ({e})") from None
        written[0] += 1
        if progress is not None:
            progress(written[0], count)

    images = run_jobs(_set_item, jobs, workers, scheduler, write, store=lambda r: r[0])
    doc = {"camera": camera.to_dict(), "holder": holder.to_dict(), "seed": seed,
           "presets": {n: asdict(PRESETS[n]) for n in names}, "images": images}
    doc |= distance_doc(distance_mm)
    path = out / "truth.json"
    path.write_text(json.dumps(doc, indent=1))
    return path


def render_field_set(count: int, seed: int, out_dir, preset: FieldPreset | str = "new",
                     camera: Camera | None = None, holder: Holder | None = None,
                     variant: str | None = None, spp: int | None = None,
                     max_angle_deg: float = 10.0, max_shift_mm: float = 20.0,
                     progress=None, resume: bool = False,
                     distance_mm: tuple[float, float] | None = None, views: int = 1) -> Path:
    """Render ``count`` pbr images at random poses (PROTOCOL.md, real-image experiment) into
    ``out_dir`` with its ``truth.json`` (rewritten after every image, so a set that is still
    rendering can already be read). Image ``i`` uses the seed ``SeedSequence([seed, i])``.
    ``resume``: keep the images of an interrupted run of the same set (same seed and preset,
    file present) and render the rest. ``distance_mm``: (near, far) depths drawn uniformly
    instead of 600 +- ``max_shift_mm``, the light auto-exposed as in ``render-sequence``.

    ``views``: each holder seen from this many random poses (what a retake sees: the same
    wear, chips, slurry and textures, another viewpoint, and the ring light with it). Image
    ``i`` is view ``v = i % views`` of holder ``h = i // views``; view 0 is image ``h`` of the
    plain set with the same seed (scene, pose and noise), view ``v >= 1`` the same scene at a
    pose and with noise from ``SeedSequence([seed, h, v, 1])``; ``truth.json`` names both
    (``holder_index``, ``view``)."""
    if count < 1:
        raise InputError(f"count must be >= 1, got {count}")
    if views < 1:
        raise InputError(f"views must be >= 1, got {views}")
    camera = default_camera("table1") if camera is None else camera
    holder = default_holder() if holder is None else holder
    preset = field_preset(preset) if isinstance(preset, str) else preset
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    doc = {"camera": camera.to_dict(), "holder": holder.to_dict(), "seed": seed,
           "engine": "pbr", "presets": {preset.name: asdict(preset)}, "images": []}
    doc |= distance_doc(distance_mm)
    if views > 1:
        doc["views"] = int(views)
    path = out / "truth.json"
    done = {}
    if resume and path.is_file():
        old = json.loads(path.read_text())
        if (old.get("seed") == seed and set(old.get("presets", {})) == {preset.name}
                and old.get("views", 1) == views):
            done = {e["file"]: e for e in old["images"] if (out / e["file"]).is_file()}
    for i in range(count):
        if f"img_{i:04d}.png" in done:
            doc["images"].append(done[f"img_{i:04d}.png"])
            continue
        h, v = divmod(i, views)
        img_seed = int(np.random.SeedSequence([seed, h]).generate_state(1)[0])
        noise_seed = (None if v == 0
                      else int(np.random.SeedSequence([seed, h, v, 1]).generate_state(1)[0]))
        pose = random_pose(np.random.default_rng(img_seed if noise_seed is None else noise_seed),
                           max_angle_deg, max_shift_mm, distance_mm)
        lit = (preset if distance_mm is None
               else preset.with_(light_dn=auto_exposed(preset.light_dn, pose)))
        r = render_field(pose, camera, holder, lit, seed=img_seed, variant=variant, spp=spp,
                         noise_seed=noise_seed)
        fname = f"img_{i:04d}.png"
        if not cv2.imwrite(str(out / fname), r.image):
            raise InputError(f"{out}: could not write {fname}")
        entry = r.truth_dict(fname)
        if views > 1:
            entry |= {"holder_index": h, "view": v}
        doc["images"].append(entry)
        tmp = path.with_suffix(".json.tmp")
        tmp.write_text(json.dumps(doc, indent=1))
        tmp.replace(path)
        if progress is not None:
            progress(i + 1, count)
    return path

