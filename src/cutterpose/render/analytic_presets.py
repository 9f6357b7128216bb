"""The analytic renderer's presets: :class:`RenderSettings` (geometry, light, surface and
sensor of an image) and the named presets (:data:`PRESETS`, :func:`preset`)."""

from __future__ import annotations

from dataclasses import dataclass, replace

from ..errors import InputError

__all__ = ["RenderSettings", "PRESETS", "preset"]


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
