"""The camera and sensor model both renderers share: the normalised coordinates of every pixel
(:func:`normalized_grid`), the ring light's beam profile and vignetting
(:func:`light_falloff`), Lambert + Blinn-Phong shading at a point light at the camera
(:func:`shade_points`), defocus blur (:func:`defocus`), shot and read noise to 8 bits
(:func:`add_sensor_noise`, EMVA 1288) and fractal value noise for textures
(:func:`fractal_noise`). Radiometry: :mod:`cutterpose.render.analytic`."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np

from ..errors import InputError
from ..geometry.camera import Camera
from .analytic_presets import RenderSettings

__all__ = ["D_REF_MM", "normalized_grid", "light_falloff", "shade_points", "defocus",
           "add_sensor_noise", "fractal_noise"]

#: the distance (mm) at which a white frontal Lambertian patch images at ``light_dn``
D_REF_MM = 600.0


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
