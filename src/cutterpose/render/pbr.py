"""Physically based images of the holder in field conditions (Mitsuba 3, optional extra
``[field]``).

The analytic renderer (``analytic.py``) paints wear, corrosion and muck onto the ideal holder;
this one builds them as geometry and materials and path-traces them, so that where the
intensity step of a rounded, chipped, dirty edge sits is decided by light transport, not by a
formula we would then be fitting:

* the holder's top face with the pocket of ``holder.json``, the pocket edge rounded (or
  chamfered) with a radius that varies smoothly along the contour, chips (ellipsoidal bites of
  the edge), vertical pocket walls and a dark floor ``pocket_depth_mm`` deep;
* a worn disc cutter in the pocket (ring + hub + shaft, a surface of revolution about an axle
  along the holder's Y axis at X = 0), protruding towards the camera above the top face;
* the cutterhead plate round the holder (a small height difference and gap, the same steel);
* slurry/sand lumps (displaced, flattened spheres), at least one across the pocket edge in
  ``worn``, sometimes over a corner;
* corrosion and wet patches as textures of the top face (albedo, roughness, metallic and a
  clear coat for the water film);
* a ring light round the lens (an annular area emitter in the camera plane), a path tracer with
  ``max_depth >= 4`` (real shadows and inter-reflections).

Convention (as ``analytic.py``):
    Holder frame: top face at ``Z = 0``, ``+Z`` away from the camera at the nominal pose; the
    pocket is the prism behind the inner contour. The design corners (the sharp intersection of
    the top plane with the walls) are the truth, whatever the edge looks like. The fillet of
    radius ``r`` starts on the top face at distance ``r`` from the design edge and meets the
    wall ``r`` deep: at distance ``s <= r`` from the contour the surface is
    ``Z = r - sqrt(r^2 - (r - s)^2)``; a chamfer of size ``c`` is ``Z = c - s``.

Camera:
    Mitsuba renders an ideal pinhole image with square pixels (focal ``f_y`` of the camera,
    principal point at the film centre, a field slightly larger than the distorted image); the
    image of the real (division-model) camera is resampled from it with ``cv2.remap`` through
    ``Camera.normalize_px``. The film uses a box filter, so a pixel is the mean radiance over its
    area and the linear interpolation of the resampling keeps a step edge where it is. Only a
    crop round the holder is rendered at full resolution with ``spp`` samples; the rest of the
    frame (the cutterhead plate) comes from a half-resolution render with few samples. Then the
    sensor of ``analytic.py``: lens vignetting ``cos^p``, defocus blur, shot and read noise,
    8 bit.

Radiometry:
    The ring light's radiance is scaled so that a white Lambertian patch facing the camera at
    600 mm images at ``light_dn`` DN (the same calibration as ``analytic.py``).

References:
    Seed paper, section 3.2 (the test rig: ring light at the lens); Zhang et al., Sensors 2023,
    23(3), 1536 (rounded-edge model of the worn holder); Jakob et al., Mitsuba 3 (2022);
    Pharr, Jakob, Humphreys, *Physically Based Rendering*, 3rd ed.; Burley, *Physically based
    shading at Disney* (2012) for the principled BSDF.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np

from ..errors import InputError
from ..geometry.camera import Camera, default_camera
from ..geometry.holder import Holder, default_holder
from ..geometry.pose import Pose
from .analytic_presets import RenderSettings
from .pbr_geometry import (
    build_geometry,
    edge_radius,
    edge_radius_stats,
    hidden_corners,
    surface_depth,
)
from .pbr_presets import FIELD_PRESETS, FieldPreset, draw_params, field_preset
from .pbr_scene import (
    MitsubaMissingError,
    build_scene,
    holder_crop,
    load_mitsuba,
    luminance,
    pinhole_film,
    ring_light,
    sensor_dict,
)
from .sensor import D_REF_MM, add_sensor_noise, defocus, normalized_grid

__all__ = [
    "FieldPreset", "FIELD_PRESETS", "field_preset", "MitsubaMissingError", "load_mitsuba",
    "draw_params", "build_geometry", "FieldRendered", "render_field", "render_holder",
    "save_field_rendered", "edge_step_offsets", "edge_radius", "edge_radius_stats",
    "hidden_corners", "surface_depth", "InputError",
]


@dataclass
class FieldRendered:
    """A pbr image with its ground truth (see :meth:`truth_dict`).

    ``value`` is the noise-free, unblurred grey level (float32 DN) the sensor starts from.
    """

    image: np.ndarray
    value: np.ndarray
    corners_px: np.ndarray
    pose: Pose
    params: dict
    seed: int
    hidden: dict
    edges: list
    timings_s: dict
    variant: str
    spp: int

    @property
    def hidden_corners(self) -> list[int]:
        return sorted(self.hidden)

    def truth_dict(self, file: str | None = None) -> dict:
        """The image's entry of an image set's ``truth.json`` (PROTOCOL.md; extra keys)."""
        d = {"file": file} if file is not None else {}
        d.update({"R_cam_holder": self.pose.R.tolist(), "t_cam_holder_mm": self.pose.t_mm.tolist(),
                  "corners_px": self.corners_px.tolist(), "difficulty": self.params["preset"],
                  "dof": self.pose.dof.tolist(), "seed": self.seed, "engine": "pbr",
                  "occluded_corners": self.hidden_corners,
                  "hidden_corners": {str(k): v for k, v in self.hidden.items()},
                  "edge_profile": self.params["profile"], "edges": self.edges,
                  "chips": self.params["chips"], "params": self.params,
                  "render": {"variant": self.variant, "spp": self.spp,
                             "seconds": {k: round(v, 3) for k, v in self.timings_s.items()}}})
        return d


def render_field(pose: Pose | None = None, camera: Camera | None = None,
                 holder: Holder | None = None, preset: FieldPreset | str = "new",
                 seed: int = 0, variant: str | None = None, spp: int | None = None,
                 params: dict | None = None, sensor: bool = True,
                 noise_seed: int | None = None) -> FieldRendered:
    """Path-trace one 8-bit image of the holder at ``pose`` in field conditions.

    Parameters
    ----------
    pose : the true pose ``T_cam_holder`` (default: nominal).
    camera : any camera (default: Table 1, division model).
    holder : the holder (default: ``holder.json``).
    preset : a :class:`FieldPreset` or its name (``sharp``, ``new``, ``worn``).
    seed : seeds the scene parameters, the Monte Carlo samples and the sensor noise.
    variant : Mitsuba variant (default: :func:`load_mitsuba`'s choice).
    spp : samples per pixel round the holder (default: the preset's).
    params : scene parameters (default: drawn by :func:`draw_params`).
    sensor : False leaves out blur and noise (``image`` is then the rounded ``value``).
    noise_seed : if given, seeds the Monte Carlo samples and the sensor noise instead of
        ``seed`` (frames of one sequence: the same scene, fresh noise in every frame).
    """
    t0 = time.perf_counter()
    mi = load_mitsuba(variant)
    pose = Pose.nominal() if pose is None else pose
    camera = default_camera("table1") if camera is None else camera
    holder = default_holder() if holder is None else holder
    preset = field_preset(preset) if isinstance(preset, str) else preset
    spp = int(preset.spp if spp is None else spp)
    r_par, r_noise, r_mc = np.random.default_rng(seed).spawn(3)
    if noise_seed is not None:
        r_noise, r_mc = np.random.default_rng(noise_seed).spawn(2)
    params = draw_params(preset, holder, r_par) if params is None else params
    if (-pose.R.T @ pose.t_mm)[2] >= 0:
        raise InputError("the camera must look at the top face of the holder (-Z side)")
    film = pinhole_film(camera)
    crop = holder_crop(pose, holder, params, film)
    bg_spp = max(1, int(preset.background_spp))
    sensors = [sensor_dict(mi, pose, film, bg_spp, scale=2),
               sensor_dict(mi, pose, film, spp, crop=crop)]
    # grid of the top face: about 0.8 of a pixel's footprint (not below 0.2 mm)
    step = float(np.clip(0.8 * pose.t_mm[2] / camera.focal_px, 0.2, 2.0))
    geometry = build_geometry(params, holder, step)
    scene, _ = build_scene(mi, params, holder, pose, sensors, preset.max_depth, geometry,
                           texel_mm=float(np.clip(step, 0.25, 2.0)))
    t1 = time.perf_counter()
    s_bg, s_crop = (int(x) for x in r_mc.integers(0, 2**31, 2))
    bg = luminance(mi.render(scene, sensor=0, seed=s_bg, spp=bg_spp))
    t2 = time.perf_counter()
    cr = luminance(mi.render(scene, sensor=1, seed=s_crop, spp=spp))
    t3 = time.perf_counter()
    full = cv2.resize(bg, (film.width, film.height), interpolation=cv2.INTER_LINEAR)
    _paste_feathered(full, cr, crop)
    value = _camera_image(full, film, camera, preset)
    if sensor:
        st = RenderSettings(name=f"pbr-{preset.name}", electrons_per_dn=preset.electrons_per_dn,
                            read_noise_dn=preset.read_noise_dn)
        image = add_sensor_noise(defocus(value, params["defocus_sigma_px"], "gaussian"), st,
                                 r_noise)
    else:
        image = np.clip(np.rint(value), 0, 255).astype(np.uint8)
    t4 = time.perf_counter()
    corners_px = camera.project(pose.apply(holder.points_holder_mm))
    hidden = hidden_corners(params, holder, pose, geometry)
    edges = edge_radius_stats(params, holder)
    t5 = time.perf_counter()
    tim = {"scene": t1 - t0, "render_background": t2 - t1, "render_crop": t3 - t2,
           "camera_sensor": t4 - t3, "truth": t5 - t4, "total": t5 - t0}
    return FieldRendered(image, value, corners_px, pose, params, int(seed), hidden, edges, tim,
                         mi.variant(), spp)


def _paste_feathered(full: np.ndarray, cr: np.ndarray, crop: tuple) -> None:
    """Paste the crop render ``cr`` into the film ``full`` at ``crop = (x0, y0, w, h)``,
    feathered over 16 px so that the seam, which lies on the cutterhead plate, does not show
    (no feathering at the film's own border)."""
    height, width = full.shape[:2]
    x0, y0, cw, ch = crop
    # feathered paste of the crop (the seam lies on the cutterhead plate)
    fe = 16.0
    wx = np.minimum(np.arange(cw) + 0.5, cw - np.arange(cw) - 0.5)
    wy = np.minimum(np.arange(ch) + 0.5, ch - np.arange(ch) - 0.5)
    if x0 == 0:
        wx[: cw // 2] = fe
    if x0 + cw == width:
        wx[cw // 2:] = fe
    if y0 == 0:
        wy[: ch // 2] = fe
    if y0 + ch == height:
        wy[ch // 2:] = fe
    w = np.clip(np.minimum(wy[:, None], wx[None, :]) / fe, 0.0, 1.0).astype(np.float32)
    sub = full[y0:y0 + ch, x0:x0 + cw]
    sub[:] = w * cr + (1.0 - w) * sub


def _camera_image(full: np.ndarray, film, camera: Camera, preset: FieldPreset) -> np.ndarray:
    """The camera's noise-free image (float32 DN) from the pinhole film's radiance: scaled so
    that a white Lambertian patch facing the camera at ``D_REF_MM`` images at ``light_dn``,
    resampled through the camera's distortion, vignetted."""
    ring = ring_light(Pose.nominal())
    A = 0.5 * np.linalg.norm(np.cross(ring.V[ring.F[:, 1]] - ring.V[ring.F[:, 0]],
                                      ring.V[ring.F[:, 2]] - ring.V[ring.F[:, 0]]), axis=1).sum()
    k = preset.light_dn * math.pi * D_REF_MM**2 / A
    xn, yn = normalized_grid(camera)
    mx = (film.f_px * xn + (film.width / 2 - 0.5)).astype(np.float32)
    my = (film.f_px * yn + (film.height / 2 - 0.5)).astype(np.float32)
    value = cv2.remap(full * np.float32(k), mx, my, cv2.INTER_LINEAR,
                      borderMode=cv2.BORDER_REPLICATE)
    value *= (1.0 / (1.0 + xn * xn + yn * yn)) ** np.float32(0.5 * preset.vignetting_power)
    return value


def render_holder(pose: Pose | None = None, camera: Camera | None = None,
                  holder: Holder | None = None, settings: FieldPreset | str = "new",
                  seed: int = 0, noise_seed: int | None = None, variant: str | None = None,
                  spp: int | None = None) -> FieldRendered:
    """:func:`render_field` with the signature of the analytic ``render_holder`` (the render
    engine ``pbr`` of :mod:`cutterpose.render.sequence`): ``settings`` is a
    :class:`FieldPreset` or its name, ``seed`` draws the scene (the same holder, cutter, slurry
    and textures in every frame of a sequence) and ``noise_seed`` the Monte Carlo samples and
    the sensor noise of the frame. Samples per pixel: ``spp``, else the preset's."""
    settings = field_preset(settings) if isinstance(settings, str) else settings
    return render_field(pose, camera, holder, settings, seed=seed, variant=variant, spp=spp,
                        noise_seed=noise_seed)


def save_field_rendered(r: FieldRendered, out_path, camera: Camera | None = None,
                        truth: bool = True) -> Path:
    """Write the PNG and, if ``truth``, ``<stem>.truth.json`` beside it."""
    out = Path(out_path)
    out.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(out), r.image):
        raise InputError(f"{out}: could not write the image (unknown extension?)")
    if truth:
        camera = default_camera("table1") if camera is None else camera
        doc = {"camera": camera.to_dict(), "engine": "pbr",
               "preset": asdict(field_preset(r.params["preset"]))
               if r.params["preset"] in FIELD_PRESETS else r.params["preset"],
               "images": [r.truth_dict(out.name)]}
        out.with_suffix(".truth.json").write_text(json.dumps(doc, indent=1))
    return out



# ------------------------------------------------------------------------------------------
# self-test: where is the intensity step relative to the projected design edge?
def edge_step_offsets(value: np.ndarray, pose: Pose, camera: Camera, holder: Holder,
                      half_px: float = 2.5, step_mm: float = 0.5, min_contrast: float = 20.0,
                      keep: float = 0.6) -> np.ndarray:
    """Signed sub-pixel offsets (px, positive = out of the pocket, onto the top face) of the
    intensity step from the projected design edge, per contour edge (median over the middle
    ``keep`` of the edge; NaN where no clean step is found).

    At points along each design edge the profile ``I(s)`` along the image normal is read over
    ``|s| <= half_px`` (exact bilinear, 0.01 px steps); with ``lo``/``hi`` its means over the
    outer half pixel at either end, the step sits at ``e = half_px - int (I - lo) / (hi - lo)
    ds``. This area estimate is exact for a box-filtered step whatever its sub-pixel phase
    (the 50 % crossing of a linearly interpolated box-filtered step is off by up to 0.09 px,
    depending on the phase)."""
    from scipy.ndimage import map_coordinates

    c = holder.corners_mm
    out = np.full(len(c), np.nan)
    ds = 0.01
    s = np.arange(-half_px, half_px + 1e-9, ds)
    end = int(round(0.5 / ds))  # samples in half a pixel
    for k, (p, q) in enumerate(zip(c, np.roll(c, -1, axis=0))):
        L = float(np.linalg.norm(q - p))
        e = (q - p) / L
        nrm = np.array([e[1], -e[0]])  # out of the pocket
        ts = np.arange(0.5 * (1 - keep) * L, 0.5 * (1 + keep) * L, step_mm)
        P = p + ts[:, None] * e
        uv = camera.project(pose.apply(np.column_stack([P, np.zeros(len(P))])))
        uo = camera.project(pose.apply(np.column_stack([P + 0.5 * nrm, np.zeros(len(P))])))
        n_img = uo - uv
        n_img /= np.linalg.norm(n_img, axis=1, keepdims=True)
        mx = uv[:, None, 0] + s[None, :] * n_img[:, None, 0]
        my = uv[:, None, 1] + s[None, :] * n_img[:, None, 1]
        prof = map_coordinates(np.asarray(value, np.float64), [my.ravel(), mx.ravel()], order=1,
                               mode="nearest").reshape(mx.shape)
        lo = prof[:, :end].mean(axis=1)
        hi = prof[:, -end:].mean(axis=1)
        ok = hi - lo >= min_contrast
        if ok.sum() < 5:
            continue
        frac = (prof[ok] - lo[ok, None]) / (hi[ok] - lo[ok])[:, None]
        area = (frac.sum(axis=1) - 0.5 * (frac[:, 0] + frac[:, -1])) * ds  # trapezoid
        out[k] = float(np.median(half_px - area))
    return out
