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

import glob
import json
import math
import os
import re
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import cv2
import numpy as np

from ..errors import CutterposeError, InputError
from ..geometry.camera import Camera, default_camera
from ..geometry.holder import Holder, default_holder
from ..geometry.pose import Pose
from .analytic import (
    D_REF_MM,
    RenderSettings,
    add_sensor_noise,
    auto_exposed,
    defocus,
    distance_doc,
    fractal_noise,
    normalized_grid,
    random_pose,
)

__all__ = [
    "FieldPreset", "FIELD_PRESETS", "field_preset", "MitsubaMissingError", "load_mitsuba",
    "draw_params", "build_geometry", "FieldRendered", "render_field", "render_holder",
    "render_field_set",
    "save_field_rendered", "edge_step_offsets",
]

#: Mitsuba variants tried in order (the llvm ones need an LLVM shared library)
VARIANTS = ("llvm_ad_mono", "llvm_ad_rgb", "scalar_rgb")


class MitsubaMissingError(CutterposeError, ImportError):
    """The pbr renderer needs Mitsuba 3 (the optional extra ``[field]``)."""


# ------------------------------------------------------------------------------------------
# presets
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


# ------------------------------------------------------------------------------------------
# Mitsuba
def _set_libllvm() -> None:
    """Point Dr.Jit at the newest LLVM shared library if the user did not."""
    if os.environ.get("DRJIT_LIBLLVM_PATH"):
        return
    found = []
    for p in glob.glob("/usr/lib/x86_64-linux-gnu/libLLVM*.so*") + glob.glob(
            "/usr/lib/llvm-*/lib/libLLVM*.so*") + glob.glob("/usr/lib64/libLLVM*.so*"):
        m = re.search(r"LLVM[-.]?(\d+)", os.path.basename(p))
        if m:
            found.append((int(m.group(1)), p))
    if found:
        os.environ["DRJIT_LIBLLVM_PATH"] = max(found)[1]


def load_mitsuba(variant: str | None = None):
    """Import Mitsuba 3 and set a variant: ``variant``, else ``$CUTTERPOSE_PBR_VARIANT``, else
    the first of :data:`VARIANTS` that works here. Returns the ``mitsuba`` module."""
    _set_libllvm()
    try:
        import mitsuba as mi
    except ImportError as e:
        raise MitsubaMissingError("the pbr renderer needs Mitsuba 3 (the optional extra "
                                  "[field]): pip install -e '.[field]'") from e
    want = variant or os.environ.get("CUTTERPOSE_PBR_VARIANT")
    cands = [want] if want else list(VARIANTS)
    errors = []
    for v in cands:
        if v not in mi.variants():
            errors.append(f"{v}: not in this build")
            continue
        try:
            mi.set_variant(v)
            if v.startswith("llvm"):  # fails here if no LLVM library can be loaded
                import drjit as dr

                dr.eval(mi.Float([1.0, 2.0]) * 2.0)
            return mi
        except Exception as e:  # noqa: BLE001 - an unusable variant, try the next
            errors.append(f"{v}: {e}")
    raise MitsubaMissingError("no usable Mitsuba variant (" + "; ".join(errors) + "); the llvm "
                              "variants need an LLVM library (apt-get install libllvm19, "
                              "DRJIT_LIBLLVM_PATH)")


# ------------------------------------------------------------------------------------------
# per-image parameters
def _u(rng, rg) -> float:
    return float(rng.uniform(rg[0], rg[1])) if rg[1] > rg[0] else float(rg[0])


def _point_on_contour(rng, corners: np.ndarray) -> tuple[int, float, np.ndarray]:
    """A point drawn uniformly along the contour: (edge index, fraction, point)."""
    d = np.roll(corners, -1, axis=0) - corners
    L = np.linalg.norm(d, axis=1)
    k = int(rng.choice(len(L), p=L / L.sum()))
    f = float(rng.uniform(0.0, 1.0))
    return k, f, corners[k] + f * d[k]


def _outward(corners: np.ndarray, k: int) -> np.ndarray:
    """Unit normal of edge ``k`` pointing out of the pocket (onto the top face)."""
    d = np.roll(corners, -1, axis=0)[k] - corners[k]
    return np.array([d[1], -d[0]]) / np.linalg.norm(d)


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
        k, _f, q = _point_on_contour(rng, c)
        n = _outward(c, k)
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
                k, _f, q = _point_on_contour(rng, c)
                q = q + _outward(c, k) * rng.uniform(-0.3, 0.3) * min(rx, ry)
            across = True
        else:  # anywhere on the top face, off the pocket
            for _ in range(100):
                q = np.array([rng.uniform(-a + 15, a - 15), rng.uniform(-b + 15, b - 15)])
                if not _inside_pocket(q[None, 0], q[None, 1], c)[0]:
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


# ------------------------------------------------------------------------------------------
# geometry (numpy)
def _inside_pocket(X, Y, corners) -> np.ndarray:
    """Even-odd test against the axis-parallel inner contour (half-open)."""
    X = np.asarray(X, float)
    Y = np.asarray(Y, float)
    inside = np.zeros(X.shape, bool)
    nxt = np.roll(corners, -1, axis=0)
    for (xa, ya), (xb, yb) in zip(corners, nxt):
        if xa != xb:
            continue
        lo, hi = min(ya, yb), max(ya, yb)
        inside ^= (Y >= lo) & (Y < hi) & (X < xa)
    return inside


def _dist_to_contour(X, Y, corners) -> np.ndarray:
    """Euclidean distance (mm) of points to the closed contour."""
    X = np.asarray(X, np.float64)
    Y = np.asarray(Y, np.float64)
    best = np.full(X.shape, np.inf)
    for p, q in zip(corners, np.roll(corners, -1, axis=0)):
        d = q - p
        t = np.clip(((X - p[0]) * d[0] + (Y - p[1]) * d[1]) / float(d @ d), 0.0, 1.0)
        best = np.minimum(best, np.hypot(X - p[0] - t * d[0], Y - p[1] - t * d[1]))
    return best


