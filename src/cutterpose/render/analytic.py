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
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np

from ..errors import InputError
from ..geometry.camera import Camera, default_camera
from ..geometry.holder import Holder, default_holder
from ..geometry.pose import Pose

__all__ = [
    "RenderSettings", "PRESETS", "preset", "Rendered", "render_holder", "render_set",
    "random_pose", "add_sensor_noise", "defocus", "light_falloff", "shade_points",
    "fractal_noise", "normalized_grid", "save_rendered", "auto_exposed", "distance_doc",
]

D_REF_MM = 600.0

# surface labels of the label image (pocket walls: WALL + edge index, so that the edge between
# two walls is antialiased too)
BACKGROUND, TOP, FLOOR, CUTTERHEAD, OUTER_WALL, WALL = 0, 1, 2, 3, 4, 10


@dataclass(frozen=True)
class RenderSettings:
    """Everything that sets the look of a rendered image (geometry, light, surface, sensor).

    Grey levels are DN of the 8-bit image; lengths in mm; angles in degrees.
    """

    name: str = "easy"
    # geometry
    pocket_depth_mm: float = 80.0
    cutterhead_depth_mm: float = 30.0
    # light at the camera
    light_dn: float = 230.0          # E: white frontal Lambertian patch at 600 mm
    ambient_dn: float = 3.0
    beam_sigma_deg: float = 40.0     # Gaussian beam profile of the lamp
    vignetting_power: float = 2.0    # v = cos(theta)^p
    specular: float = 0.25           # k_s
    shininess: float = 25.0          # m
    # surfaces (albedo)
    top_albedo: float = 0.78
    wall_albedo: float = 0.30
    floor_albedo: float = 0.06
    outer_wall_albedo: float = 0.25
    cutterhead_albedo: float = 0.09
    # texture of the top face
    texture: float = 0.08            # relative std of the mottled albedo
    machining_marks: float = 0.06    # relative amplitude of the fly-cutting arcs
    scratches: int = 30
    corrosion: float = 0.08          # fraction of the top face under corrosion blotches
    corrosion_darkening: float = 0.3
    edge_wear_mm: float = 0.0        # mean width of the worn band along the inner contour
    edge_wear_darkening: float = 0.7
    # broken pocket edge (real geometry, ray-traced): a quarter-cylinder fillet ("round") or a
    # 45 deg chamfer of radius / leg edge_radius_mm along each pocket edge, the radius of edge k
    # drawn uniformly in edge_radius_mm * (1 +- edge_radius_spread)
    edge_radius_mm: float = 0.0
    edge_radius_spread: float = 0.0
    edge_shape: str = "round"
    # occlusion: number of corners partly covered by a lump of muck in front of the holder
    occluded_corners: int = 0
    occluder_radius_px: float = 55.0
    # field conditions (issue 10): lumps of slurry across the middle of edges, and their grey
    # range (dark muck by default; a face-bright lump has no contrast to the face)
    edge_lumps: int = 0
    lump_dn: tuple = (15.0, 50.0)
    # a bright worn disc cutter in the pocket, seen edge-on: an ellipse of these semi-axes
    # (holder X, Y, mm) round the pocket's centre, ``cutter_height_mm`` in front of the top
    # face (towards the camera), so that from an oblique view it hides part of the walls and
    # of the edge; 0 = no cutter
    cutter_semi_axes_mm: tuple = (0.0, 0.0)
    cutter_height_mm: float = 40.0
    cutter_dn: float = 200.0
    # optics and sensor
    defocus_sigma_px: float = 0.8
    defocus_kernel: str = "gaussian"  # or "disk" (radius = 2 sigma)
    electrons_per_dn: float = 12.0
    read_noise_dn: float = 1.2
    # antialiasing: samples per edge pixel (an N-rooks pattern)
    aa_samples: int = 16

    def with_(self, **changes) -> RenderSettings:
        """A copy with some fields changed."""
        return replace(self, **changes)


