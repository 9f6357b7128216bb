"""The pbr renderer's field presets and the scene parameters drawn from them: edge profile
and radius along the contour, chips, the worn cutter, slurry lumps, corrosion and wet
patches, the cutterhead plate, light and sensor (:func:`draw_params`)."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..errors import InputError
from ..geometry.holder import Holder
from .pbr_geometry import inside_pocket, outward_normal, point_on_contour

__all__ = ["FieldPreset", "FIELD_PRESETS", "field_preset", "draw_params"]


@dataclass(frozen=True)
class FieldPreset:
    """Ranges the per-image parameters are drawn from (uniformly, from the image's seed).

    Lengths in mm; ``(lo, hi)`` pairs are ranges; counts are inclusive ranges.
    """

    name: str
    # pocket edge: the smallest and the largest radius along the contour of one image
    radius_lo_mm: tuple[float, float] = (0.0, 0.0)
    radius_hi_mm: tuple[float, float] = (0.0, 0.0)
    chamfer_probability: float = 0.0
    chips: tuple[int, int] = (0, 0)
    chip_depth_mm: tuple[float, float] = (1.0, 3.5)
    chip_length_mm: tuple[float, float] = (3.0, 12.0)
    # disc cutter
    cutter: bool = True
    cutter_radius_mm: tuple[float, float] = (165.0, 180.0)
    protrusion_mm: tuple[float, float] = (20.0, 50.0)
    # slurry lumps (at least ``slurry_across_edge`` of them across the pocket edge)
    slurry: tuple[int, int] = (0, 0)
    slurry_across_edge: int = 0
    slurry_on_corner_probability: float = 0.35
    # top face
    steel_albedo: tuple[float, float] = (0.6, 0.75)
    steel_roughness: tuple[float, float] = (0.5, 0.6)
    grime: float = 0.06
    corrosion: tuple[float, float] = (0.0, 0.0)
    wet_patches: tuple[int, int] = (0, 0)
    # cutterhead plate round the holder ("steel": the same steel; "dark": the lab's dark
    # surround)
    plate: str = "steel"
    plate_dz_mm: tuple[float, float] = (0.0, 3.0)
    plate_gap_mm: tuple[float, float] = (0.3, 1.5)
    pocket_depth_mm: float = 80.0
    # light and sensor
    light_dn: float = 250.0
    vignetting_power: float = 2.0
    defocus_sigma_px: tuple[float, float] = (0.6, 1.0)
    electrons_per_dn: float = 12.0
    read_noise_dn: float = 1.2
    # Monte Carlo
    spp: int = 12
    background_spp: int = 2
    max_depth: int = 5

    def with_(self, **changes) -> FieldPreset:
        return replace(self, **changes)


FIELD_PRESETS: dict[str, FieldPreset] = {
    # the lab: sharp edge, clean face, dark surround; the cutter is in the pocket
    "sharp": FieldPreset(name="sharp", plate="dark", plate_gap_mm=(2.0, 4.0), grime=0.04),
    # a new holder in the machine: machined edge break, slight corrosion, steel all round
    "new": FieldPreset(name="new", radius_lo_mm=(0.5, 0.8), radius_hi_mm=(1.0, 1.5),
                       chamfer_probability=0.4, corrosion=(0.02, 0.08)),
    # a holder after a drive: rounded and chipped, slurry, corrosion, wet patches
    "worn": FieldPreset(name="worn", radius_lo_mm=(1.5, 2.5), radius_hi_mm=(3.5, 5.0),
                        chips=(2, 6), slurry=(1, 4), slurry_across_edge=1,
                        protrusion_mm=(15.0, 45.0), steel_albedo=(0.5, 0.7),
                        steel_roughness=(0.55, 0.7), grime=0.12, corrosion=(0.1, 0.3),
                        wet_patches=(1, 4)),
}


def field_preset(name: str) -> FieldPreset:
    """The named pbr preset (``sharp``, ``new``, ``worn``)."""
    try:
        return FIELD_PRESETS[name]
    except KeyError:
        raise InputError(f"unknown pbr preset {name!r}; choose one of "
                         f"{', '.join(FIELD_PRESETS)}") from None



def _u(rng, rg) -> float:
    return float(rng.uniform(rg[0], rg[1])) if rg[1] > rg[0] else float(rg[0])


def draw_params(preset: FieldPreset, holder: Holder, rng: np.random.Generator) -> dict:
    """Draw one image's scene parameters (a JSON-able dict) from ``preset`` with ``rng``."""
    c = holder.corners_mm
    a, b = holder.outer_length_x_mm / 2, holder.outer_width_y_mm / 2
    p: dict = {"preset": preset.name, "pocket_depth_mm": preset.pocket_depth_mm}
    # edge radius along the contour: lo + (hi - lo) Phi(g), g a sum of slow plane waves
    lo, hi = _u(rng, preset.radius_lo_mm), _u(rng, preset.radius_hi_mm)
    p["radius_lo_mm"], p["radius_hi_mm"] = lo, max(lo, hi)
    p["profile"] = ("sharp" if hi <= 0 else
                    "chamfer" if rng.uniform() < preset.chamfer_probability else "round")
    waves = []
    for _ in range(4):
        lam = rng.uniform(80.0, 320.0)
        ang = rng.uniform(0, 2 * np.pi)
        waves.append([float(rng.uniform(0.5, 1.0)), float(2 * np.pi / lam * np.cos(ang)),
                      float(2 * np.pi / lam * np.sin(ang)), float(rng.uniform(0, 2 * np.pi))])
    p["radius_waves"] = waves
    # chips: ellipsoidal bites centred near the design edge
    chips = []
    for _ in range(int(rng.integers(preset.chips[0], preset.chips[1] + 1))):
        k, _f, q = point_on_contour(rng, c)
        n = outward_normal(c, k)
        along = _u(rng, preset.chip_length_mm) / 2
        across = float(rng.uniform(0.4, 0.8)) * along + 0.5
        q = q + n * rng.uniform(-0.3, 0.6) * across
        chips.append({"edge": k, "x_mm": float(q[0]), "y_mm": float(q[1]),
                      "half_length_mm": float(along), "half_width_mm": float(across),
                      "depth_mm": _u(rng, preset.chip_depth_mm),
                      "wobble": [float(rng.uniform(0.0, 0.2)), float(rng.uniform(0, 2 * np.pi))]})
    p["chips"] = chips
    # disc cutter
    if preset.cutter:
        R = _u(rng, preset.cutter_radius_mm)
        p["cutter"] = {"radius_mm": R, "protrusion_mm": _u(rng, preset.protrusion_mm),
                       "tip_half_width_mm": float(rng.uniform(6.0, 10.0)),
                       "x_mm": float(rng.uniform(-2.0, 2.0)),
                       "albedo": float(rng.uniform(0.45, 0.7)),
                       "roughness": float(rng.uniform(0.35, 0.55))}
    else:
        p["cutter"] = None
    # slurry lumps
    lumps = []
    n_lumps = int(rng.integers(preset.slurry[0], preset.slurry[1] + 1))
    for i in range(n_lumps):
        rx, ry = rng.uniform(8.0, 28.0), rng.uniform(8.0, 22.0)
        rz = rng.uniform(2.5, 0.35 * min(rx, ry) + 2.5)
        corner = None
        if i < preset.slurry_across_edge:
            if rng.uniform() < preset.slurry_on_corner_probability:
                corner = int(rng.integers(len(c)))
                q = c[corner] + rng.uniform(-0.3, 0.3, 2) * min(rx, ry)
            else:
                k, _f, q = point_on_contour(rng, c)
                q = q + outward_normal(c, k) * rng.uniform(-0.3, 0.3) * min(rx, ry)
            across = True
        else:  # anywhere on the top face, off the pocket
            for _ in range(100):
                q = np.array([rng.uniform(-a + 15, a - 15), rng.uniform(-b + 15, b - 15)])
                if not inside_pocket(q[None, 0], q[None, 1], c)[0]:
                    break
            across = False
        wet = bool(rng.uniform() < 0.5)
        lumps.append({"x_mm": float(q[0]), "y_mm": float(q[1]), "rx_mm": float(rx),
                      "ry_mm": float(ry), "rz_mm": float(rz),
                      "yaw_deg": float(rng.uniform(0, 180)), "across_edge": across,
                      "corner": corner, "wet": wet, "albedo": float(rng.uniform(0.12, 0.35)),
                      "roughness": float(rng.uniform(0.3, 0.45) if wet
                                         else rng.uniform(0.75, 0.95)),
                      "shape_seed": int(rng.integers(2**31))})
    p["slurry"] = lumps
    # materials and plate
    p["steel_albedo"] = _u(rng, preset.steel_albedo)
    p["steel_roughness"] = _u(rng, preset.steel_roughness)
    p["grime"] = preset.grime
    p["corrosion"] = _u(rng, preset.corrosion)
    p["wet_patches"] = int(rng.integers(preset.wet_patches[0], preset.wet_patches[1] + 1))
    p["plate"] = {"kind": preset.plate, "dz_mm": _u(rng, preset.plate_dz_mm),
                  "gap_mm": _u(rng, preset.plate_gap_mm),
                  "albedo": (float(rng.uniform(0.06, 0.1)) if preset.plate == "dark"
                             else p["steel_albedo"] * float(rng.uniform(0.75, 1.0)))}
    p["defocus_sigma_px"] = _u(rng, preset.defocus_sigma_px)
    p["texture_seed"] = int(rng.integers(2**31))
    return p