def edge_radius(params: dict, X, Y) -> np.ndarray:
    """Edge radius (or chamfer size) field in mm at holder points ``(X, Y)``."""
    lo, hi = params["radius_lo_mm"], params["radius_hi_mm"]
    X = np.asarray(X, np.float64)
    if hi <= 0:
        return np.zeros(X.shape)
    from scipy.special import ndtr

    w = params["radius_waves"]
    g = sum(a * np.cos(kx * X + ky * np.asarray(Y, float) + ph) for a, kx, ky, ph in w)
    g = g / math.sqrt(sum(a * a for a, *_ in w) / 2)
    return lo + (hi - lo) * ndtr(g)


def surface_depth(params: dict, holder: Holder, X, Y) -> np.ndarray:
    """Z (mm, >= 0) of the top surface at points ``(X, Y)`` off the pocket: 0 on the flat face,
    the fillet or chamfer near the contour, and the chips."""
    X = np.asarray(X, np.float64)
    Y = np.asarray(Y, np.float64)
    s = _dist_to_contour(X, Y, holder.corners_mm)
    r = edge_radius(params, X, Y)
    t = np.clip(r - s, 0.0, None)
    if params["profile"] == "chamfer":
        Z = t
    else:
        Z = r - np.sqrt(np.clip(r * r - t * t, 0.0, None))
    for ch in params["chips"]:
        k = ch["edge"]
        c = holder.corners_mm
        d = np.roll(c, -1, axis=0)[k] - c[k]
        e = d / np.linalg.norm(d)
        dx, dy = X - ch["x_mm"], Y - ch["y_mm"]
        ua = (dx * e[0] + dy * e[1]) / ch["half_length_mm"]
        ub = (-dx * e[1] + dy * e[0]) / ch["half_width_mm"]
        amp, ph = ch["wobble"]
        q2 = (ua * ua + ub * ub) * (1.0 + amp * np.cos(3.0 * np.arctan2(ub, ua) + ph))
        Z = np.maximum(Z, ch["depth_mm"] * np.sqrt(np.clip(1.0 - q2, 0.0, None)))
    return Z


def _grid_lines(lo: float, hi: float, keys, band: float, extra=(), coarse: float = 4.0,
                step_far: float = 0.2) -> np.ndarray:
    """Grid coordinates over [lo, hi]: coarse, plus lines crowding quadratically towards each
    contour coordinate in ``keys`` within ``band``, plus ``extra`` (fine ranges)."""
    parts = [np.arange(lo, hi, coarse), np.array([lo, hi], float), np.asarray(keys, float)]
    if band > 0:
        n = max(4, int(math.ceil(2.0 * band / step_far)))
        off = band * (np.arange(1, n + 1) / n) ** 2
        for k in keys:
            parts += [k - off, k + off]
    for c0, c1 in extra:
        parts.append(np.arange(c0, c1, step_far))
    x = np.unique(np.round(np.concatenate(parts), 6))
    return x[(x >= lo) & (x <= hi)]