PRESETS: dict[str, RenderSettings] = {
    "easy": RenderSettings(),
    "dim": RenderSettings(name="dim", light_dn=120.0, beam_sigma_deg=28.0, electrons_per_dn=4.0,
                          read_noise_dn=2.5, ambient_dn=1.5),
    "worn": RenderSettings(name="worn", edge_wear_mm=4.0, corrosion=0.25, scratches=120,
                           corrosion_darkening=0.5,
                           texture=0.14, machining_marks=0.08),
    "occluded": RenderSettings(name="occluded", occluded_corners=1),
    "blurred": RenderSettings(name="blurred", defocus_sigma_px=2.5, defocus_kernel="disk"),
    # field conditions (issue 10): cutterhead of the same steel nearly flush with the face, a
    # bright disc cutter in the pocket ...
    "cutter": RenderSettings(name="cutter", cutterhead_albedo=0.7, cutterhead_depth_mm=3.0,
                             cutter_semi_axes_mm=(175.0, 32.0)),
    # ... and slurry: lumps across two edges and over one corner, more corrosion
    "field": RenderSettings(name="field", cutterhead_albedo=0.7, cutterhead_depth_mm=3.0,
                            cutter_semi_axes_mm=(175.0, 32.0), edge_lumps=2,
                            occluded_corners=1, corrosion=0.18, scratches=80,
                            lump_dn=(15.0, 120.0)),
    # broken edges of a new holder (0.5-1.5 mm) and rounded worn ones (1.5-4.5 mm)
    "new": RenderSettings(name="new", edge_radius_mm=1.0, edge_radius_spread=0.5),
    "rounded": RenderSettings(name="rounded", edge_radius_mm=3.0, edge_radius_spread=0.5,
                              corrosion=0.25, corrosion_darkening=0.5, texture=0.14),
    "hard": RenderSettings(name="hard", light_dn=140.0, beam_sigma_deg=30.0, electrons_per_dn=5.0,
                           read_noise_dn=2.5, edge_wear_mm=4.0, corrosion=0.25, scratches=120,
                           corrosion_darkening=0.5,
                           texture=0.14, machining_marks=0.08, occluded_corners=1,
                           defocus_sigma_px=1.5),
}


def preset(name: str) -> RenderSettings:
    """The named preset (``easy``, ``dim``, ``worn``, ``occluded``, ``blurred``, ``hard``,
    ``cutter``, ``field``, ``new``, ``rounded``)."""
    try:
        return PRESETS[name]
    except KeyError:
        raise InputError(f"unknown render preset {name!r}; choose one of "
                         f"{', '.join(PRESETS)}") from None


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
# camera grid
_GRID_CACHE: dict[str, tuple[np.ndarray, np.ndarray]] = {}


