"""Realistic synthetic images of the disc cutter holder, ray-cast per pixel.

The scene is the holder of ``holder.json`` seen by a camera with a light at its centre, as on
the paper's test rig (seed paper, section 3.2, Fig. 6): a bright machined steel top face bounded
by the outer rectangle, a dark pocket behind the inner contour (vertical walls and a floor), and
the dark cutterhead around the holder. Every pixel's viewing ray is intersected with that
geometry in closed form; pixels on a geometric edge are supersampled, so the image edges sit
where the 20 true corners project (to a few hundredths of a pixel before blur and noise).

Convention:
    Holder frame (``holder.py``): top face at ``Z = 0``, ``+Z`` points *away* from the camera at
    the nominal pose ``R = I, t = (0, 0, 600) mm``, so the camera sits on the ``-Z`` side and
    everything behind the top face has ``Z > 0``:

    * top face: ``Z = 0``, inside the outer rectangle and outside the inner contour,
      normal ``-Z`` (towards the camera);
    * pocket: the prism over the inner contour from ``Z = 0`` to ``Z = pocket_depth_mm``; its
      walls face the pocket's inside, its floor at ``Z = pocket_depth_mm`` has normal ``-Z``;
    * outer side walls of the holder block, from ``Z = 0`` to ``Z = cutterhead_depth_mm``,
      facing outwards;
    * cutterhead: the plane ``Z = cutterhead_depth_mm`` outside the outer rectangle.

    A camera-frame ray ``d_cam = (x_n, y_n, 1)`` (normalised coordinates of an observed pixel,
    ``Camera.normalize_px``, so lens distortion is in the ray, not in a warp) becomes, in the
    holder frame, ``o_h + s d_h`` with ``o_h = -R^T t`` and ``d_h = R^T d_cam``; it meets the
    plane ``Z = z0`` at ``s = (z0 - o_h,z) / d_h,z``, where ``s`` is the camera depth in mm.
    Pixel ``(0, 0)`` is the centre of the top-left pixel (``camera.py``).

Radiometry:
    A point light at the camera centre (a ring light round the lens) gives, at a surface point
    at distance ``d`` with unit normal ``n`` and unit direction ``l`` towards the camera,

        I = E * b(theta) * v(theta) * (d_ref / d)^2 * (rho * cos(i) + k_s * g * cos(i)^m) + a

    with ``cos(i) = n . l`` (Lambert; the Blinn-Phong half vector equals ``l`` when light and
    eye coincide, hence the specular lobe ``cos(i)^m``), ``rho`` the albedo and ``g`` the gloss
    textures, ``b`` a Gaussian beam profile and ``v = cos(theta)^p`` the lens vignetting over the
    field angle ``theta``, ``E`` the grey level of a white frontal Lambertian patch at
    ``d_ref = 600 mm`` and ``a`` the ambient level. The sensor then adds shot noise (Poisson in
    electrons, ``electrons_per_dn`` per grey level) and Gaussian read noise, after a defocus blur
    of the irradiance (Gaussian or pill-box kernel).

References:
    Seed paper, sections 2.1 (threshold 70..255 of the holder image) and 3.2 (real images);
    Pharr, Jakob, Humphreys, *Physically Based Rendering*, 3rd ed., ch. 7 (supersampling) and
    ch. 8 (Lambert and Blinn-Phong); EMVA 1288 (shot and read noise model of a camera).
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path

import cv2
import numpy as np

from ..errors import InputError
from ..geometry.camera import Camera, default_camera
from ..geometry.holder import Holder, default_holder
from ..geometry.pose import Pose
from .analytic_presets import PRESETS, RenderSettings, preset
from .analytic_scene import AnalyticScene
from .draws import auto_exposed, distance_doc, random_pose
from .sensor import (
    add_sensor_noise,
    defocus,
    fractal_noise,
    light_falloff,
    normalized_grid,
    shade_points,
)

__all__ = [
    "RenderSettings", "PRESETS", "preset", "Rendered", "render_holder",
    "random_pose", "add_sensor_noise", "defocus", "light_falloff", "shade_points",
    "fractal_noise", "normalized_grid", "save_rendered", "auto_exposed", "distance_doc",
]


@dataclass
class Rendered:
    """A rendered image with its ground truth.

    Attributes
    ----------
    image : (H, W) uint8 grey image.
    corners_px : (N, 2) true observed (distorted) pixel positions of the holder's corners, in
        ``holder.json`` order.
    pose : the true pose ``T_cam_holder``.
    settings : the settings used.
    seed : the seed used.
    occluded_corners : indices of the corners partly covered by an occluder.
    """

    image: np.ndarray
    corners_px: np.ndarray
    pose: Pose
    settings: RenderSettings
    seed: int
    occluded_corners: list[int] = field(default_factory=list)
    #: (N,) radius of each pocket edge's break (mm; edge k from corner k to k + 1), if any
    edge_radius_mm: list[float] = field(default_factory=list)

    def truth_dict(self, file: str | None = None) -> dict:
        """The image's entry of an image-set ``truth.json`` (PROTOCOL.md, exchange formats)."""
        d = {"file": file} if file is not None else {}
        d.update({"R_cam_holder": self.pose.R.tolist(), "t_cam_holder_mm": self.pose.t_mm.tolist(),
                  "corners_px": self.corners_px.tolist(), "difficulty": self.settings.name,
                  "dof": self.pose.dof.tolist(), "seed": self.seed,
                  "occluded_corners": list(self.occluded_corners)})
        if self.edge_radius_mm:
            d["edge_radius_mm"] = [float(r) for r in self.edge_radius_mm]
        return d