def _vertex_normals(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals of a triangle mesh (float32)."""
    fn = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    N = np.zeros_like(V, dtype=np.float64)
    for j in range(3):
        for c in range(3):
            N[:, c] += np.bincount(F[:, j], weights=fn[:, c], minlength=len(V))
    n = np.linalg.norm(N, axis=1, keepdims=True)
    n[n == 0] = 1.0
    return (N / n).astype(np.float32)


def _orient(V: np.ndarray, F: np.ndarray, want: np.ndarray) -> np.ndarray:
    """Flip the triangles whose geometric normal points against ``want`` ((F,3) or (3,))."""
    fn = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    bad = np.einsum("ij,ij->i", fn, np.broadcast_to(want, fn.shape)) < 0
    F = F.copy()
    F[bad] = F[bad][:, [0, 2, 1]]
    return F


def _quad_faces(n_a: int, n_b: int) -> np.ndarray:
    """Triangles of an ``n_a x n_b`` vertex grid (row-major)."""
    i, j = np.meshgrid(np.arange(n_a - 1), np.arange(n_b - 1), indexing="ij")
    v0 = (i * n_b + j).ravel()
    v1, v2, v3 = v0 + 1, v0 + n_b, v0 + n_b + 1
    return np.concatenate([np.stack([v0, v2, v1], 1), np.stack([v1, v2, v3], 1)])


@dataclass
class MeshData:
    """A triangle mesh in numpy: vertices (V,3), faces (F,3), optional normals and uv."""

    name: str
    V: np.ndarray
    F: np.ndarray
    N: np.ndarray | None = None
    UV: np.ndarray | None = None


def _rect_mesh(name, x0, x1, y0, y1, z, normal_z=-1.0, uv_box=None) -> MeshData:
    """A rectangle in the plane ``Z = z``; ``uv_box = (X0, X1, Y0, Y1)`` maps uv onto it."""
    V = np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]], np.float32)
    F = _orient(V, np.array([[0, 1, 2], [0, 2, 3]]), np.array([0, 0, normal_z]))
    uv = None
    if uv_box is not None:
        X0, X1, Y0, Y1 = uv_box
        uv = np.column_stack([(V[:, 0] - X0) / (X1 - X0), (V[:, 1] - Y0) / (Y1 - Y0)])
    return MeshData(name, V, F, None, None if uv is None else uv.astype(np.float32))


def _wall_mesh(name, P0, P1, z_top0, z_top1, z_bot, normal) -> MeshData:
    """A vertical quad from the segment ``P0 -> P1`` (tops at ``z_top``) down to ``z_bot``."""
    V = np.array([[P0[0], P0[1], z_top0], [P1[0], P1[1], z_top1], [P1[0], P1[1], z_bot],
                  [P0[0], P0[1], z_bot]], np.float32)
    F = _orient(V, np.array([[0, 1, 2], [0, 2, 3]]), np.array([normal[0], normal[1], 0.0]))
    return MeshData(name, V, F)


def _merge(name: str, parts: list[MeshData]) -> MeshData:
    Vs, Fs, off = [], [], 0
    for m in parts:
        Vs.append(m.V)
        Fs.append(m.F + off)
        off += len(m.V)
    uv = (np.concatenate([m.UV for m in parts]) if all(m.UV is not None for m in parts)
          else None)
    return MeshData(name, np.concatenate(Vs).astype(np.float32), np.concatenate(Fs), None, uv)


def _top_and_walls(params: dict, holder: Holder,
                   step_mm: float = 0.2) -> tuple[MeshData, MeshData, MeshData]:
    """The holder's top face (a height field on a grid crowded at the contour, ``step_mm``
    apart at the most), the pocket walls (sharing the face's boundary vertices) and the
    pocket floor."""
    c = holder.corners_mm
    a, b = holder.outer_length_x_mm / 2, holder.outer_width_y_mm / 2
    band = params["radius_hi_mm"]
    ex, ey = [], []
    for ch in params["chips"]:
        band = max(band, 1.3 * ch["half_width_mm"])
        ext = ch["half_length_mm"] * 1.3 + 0.5
        if holder.edge_direction_index[ch["edge"]] == 0:  # edge along X
            ex.append((ch["x_mm"] - ext, ch["x_mm"] + ext))
        else:
            ey.append((ch["y_mm"] - ext, ch["y_mm"] + ext))
    band = band + 1.0 if band > 0 else 0.0
    gx = _grid_lines(-a, a, np.unique(c[:, 0]), band, ex, step_far=step_mm)
    gy = _grid_lines(-b, b, np.unique(c[:, 1]), band, ey, step_far=step_mm)
    XX, YY = np.meshgrid(gx, gy)  # (ny, nx)
    Z = surface_depth(params, holder, XX, YY)
    V = np.stack([XX, YY, Z], -1).reshape(-1, 3).astype(np.float32)
    ny, nx = XX.shape
    F = _quad_faces(ny, nx)
    cx = 0.5 * (gx[:-1] + gx[1:])
    cy = 0.5 * (gy[:-1] + gy[1:])
    inside = _inside_pocket(*np.meshgrid(cx, cy), c).ravel()  # (ny-1)*(nx-1) cells
    keep = np.concatenate([~inside, ~inside])  # both triangles of each cell
    F = _orient(V, F[keep], np.array([0.0, 0.0, -1.0]))
    UV = np.column_stack([(V[:, 0] + a) / (2 * a), (V[:, 1] + b) / (2 * b)]).astype(np.float32)
    top = MeshData("top", V, F, _vertex_normals(V, F), UV)
    # walls: one strip per contour edge through the face's boundary vertices
    D = params["pocket_depth_mm"]
    walls = []
    nxt = np.roll(c, -1, axis=0)
    for k, (p, q) in enumerate(zip(c, nxt)):
        inward = np.array([-(q - p)[1], (q - p)[0]]) / np.linalg.norm(q - p)
        if p[1] == q[1]:
            iy = int(np.flatnonzero(np.isclose(gy, p[1]))[0])
            ix = np.flatnonzero((gx >= min(p[0], q[0]) - 1e-9) & (gx <= max(p[0], q[0]) + 1e-9))
            top_pts = np.column_stack([gx[ix], np.full(ix.size, p[1]), Z[iy, ix]])
        else:
            ix = int(np.flatnonzero(np.isclose(gx, p[0]))[0])
            iy = np.flatnonzero((gy >= min(p[1], q[1]) - 1e-9) & (gy <= max(p[1], q[1]) + 1e-9))
            top_pts = np.column_stack([np.full(iy.size, p[0]), gy[iy], Z[iy, ix]])
        bot = top_pts.copy()
        bot[:, 2] = D
        Vw = np.stack([top_pts, bot], 0).reshape(-1, 3).astype(np.float32)  # 2 x n
        Fw = _orient(Vw, _quad_faces(2, len(top_pts)), np.array([inward[0], inward[1], 0.0]))
        del k
        walls.append(MeshData("wall", Vw, Fw))
    # floor: the rectangles of the contour's own coordinate grid that lie inside
    xs, ys = np.unique(c[:, 0]), np.unique(c[:, 1])
    floor = []
    for i in range(len(xs) - 1):
        for j in range(len(ys) - 1):
            if _inside_pocket(np.array([0.5 * (xs[i] + xs[i + 1])]),
                              np.array([0.5 * (ys[j] + ys[j + 1])]), c)[0]:
                floor.append(_rect_mesh("floor", xs[i], xs[i + 1], ys[j], ys[j + 1], D))
    return top, _merge("walls", walls), _merge("floor", floor)


def _revolve(name: str, profile: np.ndarray, axis_x: float, axis_z: float,
             segments: int = 256) -> MeshData:
    """Surface of revolution about the axis parallel to Y through ``(axis_x, ., axis_z)``;
    ``profile`` is (n, 2) of (y, radius). Each profile segment gets its own ring of vertices
    (creases stay sharp) with the analytic normals."""
    th = np.linspace(0.0, 2 * np.pi, segments + 1)
    radial = np.stack([np.sin(th), np.zeros_like(th), -np.cos(th)], 1)  # theta = 0 faces -Z
    Vs, Ns, Fs, off = [], [], [], 0
    for (y0, r0), (y1, r1) in zip(profile[:-1], profile[1:]):
        t = np.array([y1 - y0, r1 - r0])
        ln = np.hypot(*t)
        if ln == 0:
            continue
        n_y, n_r = -t[1] / ln, t[0] / ln
        ring = []
        for y, r in ((y0, r0), (y1, r1)):
            P = np.column_stack([axis_x + r * radial[:, 0], np.full(len(th), y),
                                 axis_z + r * radial[:, 2]])
            ring.append(P)
        V = np.concatenate(ring)
        N = np.tile(np.column_stack([n_r * radial[:, 0], np.full(len(th), n_y),
                                     n_r * radial[:, 2]]), (2, 1))
        F = _quad_faces(2, len(th))
        F = _orient(V, F, N[F[:, 0]] + N[F[:, 1]] + N[F[:, 2]])
        Vs.append(V)
        Ns.append(N)
        Fs.append(F + off)
        off += len(V)
    return MeshData(name, np.concatenate(Vs).astype(np.float32), np.concatenate(Fs),
                    np.concatenate(Ns).astype(np.float32))


def _cutter_meshes(cut: dict, holder: Holder) -> tuple[MeshData, MeshData]:
    """The disc cutter: (ring, hub + shaft), axle along Y at X = cut['x_mm']."""
    R, p, wt = cut["radius_mm"], cut["protrusion_mm"], cut["tip_half_width_mm"]
    zc = R - p  # the ring's front point is p in front of the top face
    c = holder.corners_mm
    half_w = float(np.max(np.abs(c[:, 1]))) - 0.5   # shaft from wall to wall
    rh, rs, wh, wr = 0.42 * R, 0.17 * R, 50.0, 22.0
    ring = np.array([[-wr, rh + 6], [-wr, R - 38], [-wt - 5, R - 7], [-wt, R], [wt, R],
                     [wt + 5, R - 7], [wr, R - 38], [wr, rh + 6]])
    hub = np.array([[-half_w, 0.0], [-half_w, rs], [-wh, rs], [-wh, rh], [-wr, rh + 6],
                    [wr, rh + 6], [wh, rh], [wh, rs], [half_w, rs], [half_w, 0.0]])
    return (_revolve("cutter_ring", ring, cut["x_mm"], zc),
            _revolve("cutter_hub", hub, cut["x_mm"], zc))


def _lump_mesh(lump: dict, name: str) -> MeshData:
    """A slurry lump: a flattened sphere with a random low-frequency displacement, sunk 35 %
    of its height into the face."""
    rng = np.random.default_rng(lump["shape_seed"])
    nt, npf = 40, 80
    t = np.linspace(0, np.pi, nt)
    f = np.linspace(0, 2 * np.pi, npf, endpoint=False)
    T, P = np.meshgrid(t, f, indexing="ij")
    d = np.stack([np.sin(T) * np.cos(P), np.sin(T) * np.sin(P), np.cos(T)], -1)
    s = np.ones(T.shape)
    for i in range(14):
        k = rng.normal(size=3)
        k *= rng.uniform(1.5, 4.0) * (1.0 + i // 5) / np.linalg.norm(k)
        s += rng.uniform(0.05, 0.14) / (1.0 + i // 5) * np.cos(d @ k + rng.uniform(0, 2 * np.pi))
    P3 = d * s[..., None] * np.array([lump["rx_mm"], lump["ry_mm"], lump["rz_mm"]])
    yaw = math.radians(lump["yaw_deg"])
    Rz = np.array([[math.cos(yaw), -math.sin(yaw), 0], [math.sin(yaw), math.cos(yaw), 0],
                   [0, 0, 1]])
    P3 = P3 @ Rz.T + np.array([lump["x_mm"], lump["y_mm"], 0.35 * lump["rz_mm"]])
    V = P3.reshape(-1, 3)
    # faces of a (nt x npf) grid closed in phi
    i, j = np.meshgrid(np.arange(nt - 1), np.arange(npf), indexing="ij")
    v0 = i * npf + j
    v1 = i * npf + (j + 1) % npf
    v2, v3 = v0 + npf, v1 + npf
    F = np.concatenate([np.stack([v0.ravel(), v2.ravel(), v1.ravel()], 1),
                        np.stack([v1.ravel(), v2.ravel(), v3.ravel()], 1)])
    area = np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1)
    F = F[area > 1e-9]
    cen = V[F].mean(axis=1) - np.array([lump["x_mm"], lump["y_mm"], 0.35 * lump["rz_mm"]])
    F = _orient(V, F, cen)  # outwards
    V = V.astype(np.float32)
    return MeshData(name, V, F, _vertex_normals(V, F))


def build_geometry(params: dict, holder: Holder,
                   step_mm: float = 0.2) -> dict[str, list[MeshData]]:
    """Every mesh of the scene in the holder frame, grouped by material; ``step_mm``: the
    coarsest spacing of the top face's grid near the contour (about a pixel's footprint)."""
    a, b = holder.outer_length_x_mm / 2, holder.outer_width_y_mm / 2
    top, walls, floor = _top_and_walls(params, holder, step_mm)
    pl = params["plate"]
    g, dz, L, back = pl["gap_mm"], pl["dz_mm"], 1500.0, 60.0
    A, B = a + g, b + g
    box = (-L, L, -L, L)
    plate = [_rect_mesh("plate", -L, L, B, L, dz, uv_box=box),
             _rect_mesh("plate", -L, L, -L, -B, dz, uv_box=box),
             _rect_mesh("plate", -L, -A, -B, B, dz, uv_box=box),
             _rect_mesh("plate", A, L, -B, B, dz, uv_box=box)]
    rect = holder.outer_rectangle_mm
    block, hole = [], []
    for p, q in zip(rect, np.roll(rect, -1, axis=0)):
        out = np.array([(q - p)[1], -(q - p)[0]]) / np.linalg.norm(q - p)
        block.append(_wall_mesh("block", p, q, 0.0, 0.0, back, out))
        s = np.sign(p) * [A, B]
        t = np.sign(q) * [A, B]
        hole.append(_wall_mesh("hole", s, t, dz, dz, back, -out))
    groups = {"top": [top], "walls": [walls], "floor": [floor],
              "plate": [_merge("plate", plate)],
              "dark": [_merge("dark", block + hole + [_rect_mesh("gap", -A, A, -B, B, back)])]}
    if params["cutter"]:
        ring, hub = _cutter_meshes(params["cutter"], holder)
        groups["cutter_ring"] = [ring]
        groups["cutter_hub"] = [hub]
    for i, lump in enumerate(params["slurry"]):
        groups[f"slurry_{i}"] = [_lump_mesh(lump, f"slurry_{i}")]
    return groups


# ------------------------------------------------------------------------------------------
# textures
def _top_textures(params: dict, holder: Holder, texel_mm: float = 0.25) -> dict:
    """Albedo, roughness, metallic and clear-coat maps of the top face (float32, rows along
    +Y from -b, columns along +X from -a, the uv of the face mesh)."""
    rng = np.random.default_rng(params["texture_seed"])
    a, b = holder.outer_length_x_mm / 2, holder.outer_width_y_mm / 2
    w, h = int(math.ceil(2 * a / texel_mm)), int(math.ceil(2 * b / texel_mm))
    t = 0.25 / texel_mm
    X = (-a + (np.arange(w, dtype=np.float32) + 0.5) * texel_mm)[None, :]
    Y = (-b + (np.arange(h, dtype=np.float32) + 0.5) * texel_mm)[:, None]
    gr = params["grime"]
    alb = 1.0 + gr * (0.7 * fractal_noise((h, w), rng, 160 * t, 5)
                      + 0.3 * fractal_noise((h, w), rng, 12 * t, 3))
    # fly-cutting arcs modulate the albedo a little
    cx, cy = rng.uniform(-1.5, 1.5) * a, rng.choice([-1, 1]) * rng.uniform(2.5, 4.0) * b
    r = np.sqrt((X - cx) ** 2 + (Y - cy) ** 2)
    pitch = rng.uniform(0.8, 1.6)
    alb += 0.5 * gr * np.sin(2 * np.pi * r / pitch + 1.5 * fractal_noise((h, w), rng, 200 * t, 2))
    rough = params["steel_roughness"] * (1.0 + 0.04 * fractal_noise((h, w), rng, 40 * t, 3))
    metal = np.full((h, w), 0.35, np.float32)
    coat = np.zeros((h, w), np.float32)
    if params["corrosion"] > 0:
        f = fractal_noise((h, w), rng, 240 * t, 5)
        thr = np.quantile(f[::8, ::8], 1.0 - params["corrosion"])
        blot = np.clip((f - thr) / 0.35, 0.0, 1.0)
        grain = 0.5 + 0.5 * np.clip(fractal_noise((h, w), rng, 6 * t, 3), -1, 1)
        alb *= 1.0 - 0.55 * blot * (0.6 + 0.4 * grain)
        rough = rough + (0.9 - rough) * blot
        metal = metal * (1.0 - 0.9 * blot)
    c = holder.corners_mm
    for _ in range(params["wet_patches"]):
        # wet patches lie mostly near the pocket (water runs into it)
        if rng.uniform() < 0.7:
            k, _f, q = _point_on_contour(rng, c)
            q = q + _outward(c, k) * rng.uniform(0.0, 25.0)
        else:
            q = np.array([rng.uniform(-a, a), rng.uniform(-b, b)])
        rx, ry = rng.uniform(8.0, 40.0), rng.uniform(6.0, 25.0)
        ang = rng.uniform(0, np.pi)
        u = ((X - q[0]) * np.cos(ang) + (Y - q[1]) * np.sin(ang)) / rx
        v = (-(X - q[0]) * np.sin(ang) + (Y - q[1]) * np.cos(ang)) / ry
        edge = 0.25 * fractal_noise((h, w), rng, 30 * t, 3)
        m = np.clip((1.0 - np.sqrt(u * u + v * v) + edge) / 0.15, 0.0, 1.0)
        alb *= 1.0 - 0.35 * m
        coat = np.maximum(coat, m)
    return {"albedo": (params["steel_albedo"] * np.clip(alb, 0.05, 1.6)).astype(np.float32),
            "roughness": np.clip(rough, 0.05, 1.0).astype(np.float32),
            "metallic": np.clip(metal, 0.0, 1.0).astype(np.float32),
            "coat": coat.astype(np.float32)}


# ------------------------------------------------------------------------------------------
# the Mitsuba scene
def _mi_mesh(mi, m: MeshData, bsdf=None, emitter=None):
    """A ``mitsuba.Mesh`` from numpy arrays, with its BSDF and emitter (loaded objects)."""
    props = mi.Properties()
    if bsdf is not None:
        props["bsdf"] = bsdf
    if emitter is not None:
        props["emitter"] = emitter
    mesh = mi.Mesh(m.name, len(m.V), len(m.F), props=props,
                   has_vertex_normals=m.N is not None, has_vertex_texcoords=m.UV is not None)
    prm = mi.traverse(mesh)
    if mi.variant().startswith("scalar"):
        import drjit as dr

        fl, ui = dr.scalar.ArrayXf, dr.scalar.ArrayXu
    else:
        fl, ui = mi.Float, mi.UInt32
    prm["vertex_positions"] = fl(np.ascontiguousarray(m.V, np.float32).ravel())
    prm["faces"] = ui(np.ascontiguousarray(m.F, np.uint32).ravel())
    if m.N is not None:
        prm["vertex_normals"] = fl(np.ascontiguousarray(m.N, np.float32).ravel())
    if m.UV is not None:
        prm["vertex_texcoords"] = fl(np.ascontiguousarray(m.UV, np.float32).ravel())
    prm.update()
    return mesh


def _bitmap(mi, data: np.ndarray, raw: bool = True) -> dict:
    return {"type": "bitmap", "bitmap": mi.Bitmap(np.ascontiguousarray(data[..., None])),
            "raw": raw, "filter_type": "bilinear", "wrap_mode": "clamp"}


def _principled(base, roughness, metallic=0.0, coat=None, specular=0.5) -> dict:
    d = {"type": "principled", "base_color": base, "roughness": roughness,
         "metallic": metallic, "specular": specular}
    if coat is not None:
        d.update({"clearcoat": coat, "clearcoat_gloss": 0.92})
    return {"type": "twosided", "material": d}


def _const(mi, v: float) -> dict:
    return {"type": "rgb", "value": [float(v)] * 3}


def _ring_light(pose: Pose, r_in: float = 30.0, r_out: float = 50.0, n: int = 64) -> MeshData:
    """The annular emitter round the lens, in the holder frame, facing along the optical
    axis (1 mm in front of the projection centre)."""
    th = np.linspace(0, 2 * np.pi, n, endpoint=False)
    ring = np.concatenate([np.column_stack([r * np.cos(th), r * np.sin(th), np.full(n, 1.0)])
                           for r in (r_in, r_out)])
    j = np.arange(n)
    F = np.concatenate([np.stack([j, (j + 1) % n, n + j], 1),
                        np.stack([(j + 1) % n, n + (j + 1) % n, n + j], 1)])
    F = _orient(ring, F, np.array([0.0, 0.0, 1.0]))
    Rt = pose.R.T
    V = (ring - pose.t_mm) @ Rt.T  # camera -> holder frame: R^T (x - t)
    return MeshData("ring_light", V.astype(np.float32), F)


RING_INNER_MM, RING_OUTER_MM = 30.0, 50.0


def build_scene(mi, params: dict, holder: Holder, pose: Pose, sensors: list[dict],
                max_depth: int = 5, geometry=None, texel_mm: float = 0.25):
    """The Mitsuba scene of one image: geometry, materials, the ring light, the sensors."""
    geometry = build_geometry(params, holder) if geometry is None else geometry
    tex = _top_textures(params, holder, texel_mm)
    pl = params["plate"]
    prng = np.random.default_rng(params["texture_seed"] + 1)
    plate_alb = pl["albedo"] * np.exp(0.15 * fractal_noise((1500, 1500), prng, 60, 5)
                                      + 0.05 * fractal_noise((1500, 1500), prng, 4, 2))
    mats = {
        "top": _principled(_bitmap(mi, tex["albedo"]), _bitmap(mi, tex["roughness"]),
                           _bitmap(mi, tex["metallic"]), _bitmap(mi, tex["coat"])),
        "walls": _principled(_const(mi, 0.3), 0.6, 0.4),
        "floor": _principled(_const(mi, 0.05), 0.8, 0.0),
        "plate": _principled(_bitmap(mi, plate_alb.astype(np.float32)),
                             0.75 if pl["kind"] == "dark" else params["steel_roughness"],
                             0.0 if pl["kind"] == "dark" else 0.5),
        # the block's side walls, the cutterhead's cut-out and the muck in the gap
        "dark": _principled(_const(mi, 0.12), 0.8, 0.2),
    }
    if params["cutter"]:
        cu = params["cutter"]
        mats["cutter_ring"] = _principled(_const(mi, cu["albedo"]), cu["roughness"], 0.5)
        mats["cutter_hub"] = _principled(_const(mi, 0.7 * cu["albedo"]), 0.6, 0.3)
    for i, lump in enumerate(params["slurry"]):
        mats[f"slurry_{i}"] = _principled(_const(mi, lump["albedo"]), lump["roughness"], 0.0)
    scene: dict = {"type": "scene",
                   "integrator": {"type": "path", "max_depth": int(max_depth),
                                  "rr_depth": int(max_depth)}}
    for key, meshes in geometry.items():
        bsdf = mi.load_dict(mats[key])
        for k, m in enumerate(meshes):
            scene[f"{key}_{k}"] = _mi_mesh(mi, m, bsdf=bsdf)
    emitter = mi.load_dict({"type": "area", "radiance": {"type": "rgb", "value": [1.0] * 3}})
    scene["ring_light"] = _mi_mesh(mi, _ring_light(pose, RING_INNER_MM, RING_OUTER_MM),
                                   bsdf=mi.load_dict({"type": "diffuse", "reflectance":
                                                      _const(mi, 0.0)}), emitter=emitter)
    for i, s in enumerate(sensors):
        scene[f"sensor_{i}"] = s
    return mi.load_dict(scene), geometry


# ------------------------------------------------------------------------------------------
# camera: pinhole render -> division-model image
def _to_world(pose: Pose) -> np.ndarray:
    """Mitsuba's camera-to-world matrix (holder frame). Mitsuba's camera looks along +z with
    +y up and +x to the left of the image; ours has x right and y down: a half turn about z."""
    T = np.eye(4)
    T[:3, :3] = pose.R.T
    T[:3, 3] = -pose.R.T @ pose.t_mm
    return T @ np.diag([-1.0, -1.0, 1.0, 1.0])


@dataclass(frozen=True)
class PinholeFilm:
    """The ideal pinhole image Mitsuba renders: square pixels of focal ``f_px``, principal
    point at the film centre; ideal pixel ``u = f x_n + (W/2 - 1/2)`` (pixel centres)."""

    f_px: float
    width: int
    height: int

    def film_xy(self, xn, yn):
        """Film coordinates (pixel corners at integers) of normalised coordinates."""
        return self.f_px * np.asarray(xn) + self.width / 2, self.f_px * np.asarray(yn) + (
            self.height / 2)


def pinhole_film(camera: Camera, oversample: float = 1.0) -> PinholeFilm:
    """A pinhole film covering the whole distorted image of ``camera`` (plus 4 px)."""
    w, h = camera.image_size_px
    u = np.arange(w, dtype=float)
    v = np.arange(h, dtype=float)
    border = np.concatenate([np.column_stack([u, np.zeros(w)]),
                             np.column_stack([u, np.full(w, h - 1.0)]),
                             np.column_stack([np.zeros(h), v]),
                             np.column_stack([np.full(h, w - 1.0), v])])
    m = camera.normalize_px(border)
    f = float(camera.K[1, 1]) * oversample
    W = 2 * int(math.ceil(f * np.abs(m[:, 0]).max() + 4))
    H = 2 * int(math.ceil(f * np.abs(m[:, 1]).max() + 4))
    return PinholeFilm(f, W, H)


def _holder_crop(pose: Pose, holder: Holder, params: dict, film: PinholeFilm,
                 margin_px: int = 24) -> tuple[int, int, int, int]:
    """Film window (x0, y0, width, height) round the holder, its gap, the cutter and lumps."""
    g = params["plate"]["gap_mm"] + 12.0
    a, b = holder.outer_length_x_mm / 2 + g, holder.outer_width_y_mm / 2 + g
    zf = -(params["cutter"]["protrusion_mm"] if params["cutter"] else 0.0) - 15.0
    P = np.array([[x, y, z] for x in (-a, a) for y in (-b, b) for z in (zf, 10.0)])
    Pc = pose.apply(P)
    x, y = film.film_xy(Pc[:, 0] / Pc[:, 2], Pc[:, 1] / Pc[:, 2])
    x0 = int(np.clip(math.floor(x.min()) - margin_px, 0, film.width - 1))
    y0 = int(np.clip(math.floor(y.min()) - margin_px, 0, film.height - 1))
    x1 = int(np.clip(math.ceil(x.max()) + margin_px, x0 + 1, film.width))
    y1 = int(np.clip(math.ceil(y.max()) + margin_px, y0 + 1, film.height))
    return x0, y0, x1 - x0, y1 - y0


def _sensor_dict(mi, pose: Pose, film: PinholeFilm, spp: int, scale: int = 1,
                 crop: tuple[int, int, int, int] | None = None) -> dict:
    fov = 2.0 * math.degrees(math.atan(0.5 * film.width / film.f_px))
    f = {"type": "hdrfilm", "width": film.width // scale, "height": film.height // scale,
         "rfilter": {"type": "box"}, "sample_border": False,
         "pixel_format": "luminance" if "mono" in mi.variant() else "rgb"}
    if crop is not None:
        f.update({"crop_offset_x": crop[0], "crop_offset_y": crop[1], "crop_width": crop[2],
                  "crop_height": crop[3]})
    return {"type": "perspective", "fov": fov, "fov_axis": "x", "near_clip": 1.0,
            "far_clip": 1.0e5, "to_world": mi.ScalarTransform4f(_to_world(pose).tolist()),
            "sampler": {"type": "independent", "sample_count": int(spp)}, "film": f}


def _luminance(img) -> np.ndarray:
    a = np.asarray(img, np.float32)
    if a.ndim == 3:
        a = a[..., :3].mean(axis=2) if a.shape[2] >= 3 else a[..., 0]
    return a


# ------------------------------------------------------------------------------------------
# truth
def _ray_hits(origin: np.ndarray, targets: np.ndarray, V: np.ndarray, F: np.ndarray,
              eps: float = 1e-3) -> np.ndarray:
    """For rays origin -> target (segment parameter in (0, 1 - eps)): does any triangle of
    (V, F) cut the segment? (Moller-Trumbore, vectorised.)"""
    d = targets - origin  # (R, 3)
    v0, e1, e2 = V[F[:, 0]], V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]
    hit = np.zeros(len(targets), bool)
    for r in range(len(targets)):
        p = np.cross(d[r], e2)
        det = np.einsum("ij,ij->i", e1, p)
        ok = np.abs(det) > 1e-12
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        s = origin - v0
        u = np.einsum("ij,ij->i", s, p) * inv
        q = np.cross(s, e1)
        v = (q @ d[r]) * inv
        t = np.einsum("ij,ij->i", e2, q) * inv
        hit[r] = bool(np.any(ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > eps)
                             & (t < 1 - eps)))
    return hit


def hidden_corners(params: dict, holder: Holder, pose: Pose, geometry: dict,
                   probe_mm: float = 1.5) -> dict[int, list[str]]:
    """Corners whose neighbourhood (the corner and the points ``probe_mm`` along its two
    edges) is covered by the cutter or a slurry lump, or bitten by a chip: {index: reasons}."""
    c = holder.corners_mm
    n = len(c)
    prev, nxt = np.roll(c, 1, axis=0), np.roll(c, -1, axis=0)
    u1 = (prev - c) / np.linalg.norm(prev - c, axis=1)[:, None]
    u2 = (nxt - c) / np.linalg.norm(nxt - c, axis=1)[:, None]
    probes = np.stack([c, c + probe_mm * u1, c + probe_mm * u2], 1)  # (n, 3, 2)
    P = np.concatenate([probes.reshape(-1, 2), np.zeros((3 * n, 1))], 1)
    origin = -pose.R.T @ pose.t_mm
    out: dict[int, list[str]] = {}
    for key, meshes in geometry.items():
        if not (key.startswith("cutter") or key.startswith("slurry")):
            continue
        why = "cutter" if key.startswith("cutter") else "slurry"
        for m in meshes:
            V, F = m.V.astype(np.float64), m.F
            # only triangles in front of the face can hide a point of it
            F = F[V[F][:, :, 2].min(axis=1) < 0]
            if len(F) == 0:
                continue
            hit = _ray_hits(origin, P, V, F).reshape(n, 3).any(axis=1)
            for i in np.flatnonzero(hit):
                out.setdefault(int(i), [])
                if why not in out[int(i)]:
                    out[int(i)].append(why)
    for ch in params["chips"]:
        k = ch["edge"]
        d = nxt[k] - c[k]
        e = d / np.linalg.norm(d)
        q = probes.reshape(-1, 2) - [ch["x_mm"], ch["y_mm"]]
        ua = (q @ e) / (ch["half_length_mm"] + 1.0)
        ub = (q @ np.array([-e[1], e[0]])) / (ch["half_width_mm"] + 1.0)
        inside = ((ua * ua + ub * ub) < 1.0).reshape(n, 3).any(axis=1)
        for i in np.flatnonzero(inside):
            out.setdefault(int(i), [])
            if "chip" not in out[int(i)]:
                out[int(i)].append("chip")
    return dict(sorted(out.items()))


def edge_radius_stats(params: dict, holder: Holder, step_mm: float = 5.0) -> list[dict]:
    """Per contour edge: mean, min and max radius (mm) and samples every ``step_mm``."""
    c = holder.corners_mm
    out = []
    for k, (p, q) in enumerate(zip(c, np.roll(c, -1, axis=0))):
        L = float(np.linalg.norm(q - p))
        s = np.linspace(0.0, 1.0, max(2, int(round(L / 1.0)) + 1))
        pts = p + s[:, None] * (q - p)
        r = edge_radius(params, pts[:, 0], pts[:, 1])
        ss = np.linspace(0.0, 1.0, max(2, int(round(L / step_mm)) + 1))
        rs = edge_radius(params, p[0] + ss * (q - p)[0], p[1] + ss * (q - p)[1])
        out.append({"edge": k, "radius_mean_mm": float(r.mean()),
                    "radius_min_mm": float(r.min()), "radius_max_mm": float(r.max()),
                    "radius_step_mm": L / (len(ss) - 1),
                    "radius_samples_mm": [round(float(x), 3) for x in rs],
                    "chips": [i for i, ch in enumerate(params["chips"]) if ch["edge"] == k]})
    return out


# ------------------------------------------------------------------------------------------
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
    crop = _holder_crop(pose, holder, params, film)
    bg_spp = max(1, int(preset.background_spp))
    sensors = [_sensor_dict(mi, pose, film, bg_spp, scale=2),
               _sensor_dict(mi, pose, film, spp, crop=crop)]
    # grid of the top face: about 0.8 of a pixel's footprint (not below 0.2 mm)
    step = float(np.clip(0.8 * pose.t_mm[2] / camera.focal_px, 0.2, 2.0))
    geometry = build_geometry(params, holder, step)
    scene, _ = build_scene(mi, params, holder, pose, sensors, preset.max_depth, geometry,
                           texel_mm=float(np.clip(step, 0.25, 2.0)))
    t1 = time.perf_counter()
    s_bg, s_crop = (int(x) for x in r_mc.integers(0, 2**31, 2))
    bg = _luminance(mi.render(scene, sensor=0, seed=s_bg, spp=bg_spp))
    t2 = time.perf_counter()
    cr = _luminance(mi.render(scene, sensor=1, seed=s_crop, spp=spp))
    t3 = time.perf_counter()
    full = cv2.resize(bg, (film.width, film.height), interpolation=cv2.INTER_LINEAR)
    x0, y0, cw, ch = crop
    # feathered paste of the crop (the seam lies on the cutterhead plate)
    fe = 16.0
    wx = np.minimum(np.arange(cw) + 0.5, cw - np.arange(cw) - 0.5)
    wy = np.minimum(np.arange(ch) + 0.5, ch - np.arange(ch) - 0.5)
    if x0 == 0:
        wx[: cw // 2] = fe
    if x0 + cw == film.width:
        wx[cw // 2:] = fe
    if y0 == 0:
        wy[: ch // 2] = fe
    if y0 + ch == film.height:
        wy[ch // 2:] = fe
    w = np.clip(np.minimum(wy[:, None], wx[None, :]) / fe, 0.0, 1.0).astype(np.float32)
    sub = full[y0:y0 + ch, x0:x0 + cw]
    sub[:] = w * cr + (1.0 - w) * sub
    # radiometric scale: a white Lambertian patch facing the camera at D_REF -> light_dn
    ring = _ring_light(Pose.nominal())
    A = 0.5 * np.linalg.norm(np.cross(ring.V[ring.F[:, 1]] - ring.V[ring.F[:, 0]],
                                      ring.V[ring.F[:, 2]] - ring.V[ring.F[:, 0]]), axis=1).sum()
    k = preset.light_dn * math.pi * D_REF_MM**2 / A
    xn, yn = normalized_grid(camera)
    mx = (film.f_px * xn + (film.width / 2 - 0.5)).astype(np.float32)
    my = (film.f_px * yn + (film.height / 2 - 0.5)).astype(np.float32)
    value = cv2.remap(full * np.float32(k), mx, my, cv2.INTER_LINEAR,
                      borderMode=cv2.BORDER_REPLICATE)
    value *= (1.0 / (1.0 + xn * xn + yn * yn)) ** np.float32(0.5 * preset.vignetting_power)
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