def normalized_grid(camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Normalised coordinates ``(x_n, y_n)`` (float32, (H, W)) of every pixel centre.

    Undistorts the pixel grid once per camera (cached; the two most recent cameras are kept).
    """
    key = json.dumps(camera.to_dict(), sort_keys=True)
    if key not in _GRID_CACHE:
        w, h = camera.image_size_px
        xn = np.empty((h, w), np.float32)
        yn = np.empty((h, w), np.float32)
        u = np.arange(w, dtype=float)
        step = max(1, 2**20 // w)  # row blocks of ~1 Mpx keep the float64 temporaries small
        for r0 in range(0, h, step):
            r = np.arange(r0, min(h, r0 + step), dtype=float)
            px = np.stack(np.broadcast_arrays(u[None, :], r[:, None]), axis=-1)
            m = camera.normalize_px(px)
            xn[r0:r0 + len(r)] = m[..., 0]
            yn[r0:r0 + len(r)] = m[..., 1]
        while len(_GRID_CACHE) >= 2:
            _GRID_CACHE.pop(next(iter(_GRID_CACHE)))
        _GRID_CACHE[key] = (xn, yn)
    return _GRID_CACHE[key]


# ------------------------------------------------------------------------------------------
# low-level helpers (reused by the calibration plate renderer)
def light_falloff(xn, yn, settings: RenderSettings) -> np.ndarray:
    """Beam profile times vignetting over the field angle of normalised coordinates.

    ``b(theta) v(theta) = exp(-theta^2 / (2 sigma_b^2)) cos(theta)^p`` with
    ``cos(theta) = 1 / sqrt(1 + x_n^2 + y_n^2)``.
    """
    xn = np.asarray(xn, np.float32)
    yn = np.asarray(yn, np.float32)
    cos_field = 1.0 / np.sqrt(1.0 + xn * xn + yn * yn)
    theta = np.arccos(np.clip(cos_field, 0.0, 1.0))
    sb = np.float32(math.radians(settings.beam_sigma_deg))
    return (np.exp(-0.5 * (theta / sb) ** 2) * cos_field ** settings.vignetting_power).astype(
        np.float32)


def shade_points(cos_incidence, distance_mm, albedo, gloss, falloff,
                 settings: RenderSettings) -> np.ndarray:
    """Grey level (float32, DN, unclipped) of surface points lit by the light at the camera.

    ``I = E falloff (d_ref / d)^2 (rho cos i + k_s g cos^m i) + a``; ``cos_incidence`` below 0
    (surface facing away) counts as 0.
    """
    c = np.clip(np.asarray(cos_incidence, np.float32), 0.0, 1.0)
    d = np.asarray(distance_mm, np.float32)
    s = settings
    brdf = albedo * c + np.float32(s.specular) * gloss * c ** np.float32(s.shininess)
    return (np.float32(s.light_dn) * falloff * (np.float32(D_REF_MM) / d) ** 2 * brdf
            + np.float32(s.ambient_dn)).astype(np.float32)


def defocus(img: np.ndarray, sigma_px: float, kernel: str = "gaussian") -> np.ndarray:
    """Defocus blur of a float image: Gaussian of std ``sigma_px`` or pill-box of radius
    ``2 sigma_px`` (a defocused circular aperture), both through OpenCV."""
    if sigma_px <= 0:
        return img
    img = np.asarray(img, np.float32)
    if kernel == "gaussian":
        return cv2.GaussianBlur(img, (0, 0), sigma_px, borderType=cv2.BORDER_REFLECT)
    if kernel == "disk":
        r = 2.0 * sigma_px
        n = int(math.ceil(r)) + 1
        y, x = np.mgrid[-n:n + 1, -n:n + 1]
        # coverage of each kernel pixel by the disc, from its centre distance (1-px ramp)
        k = np.clip(r + 0.5 - np.hypot(x, y), 0.0, 1.0).astype(np.float32)
        return cv2.filter2D(img, -1, k / k.sum(), borderType=cv2.BORDER_REFLECT)
    raise InputError(f"defocus kernel must be 'gaussian' or 'disk', got {kernel!r}")


def add_sensor_noise(img: np.ndarray, settings: RenderSettings,
                     rng: np.random.Generator) -> np.ndarray:
    """Irradiance in DN (float) -> noisy 8-bit image.

    Shot noise: the signal in electrons ``N = I k`` (``k = electrons_per_dn``) is Poisson below
    ``N = 8`` and the Gaussian ``N + sqrt(N) z`` above (numpy's Poisson draw costs 0.1 s per Mpx,
    ten times the Gaussian, and a dim image has most of its pixels below 20 electrons; from 8
    electrons on the two differ by a skewness below 0.35, i.e. fractions of a grey level).
    Read noise: Gaussian of std ``read_noise_dn``. Rounded and clipped to 0..255.
    """
    k = float(settings.electrons_per_dn)
    sig = np.clip(np.asarray(img, np.float32), 0.0, None)
    if k > 0:
        e = sig * np.float32(k)
        out = e + np.sqrt(e) * rng.standard_normal(sig.shape, dtype=np.float32)
        low = np.flatnonzero(e < 8.0)
        if low.size:
            out.flat[low] = rng.poisson(e.flat[low]).astype(np.float32)
        out /= np.float32(k)
    else:
        out = sig.copy()
    if settings.read_noise_dn > 0:
        out += np.float32(settings.read_noise_dn) * rng.standard_normal(sig.shape, np.float32)
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


def fractal_noise(shape, rng: np.random.Generator, scale_px: float, octaves: int = 4,
                  persistence: float = 0.5) -> np.ndarray:
    """Smooth random field of zero mean and unit std (float32): octaves of upsampled white
    noise, the coarsest with features of ``scale_px`` texels."""
    h, w = shape
    acc = np.zeros((h, w), np.float32)
    amp = 1.0
    s = float(scale_px)
    for _ in range(octaves):
        gh, gw = max(2, int(h / s) + 2), max(2, int(w / s) + 2)
        g = rng.standard_normal((gh, gw), dtype=np.float32)
        acc += np.float32(amp) * cv2.resize(g, (w, h), interpolation=cv2.INTER_CUBIC)
        amp *= persistence
        s = max(1.0, s / 2.0)
    acc -= acc.mean()
    return acc / max(float(acc.std()), 1e-6)


def _sample(tex: np.ndarray, u, v) -> np.ndarray:
    """Bilinear lookup of ``tex`` at texel coordinates ``(u, v)`` (any shape, reflected at the
    border) through ``cv2.remap``, which needs 2-D maps below 32767 on a side."""
    u = np.asarray(u, np.float32)
    v = np.asarray(v, np.float32)
    shape = u.shape
    n = u.size
    if n == 0:
        return np.zeros(shape, np.float32)
    w = 1024
    rows = -(-n // w)
    pad = rows * w - n
    mu = np.concatenate([u.ravel(), np.zeros(pad, np.float32)]).reshape(rows, w)
    mv = np.concatenate([v.ravel(), np.zeros(pad, np.float32)]).reshape(rows, w)
    out = cv2.remap(tex, mu, mv, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    return out.ravel()[:n].reshape(shape)


# ------------------------------------------------------------------------------------------
# the scene
class _Texture:
    """A float32 texture over a rectangle of a surface's own 2-D coordinates (mm)."""

    def __init__(self, data: np.ndarray, x0_mm: float, y0_mm: float, texel_mm: float):
        self.data = data
        self.x0, self.y0, self.texel = x0_mm, y0_mm, texel_mm

    def __call__(self, x_mm, y_mm) -> np.ndarray:
        return _sample(self.data, (x_mm - self.x0) / self.texel, (y_mm - self.y0) / self.texel)


class _Scene:
    """Geometry, pose and textures of one image."""

    def __init__(self, pose: Pose, holder: Holder, settings: RenderSettings,
                 rng: np.random.Generator, texel_mm: float = 0.25):
        self.pose, self.holder, self.s = pose, holder, settings
        self.texel_mm = float(texel_mm)
        R = pose.R
        self.Rt = R.T.astype(np.float64)
        self.o_h = -R.T @ pose.t_mm
        if self.o_h[2] >= 0:
            raise InputError("the camera must look at the top face of the holder (the camera "
                             f"centre is at Z = {self.o_h[2]:.1f} mm in the holder frame; it must "
                             "be on the -Z side)")
        c = holder.corners_mm
        self.edges = np.stack([c, np.roll(c, -1, axis=0)], axis=1)  # (N, 2, 2)
        d = self.edges[:, 1] - self.edges[:, 0]
        self.inward = np.column_stack([-d[:, 1], d[:, 0]]) / np.linalg.norm(d, axis=1)[:, None]
        self.arc0 = np.concatenate([[0.0], np.cumsum(np.linalg.norm(d, axis=1))[:-1]])
        a, b = holder.outer_length_x_mm / 2, holder.outer_width_y_mm / 2
        self.a, self.b = a, b
        rect = holder.outer_rectangle_mm
        self.rect_edges = np.stack([rect, np.roll(rect, -1, axis=0)], axis=1)
        dr = self.rect_edges[:, 1] - self.rect_edges[:, 0]
        self.rect_outward = np.column_stack([dr[:, 1], -dr[:, 0]]) / np.linalg.norm(
            dr, axis=1)[:, None]
        self.rect_arc0 = np.concatenate([[0.0], np.cumsum(np.linalg.norm(dr, axis=1))[:-1]])
        self._make_textures(rng)
        r_edge = rng.spawn(1)[0]  # after the textures' streams: they stay as they were
        self.edge_radius = np.zeros(len(c))
        if settings.edge_radius_mm > 0:
            if settings.edge_shape not in ("round", "chamfer"):
                raise InputError("edge_shape must be 'round' or 'chamfer', got "
                                 f"{settings.edge_shape!r}")
            self.edge_radius = settings.edge_radius_mm * (
                1.0 + settings.edge_radius_spread * r_edge.uniform(-1, 1, len(c)))
        self.edge_len = np.linalg.norm(d, axis=1)
        self.edge_dir = d / self.edge_len[:, None]

    # --- textures --------------------------------------------------------------------------
    def _make_textures(self, rng: np.random.Generator):
        s, a, b = self.s, self.a, self.b
        # one stream per surface: a setting of one surface does not reshuffle the others
        rng, r_floor, r_cut, r_wall = rng.spawn(4)
        margin = 10.0
        texel = self.texel_mm
        t = 0.25 / texel  # texture scales below are written in texels of 0.25 mm
        w = int(math.ceil((2 * a + 2 * margin) / texel))
        h = int(math.ceil((2 * b + 2 * margin) / texel))
        x0, y0 = -a - margin, -b - margin
        X = (x0 + (np.arange(w, dtype=np.float32) + 0.5) * texel)[None, :]
        Y = (y0 + (np.arange(h, dtype=np.float32) + 0.5) * texel)[:, None]
        alb = 1.0 + s.texture * (0.7 * fractal_noise((h, w), rng, 160 * t, 5)
                                 + 0.3 * fractal_noise((h, w), rng, 12 * t, 3))
        gloss = np.ones((h, w), np.float32)
        # fly-cutting marks: arcs round a cutter centre off the part; a jittered pitch of about
        # a millimetre (a few pixels) and a slow beat between passes. The marks modulate the
        # specular lobe more than the albedo: that is what makes machined steel look machined.
        cx, cy = rng.uniform(-1.5, 1.5) * a, rng.choice([-1, 1]) * rng.uniform(2.5, 4.0) * b
        r = np.sqrt((X - cx) ** 2 + (Y - cy) ** 2)
        pitch = rng.uniform(0.8, 1.6)
        phase = 2 * np.pi * (r / pitch) + 1.5 * fractal_noise((h, w), rng, 200 * t, 2)
        beat = 0.5 + 0.5 * np.sin(2 * np.pi * r / rng.uniform(15.0, 40.0))
        # marks finer than two texels average out within a pixel: fade them
        fade = float(np.clip(pitch / (2 * texel) - 1.0, 0.0, 1.0))
        marks = fade * (np.sin(phase) + 0.5 * np.sin(2 * phase + 1.0)) * (0.5 + beat)
        alb += s.machining_marks * marks
        gloss *= np.clip(1.0 + 3.0 * s.machining_marks * marks, 0.0, None)
        # fine streaks along the cutting direction (noise blurred along X)
        streak = cv2.GaussianBlur(rng.standard_normal((h, w), dtype=np.float32), (0, 0),
                                  sigmaX=6.0 * t, sigmaY=max(0.5, 0.6 * t))
        alb += 0.5 * s.texture * streak / max(float(streak.std()), 1e-6)
        # scratches: thin antialiased lines, a little brighter or darker than the steel
        scr = np.zeros((h, w), np.float32)
        for _ in range(int(s.scratches)):
            p = np.array([rng.uniform(0, w), rng.uniform(0, h)])
            ang = rng.uniform(0, np.pi)
            ln = rng.uniform(5.0, 100.0) / texel
            q = p + ln * np.array([np.cos(ang), np.sin(ang)])
            cv2.line(scr, (int(p[0] * 16), int(p[1] * 16)), (int(q[0] * 16), int(q[1] * 16)),
                     float(rng.choice([-1.0, 1.0]) * rng.uniform(0.15, 0.35)), 1, cv2.LINE_AA, 4)
        alb += scr
        # corrosion blotches: thresholded low-frequency noise, dark, dull and pitted
        if s.corrosion > 0:
            f = fractal_noise((h, w), rng, 240 * t, 5)
            thr = np.quantile(f[::8, ::8], 1.0 - s.corrosion)
            blot = np.clip((f - thr) / 0.35, 0.0, 1.0)
            grain = 0.5 + 0.5 * np.clip(fractal_noise((h, w), rng, 6 * t, 3), -1, 1)
            pits = (rng.random((h, w), dtype=np.float32) < 0.004 / t**2 * blot).astype(np.float32)
            pits = cv2.GaussianBlur(pits, (0, 0), max(0.5, 0.7 * t)) * 2.5
            alb *= (1.0 - s.corrosion_darkening * blot * (0.6 + 0.4 * grain)) * np.clip(
                1.0 - pits, 0.2, 1.0)
            gloss *= 1.0 - 0.9 * blot
        # worn band along the inner contour: a rounded, chipped, dull edge of varying width.
        # Its normal turns away from the light, so it darkens towards the contour; chips are
        # bites of the band into the face.
        if s.edge_wear_mm > 0:
            pocket = np.zeros((h, w), np.uint8)
            pts = np.round((self.holder.corners_mm - [x0, y0]) / texel * 16).astype(np.int32)
            cv2.fillPoly(pocket, [pts], 1, cv2.LINE_8, 4)
            dist_mm = cv2.distanceTransform(1 - pocket, cv2.DIST_L2, 5) * texel
            width = s.edge_wear_mm * np.clip(1.0 + 0.7 * fractal_noise((h, w), rng, 120 * t, 3),
                                             0.15, 3.0)
            chips = np.clip(fractal_noise((h, w), rng, 10 * t, 2) - 1.2, 0.0, None) * 2.5
            width = width * (1.0 + chips)
            band = np.clip(1.0 - dist_mm / width, 0.0, 1.0) ** 0.8
            grime = 0.5 + 0.5 * np.clip(fractal_noise((h, w), rng, 4 * t, 2), -1, 1)
            alb *= 1.0 - s.edge_wear_darkening * band * (0.75 + 0.25 * grime)
            gloss *= 1.0 - band
        self.top_albedo = _Texture((s.top_albedo * np.clip(alb, 0.05, 2.0)).astype(np.float32),
                                   x0, y0, texel)
        self.top_gloss = _Texture(np.clip(gloss, 0, 1).astype(np.float32), x0, y0, texel)
        # floor and cutterhead: dark, greasy, coarse texture
        texel = 1.0
        w2, h2 = 1600, 1200
        ch = np.exp(0.35 * fractal_noise((h2, w2), r_cut, 150, 5)).astype(np.float32)
        self.cut_albedo = _Texture((s.cutterhead_albedo * ch).astype(np.float32),
                                   -w2 / 2, -h2 / 2, texel)
        fl = np.exp(0.35 * fractal_noise((int(2 * b) + 20, int(2 * a) + 20), r_floor, 40, 4))
        self.floor_albedo = _Texture((s.floor_albedo * fl).astype(np.float32), -a - 10, -b - 10,
                                     1.0)
        per = float(np.sum(np.linalg.norm(self.edges[:, 1] - self.edges[:, 0], axis=1)))
        per_o = 2 * (2 * a + 2 * b)
        # (depth, arc length) at 0.5 mm; reflected beyond 256 mm of depth
        wl = np.exp(0.3 * fractal_noise((512, int(max(per, per_o) * 2) + 4), r_wall, 30,
                                        4)).astype(np.float32)
        self.wall_tex = _Texture(wl, 0.0, 0.0, 0.5)

    # --- ray casting -----------------------------------------------------------------------
    def trace(self, xn: np.ndarray, yn: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Labels (uint8) and grey levels (float32 DN, before blur and noise) of the rays of
        normalised coordinates ``(xn, yn)`` (1-D float32 arrays)."""
        s = self.s
        xn = xn.astype(np.float32, copy=False)
        yn = yn.astype(np.float32, copy=False)
        Rt = self.Rt.astype(np.float32)
        o = self.o_h.astype(np.float32)
        dx = Rt[0, 0] * xn + Rt[0, 1] * yn + Rt[0, 2]
        dy = Rt[1, 0] * xn + Rt[1, 1] * yn + Rt[1, 2]
        dz = Rt[2, 0] * xn + Rt[2, 1] * yn + Rt[2, 2]
        norm_d = np.sqrt(1.0 + xn * xn + yn * yn)
        falloff = light_falloff(xn, yn, s)
        n = xn.size
        label = np.zeros(n, np.uint8)
        value = np.full(n, np.float32(s.ambient_dn), np.float32)
        ok = dz > 1e-6
        with np.errstate(divide="ignore", invalid="ignore"):
            s0 = np.where(ok, (0.0 - o[2]) / dz, np.nan).astype(np.float32)
        X0 = o[0] + s0 * dx
        Y0 = o[1] + s0 * dy
        in_rect = ok & (np.abs(X0) <= self.a) & (np.abs(Y0) <= self.b)
        in_pocket = np.zeros(n, bool)
        ir = np.flatnonzero(in_rect)
        in_pocket[ir] = _inside_axis_polygon(X0[ir], Y0[ir], self.edges)
        top = in_rect & ~in_pocket
        # cos(i) of a face with normal -Z: n . (-d/|d|) in the holder frame = dz / |d|
        cos_flat = dz / norm_d
        if self.edge_radius.max() > 0:
            self._trace_broken_edges(ok, top, in_pocket, X0, Y0, s0, (dx, dy, dz, norm_d),
                                     falloff, label, value)
        i = np.flatnonzero(top)
        if i.size:
            label[i] = TOP
            value[i] = shade_points(cos_flat[i], s0[i] * norm_d[i],
                                    self.top_albedo(X0[i], Y0[i]), self.top_gloss(X0[i], Y0[i]),
                                    falloff[i], s)
        # pocket: first wall crossed between Z = 0 and the floor, else the floor
        i = np.flatnonzero(in_pocket)
        if i.size:
            D = np.float32(s.pocket_depth_mm)
            s1 = (D - o[2]) / dz[i]
            X1, Y1 = o[0] + s1 * dx[i], o[1] + s1 * dy[i]
            frac, edge = _first_crossing(X0[i], Y0[i], X1, Y1, self.edges)
            wall = edge >= 0
            fl = i[~wall]
            label[fl] = FLOOR
            value[fl] = shade_points(cos_flat[fl], s1[~wall] * norm_d[fl],
                                     self.floor_albedo(X1[~wall], Y1[~wall]), np.float32(0.1),
                                     falloff[fl], s)
            wi = i[wall]
            if wi.size:
                e = edge[wall]
                label[wi] = WALL + e.astype(np.uint8)
                value[wi] = self._shade_wall(
                    wi, e, frac[wall], s1[wall], D, (X0, Y0, s0, X1[wall], Y1[wall]),
                    (dx, dy, norm_d, falloff), self.edges, self.inward, self.arc0,
                    s.wall_albedo)
        # outside the holder: its outer side walls, else the cutterhead
        i = np.flatnonzero(ok & ~in_rect)
        if i.size:
            C = np.float32(s.cutterhead_depth_mm)
            s1 = (C - o[2]) / dz[i]
            X1, Y1 = o[0] + s1 * dx[i], o[1] + s1 * dy[i]
            # only segments whose bounding box meets the rectangle can hit a side wall
            near = np.flatnonzero((np.minimum(X0[i], X1) <= self.a)
                                  & (np.maximum(X0[i], X1) >= -self.a)
                                  & (np.minimum(Y0[i], Y1) <= self.b)
                                  & (np.maximum(Y0[i], Y1) >= -self.b))
            frac = np.full(i.size, np.inf, np.float32)
            edge = np.full(i.size, -1, np.int64)
            frac[near], edge[near] = _first_crossing(X0[i[near]], Y0[i[near]], X1[near],
                                                     Y1[near], self.rect_edges)
            wall = edge >= 0
            ci = i[~wall]
            label[ci] = CUTTERHEAD
            value[ci] = shade_points(cos_flat[ci], s1[~wall] * norm_d[ci],
                                     self.cut_albedo(X1[~wall], Y1[~wall]), np.float32(0.1),
                                     falloff[ci], s)
            wi = i[wall]
            if wi.size:
                e = edge[wall]
                label[wi] = OUTER_WALL
                value[wi] = self._shade_wall(
                    wi, e, frac[wall], s1[wall], C, (X0, Y0, s0, X1[wall], Y1[wall]),
                    (dx, dy, norm_d, falloff), self.rect_edges, self.rect_outward,
                    self.rect_arc0, s.outer_wall_albedo)
        return label, value

    def _trace_broken_edges(self, ok, top, in_pocket, X0, Y0, s0, ray, falloff, label, value):
        """Rays that meet the broken pocket edge: shaded here and removed from ``top`` /
        ``in_pocket`` (edited in place); rays that cross the cut-away band and miss it go on
        into the pocket.

        In the local frame of edge k (``s`` outwards from the pocket, ``z`` depth, both 0 at the
        design edge) a ray leaving the plane ``Z = 0`` at ``s0`` goes ``s = s0 + mu d_s``,
        ``z = mu d_z`` (``mu`` in camera-depth units). Fillet (circle of radius r about
        ``(r, r)``, the quadrant ``s, z <= r``): the entry root of
        ``(d_s^2 + d_z^2) mu^2 + 2 ((s0 - r) d_s - r d_z) mu + (s0 - r)^2 = 0``; chamfer (the
        plane ``s + z = r``): ``mu = (r - s0) / (d_s + d_z)``.
        """
        dx, dy, dz, norm_d = ray
        rmax = float(self.edge_radius.max())
        # a ray reaches the break within a few radii of the edge (|d_s / d_z| < 1 in the rig)
        near = ok & (top | in_pocket)
        idx = np.flatnonzero(near)
        if not idx.size:
            return
        best = np.full(idx.size, np.inf)
        hit_e = np.full(idx.size, -1, np.int64)
        band = np.zeros(idx.size, bool)
        X, Y = X0[idx].astype(np.float64), Y0[idx].astype(np.float64)
        DX, DY, DZ = dx[idx].astype(np.float64), dy[idx].astype(np.float64), dz[idx].astype(
            np.float64)
        n_s = np.zeros(idx.size)
        n_z = np.zeros(idx.size)
        round_ = self.s.edge_shape == "round"
        for k, r in enumerate(self.edge_radius):
            o = -self.inward[k]
            tk = self.edge_dir[k]
            e0 = self.edges[k, 0]
            sk = (X - e0[0]) * o[0] + (Y - e0[1]) * o[1]
            tt = (X - e0[0]) * tk[0] + (Y - e0[1]) * tk[1]
            m = (sk > -3 * rmax - 1) & (sk < r) & (tt >= 0) & (tt <= self.edge_len[k])
            band |= m & (sk >= 0)
            j = np.flatnonzero(m)
            if not j.size:
                continue
            s_0, ds = sk[j], DX[j] * o[0] + DY[j] * o[1]
            dzj = DZ[j]
            with np.errstate(invalid="ignore", divide="ignore"):
                if round_:
                    A = ds * ds + dzj * dzj
                    B = (s_0 - r) * ds - r * dzj
                    disc = B * B - A * (s_0 - r) ** 2
                    mu = (-B - np.sqrt(disc)) / A
                else:
                    mu = (r - s_0) / (ds + dzj)
            ss, zz = s_0 + mu * ds, mu * dzj
            good = (np.isfinite(mu) & (mu >= 0) & (ss >= -1e-9) & (ss <= r + 1e-9)
                    & (zz <= r + 1e-9) & (mu < best[j]))
            g = j[good]
            best[g] = mu[good]
            hit_e[g] = k
            if round_:
                n_s[g], n_z[g] = (ss[good] - r) / r, (zz[good] - r) / r
            else:
                n_s[g], n_z[g] = -np.sqrt(0.5), -np.sqrt(0.5)
        hit = hit_e >= 0
        fi = idx[hit]
        top[idx[band]] = False
        in_pocket[idx[band & ~hit]] = True      # past the break's silhouette: into the pocket
        top[fi] = False
        in_pocket[fi] = False
        if not fi.size:
            return
        e = hit_e[hit]
        o = -self.inward[e]
        nx, ny, nz = n_s[hit] * o[:, 0], n_s[hit] * o[:, 1], n_z[hit]
        cos_i = -(nx * DX[hit] + ny * DY[hit] + nz * DZ[hit]) / norm_d[fi]
        mu = best[hit]
        Xh, Yh = X[hit] + mu * DX[hit], Y[hit] + mu * DY[hit]
        label[fi] = TOP
        value[fi] = shade_points(cos_i, (s0[fi] + mu) * norm_d[fi], self.top_albedo(Xh, Yh),
                                 self.top_gloss(Xh, Yh), falloff[fi], self.s)

    def _shade_wall(self, wi, e, f, s1, depth_mm, seg, ray, edges, normals, arc0, albedo):
        """Grey levels of rays ``wi`` that hit wall ``e`` at fraction ``f`` of their segment
        from the top plane (``X0, Y0`` at ray length ``s0``) to the plane ``depth_mm`` deep
        (``X1, Y1`` at ``s1``); the wall's normal ``normals[e]`` faces the camera side, and its
        texture runs along the outline (arc length from ``arc0``) and down the wall."""
        X0, Y0, s0, X1, Y1 = seg
        dx, dy, norm_d, falloff = ray
        sw = s0[wi] + f * (s1 - s0[wi])
        Xw = X0[wi] + f * (X1 - X0[wi])
        Yw = Y0[wi] + f * (Y1 - Y0[wi])
        nrm = normals[e].astype(np.float32)
        cos_w = -(nrm[:, 0] * dx[wi] + nrm[:, 1] * dy[wi]) / norm_d[wi]
        along = arc0[e].astype(np.float32) + np.hypot(Xw - edges[e, 0, 0], Yw - edges[e, 0, 1])
        alb = np.float32(albedo) * self.wall_tex(along, f * np.float32(depth_mm))
        return shade_points(cos_w, sw * norm_d[wi], alb, np.float32(0.5), falloff[wi], self.s)


def _inside_axis_polygon(X, Y, edges) -> np.ndarray:
    """Even-odd point-in-polygon test for a polygon with axis-parallel edges: count the edges
    parallel to Y crossed by the ray from ``(X, Y)`` towards +X (half-open in Y)."""
    inside = np.zeros(X.shape, bool)
    for (xa, ya), (xb, yb) in edges:
        if xa != xb:
            continue
        lo, hi = min(ya, yb), max(ya, yb)
        inside ^= (Y >= lo) & (Y < hi) & (X < xa)
    return inside


def _first_crossing(X0, Y0, X1, Y1, edges) -> tuple[np.ndarray, np.ndarray]:
    """First edge of an axis-parallel polygon crossed by the segments ``P0 -> P1``.

    Returns the fraction ``f`` in (0, 1] along the segment and the edge index (-1: none).
    """
    n = X0.shape[0]
    best = np.full(n, np.inf, np.float32)
    idx = np.full(n, -1, np.int64)
    DX, DY = X1 - X0, Y1 - Y0
    with np.errstate(divide="ignore", invalid="ignore"):
        for k, ((xa, ya), (xb, yb)) in enumerate(edges):
            if ya == yb:  # edge along X at y = ya
                f = (np.float32(ya) - Y0) / DY
                c = X0 + f * DX
                lo, hi = min(xa, xb), max(xa, xb)
            else:          # edge along Y at x = xa
                f = (np.float32(xa) - X0) / DX
                c = Y0 + f * DY
                lo, hi = min(ya, yb), max(ya, yb)
            hit = (f > 0) & (f <= 1) & (c >= lo) & (c <= hi) & (f < best)
            best[hit] = f[hit]
            idx[hit] = k
    return best, idx


# ------------------------------------------------------------------------------------------
def _rook_offsets(n: int) -> np.ndarray:
    """``n`` sub-pixel offsets in (-0.5, 0.5)^2, one per row and column of an n x n grid
    (N-rooks pattern): near-axis edges get n coverage levels instead of sqrt(n)."""
    k = np.arange(n)
    step = max(1, int(round(math.sqrt(n))))
    while math.gcd(step, n) != 1:
        step += 1
    return np.column_stack([(k + 0.5) / n - 0.5, ((k * step) % n + 0.5) / n - 0.5])


def _render_irradiance(scene: _Scene, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
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
    scene = _Scene(pose, holder, settings, r_scene, texel_mm)
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


# ------------------------------------------------------------------------------------------
#: difficulty mix of ``render_set`` (preset name, weight)
DEFAULT_MIX = (("easy", 0.35), ("dim", 0.15), ("worn", 0.15), ("occluded", 0.1),
               ("blurred", 0.1), ("hard", 0.15))


def random_pose(rng: np.random.Generator, max_angle_deg: float = 10.0,
                max_shift_mm: float = 20.0, distance_mm: tuple[float, float] | None = None
                ) -> Pose:
    """A pose drawn uniformly within +-``max_angle_deg`` and +-``max_shift_mm`` of the nominal
    pose (PROTOCOL.md, real-image experiment); with ``distance_mm`` = (near, far) the depth is
    drawn uniformly in it instead (the same draws: the angles and sideways shifts do not
    change)."""
    ang = rng.uniform(-max_angle_deg, max_angle_deg, 3)
    sh = rng.uniform(-max_shift_mm, max_shift_mm, 3)
    if distance_mm is None:
        z = D_REF_MM + sh[2]
    else:
        lo, hi = distance_mm
        z = lo + (hi - lo) * (sh[2] + max_shift_mm) / (2 * max_shift_mm)
    return Pose.from_euler(*ang, sh[0], sh[1], z)


def auto_exposed(light_dn: float, pose: Pose) -> float:
    """The light level (DN) of an auto-exposing camera at ``pose``: ``light_dn`` at 600 mm,
    scaled by ``(Z / 600 mm)^2`` so that the face keeps its grey level (render-sequence's and
    render-set's ``--distance-mm``)."""
    return light_dn * (float(pose.t_mm[2]) / D_REF_MM) ** 2


def distance_doc(distance_mm: tuple[float, float] | None) -> dict:
    """The ``truth.json`` keys of a set drawn over ``distance_mm`` = (near, far) depths and lit
    by :func:`auto_exposed` (none for the default 600 mm sets)."""
    if distance_mm is None:
        return {}
    return {"distance_mm": list(distance_mm),
            "auto_exposure": f"light_dn * (Z / {D_REF_MM:g} mm)^2"}


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
