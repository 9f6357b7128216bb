"""The tracker's parameters (:class:`TrackParams`) and the full measurement's settings during
an approach (:func:`approach_limits`, :func:`approach_params`)."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

from ..budget import Tolerance
from ..geometry.camera import Camera
from ..image import FeatureParams
from ..pipeline import QualityLimits

__all__ = ["TrackParams", "approach_limits", "approach_params", "MIN_LINES"]

#: the fewest edges a tracked frame may rest on, whatever the holder's design
MIN_LINES = 4


@dataclass(frozen=True)
class TrackParams:
    """Parameters of the tracker (pixel lengths for the paper's 12-Mpx camera; scaled with
    the focal length by :meth:`for_camera`)."""

    band_half_width_px: float = 6.0   #: profiles across the predicted edge, +- this
    cold_band_factor: float = 2.0     #: wider band while the velocity is unknown
    profile_step_px: float = 3.0      #: spacing of the profiles along an edge
    passes: int = 1                   #: refinement passes (re-centred on the refined line)
    end_trim_px: float = 10.0         #: profiles kept this far from the predicted corners
    min_support: float = 0.5          #: an edge is seen if its inliers cover this share
    #: RMS model-to-edge distance after the fit (ideal px) and the largest one (at least
    #: 2.5 RMS limits): a broken edge whose radius varies by +-0.5 mm along the contour
    #: (preset ``new``) leaves ~0.4 px of RMS at 600-900 mm that the full measurement has as
    #: well; a wrong edge leaves more. The RMS limit is at least ``rms_ref_factor`` times the
    #: corner RMS of the last full measurement (the tracker's RMS is ~0.7 of it on the same
    #: frames: analytic ``new`` 0.40 / 0.58 px, pbr ``new`` 0.55 / 0.76 px)
    max_rms_px: float = 0.6
    max_corner_residual_px: float = 1.5
    rms_ref_factor: float = 1.0
    #: edges seen for a pose, as a share of the holder's edges (10 of the reference's 20),
    #: at least ``MIN_LINES``, and two per direction (:meth:`lines_needed`)
    min_line_share: float = 0.5
    shift_fraction: float = 0.75      #: a seen edge lies within this share of the band
    #: the last pass's pose fit moved the bands by at most this share of them (the edges may
    #: lie farther from the model: the residual limits judge that)
    centred_fraction: float = 0.35
    max_passes: int = 3               #: band passes, each centred on the previous pose
    #: a seen edge whose ends lie farther than max(line_outlier_px, line_outlier_factor x the
    #: median) from their line after the pose fit is left out (at most max_dropped_lines)
    line_outlier_px: float = 0.25
    line_outlier_factor: float = 4.0
    max_dropped_lines: int = 3
    #: the seen edges must fix every DOF within this factor of all the holder's edges' std
    max_std_ratio: float = 1.5
    filter_alpha: float = 0.5         #: alpha-beta filter gains (beta: Benedict-Bordner)
    filter_beta: float = 0.5 ** 2 / 1.5
    gate_mm: float = 5.0              #: filter reset when the innovation exceeds these
    gate_deg: float = 2.0
    #: ``dm+b``: the tracked edges' offsets from the design edge are measured again (a band
    #: fit from the tracked pose, docs/tracking.md) once the distance to the holder has changed by
    #: this fraction since the last measurement of them (``math.inf``: never) ...
    anchor_scale_change: float = 0.05
    anchor_every: int = 0             #: ... or every this many frames (0: no such rule)
    #: the band fit's passes (``measure_band``; one pass from the tracked pose takes longer:
    #: it chooses the look on all segments)
    anchor_passes: int = 2
    #: the weight of a re-anchor's offsets against those carried (a fading-memory average:
    #: ``1 / n`` for the ``n``-th measurement since the full one while that is larger; 1:
    #: the last measurement only)
    anchor_gain: float = 0.5
    #: after a full measurement, this many tracked frames re-anchor whatever the view's change
    #: (one measurement of the offsets carries its pose's error to every frame after it)
    anchor_warmup: int = 2
    #: an offset at each end of every edge (True) or one per edge: the break of a worn edge
    #: varies along it, so the edge tracked is tilted against the design edge, and one
    #: offset per edge leaves half that tilt at each end for the pose to absorb. Not the
    #: default: on the pbr approaches of the eleventh session it followed the full
    #: measurement more closely (worn), but an edge whose line was bent by an occluder at the
    #: anchor keeps that tilt at its ends, and 8 of 20 frames of a held-back ``new`` approach
    #: fell back (docs/RESULTS.md section 13)
    anchor_ends: bool = False
    #: the band's pose and the tracked pose may differ per DOF by this many combined std;
    #: beyond, one of them is wrong and the frame is measured in full
    anchor_gate_sigma: float = 5.0
    #: a re-anchor's band fit (~120 ms) runs beside the tracking and its offsets are applied
    #: this many frames after the frame it was measured on (docs/tracking.md, "Jobs beside
    #: the tracking"); 0: on that frame itself, which then waits for the fit
    anchor_lag: int = 0
    #: with ``anchor_lag > 0``, a frame the tracking cannot follow is measured in full beside
    #: the tracking too (docs/tracking.md, "Jobs beside the tracking"): it is answered at
    #: once without a pose, the next ones are tracked from the last pose until it is applied
    #: ``anchor_lag`` frames on, instead of waiting ~250 ms for it; False: measured on the
    #: frame itself
    defer_fallbacks: bool = True
    #: ``dm+b``: the offsets follow the view between anchors as the edge model says a broken
    #: edge of the band fit's radius images (docs/tracking.md, "Broken edges: the offsets");
    #: False: a length on the holder, constant until the next anchor
    view_model: bool = True

    def lines_needed(self, n_edges: int) -> int:
        """Edges a tracked frame must see on a holder of ``n_edges`` edges: the share
        ``min_line_share`` of them, at least :data:`MIN_LINES` (six pose DOFs from two lines
        per direction and their spacing) and never more than the holder has."""
        return min(n_edges, max(MIN_LINES, math.ceil(self.min_line_share * n_edges - 1e-9)))

    def for_camera(self, camera: Camera) -> TrackParams:
        k = camera.focal_px / (0.00854103 / 3.45e-6)
        if abs(k - 1) < 0.1:
            return self
        return replace(self, band_half_width_px=max(3.0, self.band_half_width_px * k),
                       profile_step_px=max(1.0, self.profile_step_px * k),
                       end_trim_px=max(4.0, self.end_trim_px * k))


def approach_limits() -> QualityLimits:
    """Quality limits of the full measurement during an approach: the working range's angles,
    lateral shifts up to 60 mm, depths from 580 to 940 mm, and an error budget of 10 mm / 3 deg
    (3 sigma): on the way the pose guides the robot and seeds the tracker; the grasp tolerance
    (1 mm, ``Tolerance()``) is the verdict of the measurement at the final stop."""
    return QualityLimits(range_center_dof=(0.0, 0.0, 0.0, 0.0, 0.0, 760.0),
                         range_half_width_dof=(10.0, 10.0, 10.0, 60.0, 60.0, 180.0),
                         tolerance=Tolerance(position_mm=10.0, angle_deg=3.0))


def approach_params(camera: Camera) -> FeatureParams:
    """Image-stage parameters of the full measurement during an approach: the field chain with
    outline templates at 600-900 mm (``roi_depths_mm``; the default matches only the nominal
    600 mm, where a holder at 800-900 mm, 1.3-1.5 times smaller, scores ~0.3 and lands off
    centre)."""
    return FeatureParams.for_camera(camera, roi_depths_mm=(600.0, 675.0, 750.0, 825.0, 900.0))

