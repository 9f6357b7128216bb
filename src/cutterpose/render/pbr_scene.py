"""The pbr renderer's Mitsuba side: loading Mitsuba 3 (:func:`load_mitsuba`), the scene built
from the numpy geometry (meshes, principled materials, the ring light at the lens:
:func:`build_scene`) and the pinhole film the division-model image is resampled from
(:func:`pinhole_film`, :func:`sensor_dict`)."""

from __future__ import annotations

import glob
import math
import os
import re
from dataclasses import dataclass

import numpy as np

from ..errors import CutterposeError
from ..geometry.camera import Camera
from ..geometry.holder import Holder
from ..geometry.pose import Pose
from .pbr_geometry import MeshData, build_geometry, orient_faces, top_textures
from .sensor import fractal_noise

__all__ = ["VARIANTS", "MitsubaMissingError", "load_mitsuba", "build_scene", "ring_light",
           "PinholeFilm", "pinhole_film", "holder_crop", "sensor_dict", "luminance"]

#: Mitsuba variants tried in order (the llvm ones need an LLVM shared library)
VARIANTS = ("llvm_ad_mono", "llvm_ad_rgb", "scalar_rgb")


class MitsubaMissingError(CutterposeError, ImportError):
    """The pbr renderer needs Mitsuba 3 (the optional extra ``[field]``)."""



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


def ring_light(pose: Pose, r_in: float = 30.0, r_out: float = 50.0, n: int = 64) -> MeshData:
    """The annular emitter round the lens, in the holder frame, facing along the optical
    axis (1 mm in front of the projection centre)."""
    th = np.linspace(0, 2 * np.pi, n, endpoint=False)
    ring = np.concatenate([np.column_stack([r * np.cos(th), r * np.sin(th), np.full(n, 1.0)])
                           for r in (r_in, r_out)])
    j = np.arange(n)
    F = np.concatenate([np.stack([j, (j + 1) % n, n + j], 1),
                        np.stack([(j + 1) % n, n + (j + 1) % n, n + j], 1)])
    F = orient_faces(ring, F, np.array([0.0, 0.0, 1.0]))
    Rt = pose.R.T
    V = (ring - pose.t_mm) @ Rt.T  # camera -> holder frame: R^T (x - t)
    return MeshData("ring_light", V.astype(np.float32), F)


RING_INNER_MM, RING_OUTER_MM = 30.0, 50.0


def build_scene(mi, params: dict, holder: Holder, pose: Pose, sensors: list[dict],
                max_depth: int = 5, geometry=None, texel_mm: float = 0.25):
    """The Mitsuba scene of one image: geometry, materials, the ring light, the sensors."""
    geometry = build_geometry(params, holder) if geometry is None else geometry
    tex = top_textures(params, holder, texel_mm)
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
    scene["ring_light"] = _mi_mesh(mi, ring_light(pose, RING_INNER_MM, RING_OUTER_MM),
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


def holder_crop(pose: Pose, holder: Holder, params: dict, film: PinholeFilm,
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


def sensor_dict(mi, pose: Pose, film: PinholeFilm, spp: int, scale: int = 1,
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


def luminance(img) -> np.ndarray:
    a = np.asarray(img, np.float32)
    if a.ndim == 3:
        a = a[..., :3].mean(axis=2) if a.shape[2] >= 3 else a[..., 0]
    return a