# ------------------------------------------------------------------------------------------
def _rook_offsets(n: int) -> np.ndarray:
    """``n`` sub-pixel offsets in (-0.5, 0.5)^2, one per row and column of an n x n grid
    (N-rooks pattern): near-axis edges get n coverage levels instead of sqrt(n)."""
    k = np.arange(n)
    step = max(1, int(round(math.sqrt(n))))
    while math.gcd(step, n) != 1:
        step += 1
    return np.column_stack([(k + 0.5) / n - 0.5, ((k * step) % n + 0.5) / n - 0.5])


def _render_irradiance(scene: AnalyticScene, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free, unblurred grey levels (float32 (H, W)) and labels, supersampled on edges."""
    xn, yn = normalized_grid(camera)
    h, w = xn.shape
    value = np.empty((h, w), np.float32)
    label = np.empty((h, w), np.uint8)
    rows = max(1, 2**20 // w)
    for r0 in range(0, h, rows):
        sl = slice(r0, min(h, r0 + rows))
        lab, val = scene.trace(xn[sl].ravel(), yn[sl].ravel())
        value[sl] = val.reshape(-1, w)
        label[sl] = lab.reshape(-1, w)
    # pixels near a change of surface: average over sub-pixel rays
    ns = int(scene.s.aa_samples)
    if ns > 1:
        k = np.ones((3, 3), np.uint8)
        edge = cv2.dilate(label, k) != cv2.erode(label, k)
        edge = cv2.dilate(edge.view(np.uint8), k).astype(bool)
        vv, uu = np.nonzero(edge)
        off = _rook_offsets(ns)
        chunk = max(1, 2**20 // ns)
        for c0 in range(0, len(uu), chunk):
            u = uu[c0:c0 + chunk]
            v = vv[c0:c0 + chunk]
            px = np.stack([u[:, None] + off[None, :, 0], v[:, None] + off[None, :, 1]], axis=-1)
            m = camera.normalize_px(px.reshape(-1, 2)).astype(np.float32)
            _, val = scene.trace(m[:, 0], m[:, 1])
            value[v, u] = val.reshape(-1, ns).mean(axis=1)
    return value, label


def _occlude(value: np.ndarray, corners_px: np.ndarray, settings: RenderSettings,
             rng: np.random.Generator, n: int | None = None,
             shade_dn: tuple = (15.0, 50.0)) -> list[int]:
    """Paint lumps of muck (irregular, antialiased, grey in ``shade_dn``) over part of ``n``
    random points of ``corners_px`` (default: ``occluded_corners`` of the corners), in front
    of everything. Returns the indices of the covered points."""
    h, w = value.shape
    n = int(settings.occluded_corners) if n is None else int(n)
    if n <= 0:
        return []
    chosen = sorted(rng.choice(len(corners_px), size=min(n, len(corners_px)), replace=False))
    for ci in chosen:
        r0 = settings.occluder_radius_px * rng.uniform(0.7, 1.2)
        # centre offset so that the lump covers the corner but not all of its neighbourhood
        ang = rng.uniform(0, 2 * np.pi)
        c = corners_px[ci] + rng.uniform(0.4, 0.9) * r0 * np.array([np.cos(ang), np.sin(ang)])
        m = int(r0 * 1.8) + 3
        u0, v0 = int(c[0]) - m, int(c[1]) - m
        u1, v1 = int(c[0]) + m + 1, int(c[1]) + m + 1
        u0c, v0c, u1c, v1c = max(u0, 0), max(v0, 0), min(u1, w), min(v1, h)
        if u0c >= u1c or v0c >= v1c:
            continue
        vv, uu = np.mgrid[v0c:v1c, u0c:u1c].astype(np.float32)
        dx, dy = uu - c[0], vv - c[1]
        phi = np.arctan2(dy, dx)
        rad = np.full(phi.shape, r0, np.float32)
        for k in range(1, 6):  # irregular outline: a random Fourier series of the radius
            rad += r0 * rng.uniform(0.0, 0.25 / k) * np.cos(k * phi + rng.uniform(0, 2 * np.pi))
        cover = np.clip(rad - np.hypot(dx, dy) + 0.5, 0.0, 1.0)
        shade = rng.uniform(*shade_dn) + 10.0 * fractal_noise(cover.shape, rng, 20, 3)
        sub = value[v0c:v1c, u0c:u1c]
        sub[:] = (1 - cover) * sub + cover * shade
    return [int(i) for i in chosen]


def _paint_cutter(value: np.ndarray, pose: Pose, camera: Camera, settings: RenderSettings,
                  rng: np.random.Generator) -> None:
    """Paint the bright disc cutter (``cutter_semi_axes_mm``; module doc of the settings) in
    front of the pocket: its outline is an ellipse at ``Z = -cutter_height_mm`` projected
    through the camera, filled antialiased with a steel grey shaded across its width (a
    rounded rim) and mottled."""
    ax, ay = settings.cutter_semi_axes_mm
    if ax <= 0 or ay <= 0:
        return
    h, w = value.shape
    phi = np.linspace(0, 2 * np.pi, 180, endpoint=False)
    P = np.column_stack([ax * np.cos(phi), ay * np.sin(phi),
                         np.full(phi.shape, -settings.cutter_height_mm)])
    uv = camera.project(pose.apply(P))
    if not np.all(np.isfinite(uv)):
        return
    u0, v0 = np.maximum(np.floor(uv.min(axis=0)).astype(int) - 2, 0)
    u1, v1 = np.minimum(np.ceil(uv.max(axis=0)).astype(int) + 3, [w, h])
    if u0 >= u1 or v0 >= v1:
        return
    cover = np.zeros((v1 - v0, u1 - u0), np.float32)
    cv2.fillPoly(cover, [np.rint((uv - [u0, v0]) * 16).astype(np.int32)], 1.0, cv2.LINE_AA, 4)
    # shading across the rim: brightest along the ellipse's long axis
    c = camera.project(pose.apply(np.array([[0.0, 0.0, -settings.cutter_height_mm]])))[0]
    vv, uu = np.mgrid[v0:v1, u0:u1].astype(np.float32)
    half_px = max(float(np.ptp(uv[:, 1])) / 2, 1.0)
    across = np.clip(np.abs(vv - c[1]) / half_px, 0, 1)
    shade = settings.cutter_dn * (1.0 - 0.35 * across ** 2) * (
        1.0 + 0.08 * fractal_noise(cover.shape, rng, 30, 3))
    sub = value[v0:v1, u0:u1]
    sub[:] = (1 - cover) * sub + cover * shade


def render_holder(pose: Pose | None = None, camera: Camera | None = None,
                  holder: Holder | None = None, settings: RenderSettings | str | None = None,
                  seed: int = 0, noise_seed: int | None = None) -> Rendered:
    """Render an 8-bit grey image of the holder at ``pose``.

    Parameters
    ----------
    pose : the true pose ``T_cam_holder`` (default: the nominal pose).
    camera : any :class:`Camera` (default: the Table 1 division camera).
    holder : the holder model (default: ``holder.json``).
    settings : a :class:`RenderSettings` or the name of a preset (default ``"easy"``).
    seed : seeds every random choice (textures, occluders, noise): same seed, same image.
    noise_seed : if given, seeds the sensor noise instead (frames of one sequence: the same
        holder surface, fresh noise in every frame).

    Returns
    -------
    Rendered : the image, the true observed pixels of the corners, the pose.
    """
    pose = Pose.nominal() if pose is None else pose
    camera = default_camera("table1") if camera is None else camera
    holder = default_holder() if holder is None else holder
    if settings is None:
        settings = PRESETS["easy"]
    elif isinstance(settings, str):
        settings = preset(settings)
    # children are fixed by their index: the fourth stream leaves the first three unchanged
    r_scene, r_occ, r_noise, r_field = np.random.default_rng(seed).spawn(4)
    if noise_seed is not None:
        r_noise = np.random.default_rng(noise_seed)
    corners_px = camera.project(pose.apply(holder.points_holder_mm))
    # top-face texels of ~0.9 pixel footprint: finer is wasted, coarser blurs the steel
    texel_mm = max(0.1, 0.9 * float(pose.t_mm[2]) / camera.focal_px)
    scene = AnalyticScene(pose, holder, settings, r_scene, texel_mm)
    value, _ = _render_irradiance(scene, camera)
    _paint_cutter(value, pose, camera, settings, r_field)
    occluded = _occlude(value, corners_px, settings, r_occ)
    if settings.edge_lumps > 0:
        # lumps over the middle of edges (mid-points of the edges, projected)
        mid_mm = 0.5 * (holder.corners_mm + np.roll(holder.corners_mm, -1, axis=0))
        mids = camera.project(pose.apply(np.column_stack([mid_mm, np.zeros(len(mid_mm))])))
        _occlude(value, mids, settings, r_field, settings.edge_lumps, settings.lump_dn)
    value = defocus(value, settings.defocus_sigma_px, settings.defocus_kernel)
    image = add_sensor_noise(value, settings, r_noise)
    return Rendered(image, corners_px, pose, settings, int(seed), occluded,
                    [float(r) for r in scene.edge_radius] if scene.edge_radius.max() > 0
                    else [])


def save_rendered(rendered: Rendered, out_path, camera: Camera | None = None,
                  truth: bool = True) -> Path:
    """Write the PNG (``cv2.imwrite``) and, if ``truth``, ``<stem>.truth.json`` beside it
    (the one-image form of an image set's ``truth.json``). Returns the image path."""
    out = Path(out_path)
    out.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(out), rendered.image):
        raise InputError(f"{out}: could not write the image (unknown extension?)")
    if truth:
        camera = default_camera("table1") if camera is None else camera
        doc = {"camera": camera.to_dict(), "settings": asdict(rendered.settings),
               "images": [rendered.truth_dict(out.name)]}
        out.with_suffix(".truth.json").write_text(json.dumps(doc, indent=1))
    return out

