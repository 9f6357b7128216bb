"""Request and answer models of the service API, with units and frames (they make the OpenAPI
schema at ``/openapi.json``; ``docs/service.md`` is the prose version).

Convention:
    Poses as in PROTOCOL.md: ``x_cam = R_cam_holder @ x_holder + t_cam_holder_mm``,
    ``R = Rz(gamma) Ry(beta) Rx(alpha)``, angles in degrees, lengths in mm; camera frame x right,
    y down, z along the optical axis. ``T_a_b`` is the 4x4 transform of frame b in frame a
    (``x_a = T_a_b x_b``), mm. The flange pose ``T_base_flange`` travels as the PROTOCOL pose
    row ``x_mm,y_mm,z_mm,qx,qy,qz,qw`` (unit quaternion, scalar last). Pixels: observed
    (distorted) image pixels, (0, 0) the centre of the top-left pixel.
"""

from __future__ import annotations

import math
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

__all__ = ["ErrorBody", "MeasureQuery", "MeasureJSON", "MeasurementRecord", "MeasurementList",
           "Ready", "Health", "parse_flange_pose", "FLANGE_POSE_DOC", "REQUEST_ID_PATTERN",
           "ImageQuery", "TrackFrameQuery", "TrackCreate", "TrackInfo", "TrackFrameOut"]

REQUEST_ID_PATTERN = r"^[A-Za-z0-9._:-]{1,128}$"
FLANGE_POSE_DOC = ("The robot's flange pose T_base_flange when the picture was taken, as the "
                   "PROTOCOL.md pose row `x_mm,y_mm,z_mm,qx,qy,qz,qw`: flange origin in the "
                   "base frame [mm] and unit quaternion of R_base_flange, scalar last "
                   "(|q| within 1e-3 of 1; it is normalised).")
MAX_TRANSLATION_MM = 1e5  # 100 m: anything larger is a unit mistake (m vs mm), not a robot


def parse_flange_pose(value) -> list[float]:
    """The 7 numbers of a flange pose row (a ``"x,y,z,qx,qy,qz,qw"`` string or a list), the
    quaternion normalised.

    Raises
    ------
    ValueError
        Not 7 finite numbers, translation beyond 100 m, or a quaternion far from unit norm.
    """
    try:
        parts = value.split(",") if isinstance(value, str) else list(value)
    except TypeError:
        raise ValueError("flange_pose must be 7 numbers x_mm,y_mm,z_mm,qx,qy,qz,qw") from None
    if len(parts) != 7:
        raise ValueError(f"flange_pose needs 7 numbers x_mm,y_mm,z_mm,qx,qy,qz,qw, got "
                         f"{len(parts)}")
    try:
        v = [float(p) for p in parts]
    except (TypeError, ValueError, OverflowError):
        raise ValueError("flange_pose: every element must be a number") from None
    if not all(math.isfinite(x) for x in v):
        raise ValueError("flange_pose: every element must be finite")
    if max(abs(x) for x in v[:3]) > MAX_TRANSLATION_MM:
        raise ValueError(f"flange_pose: translation beyond {MAX_TRANSLATION_MM:g} mm (metres "
                         "given instead of mm?)")
    n = math.sqrt(sum(x * x for x in v[3:]))
    if abs(n - 1.0) > 1e-3:
        raise ValueError(f"flange_pose: the quaternion qx,qy,qz,qw must have unit norm, got "
                         f"|q| = {n:.6g}")
    return v[:3] + [x / n for x in v[3:]]


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid")


class _Open(BaseModel):
    # answers carry what the pipeline adds later (issues 10, 11) without a schema change here
    model_config = ConfigDict(extra="allow")


class ErrorBody(_Model):
    """Every 4xx/5xx answer."""

    error: str = Field(description="Machine-readable code: unauthorized, too_large, "
                       "unsupported_media_type, empty_body, bad_json, validation_error, "
                       "bad_flange_pose, image_unusable, bad_input, conflict, not_found, "
                       "image_not_kept, queue_full, deadline_exceeded, worker_crashed, "
                       "shutting_down, internal_error, too_many_tracks")
    message: str = Field(description="One line for a person.")
    detail: list | None = Field(None, description="Per-field errors of a validation_error.")


class ImageQuery(_Model):
    """Query parameters of every request with an image body: the flange pose at the picture
    and a raw body's size."""

    flange_pose: str | None = Field(None, description=FLANGE_POSE_DOC,
                                    examples=["850.0,-120.5,1430.2,0,0,0.7071068,0.7071068"])
    width: int | None = Field(None, ge=1, le=65535, description="Raw bodies only: image width "
                              "[px].")
    height: int | None = Field(None, ge=1, le=65535, description="Raw bodies only: image "
                               "height [px].")


class MeasureQuery(ImageQuery):
    """Query parameters of ``POST /v1/measurements`` with an image body."""

    request_id: str | None = Field(None, pattern=REQUEST_ID_PATTERN, description=(
        "The client's id of this request (1..128 of A-Z a-z 0-9 . _ : -). A request repeated "
        "with the same id gets the first answer (same measurement id) without measuring again; "
        "the same id with a different image, flange pose or holder gets 409."))
    holder: str | None = Field(None, max_length=64, description="Holder model name from the "
                               "cell file (default: the cell's default_holder).")


class TrackFrameQuery(ImageQuery):
    """Query parameters of ``POST /v1/tracks/{id}/frames``."""

    t_s: float | None = Field(None, allow_inf_nan=False, description="The frame's time (s, the "
                              "camera's timestamp): for a client that sends the newest frame "
                              "and skips stale ones, the motion is then predicted per second. "
                              "For every frame of the session or for none.")
    frame_id: int | None = Field(None, ge=0, description="The camera's frame number "
                                 "(increasing; skipped frames leave gaps): the answer carries "
                                 "it and its messages name frames by it. For every frame of "
                                 "the session or for none.")


class MeasureJSON(_Model):
    """``POST /v1/measurements`` with ``Content-Type: application/json`` (image in base64)."""

    image_base64: str = Field(description="The image file (PNG, TIFF, JPEG) or raw 8-bit grey "
                              "pixels, base64.")
    format: Literal["png", "tiff", "jpeg", "raw"] = Field(description="Format of the image.")
    width: int | None = Field(None, ge=1, le=65535, description="Raw only: width [px].")
    height: int | None = Field(None, ge=1, le=65535, description="Raw only: height [px].")
    flange_pose: list[float] | None = Field(None, description=FLANGE_POSE_DOC + " As a list "
                                            "of 7 numbers.")
    request_id: str | None = Field(None, pattern=REQUEST_ID_PATTERN,
                                   description="As the query parameter.")
    holder: str | None = Field(None, max_length=64, description="As the query parameter.")


class PoseOut(_Open):
    """The holder pose in the camera frame, ``T_cam_holder``."""

    R_cam_holder: list[list[float]] = Field(description="3x3 rotation, holder axes in the "
                                            "camera frame.")
    t_cam_holder_mm: list[float] = Field(description="Holder origin in the camera frame [mm].")
    alpha_deg: float = Field(description="Rotation about x [deg] (R = Rz Ry Rx).")
    beta_deg: float = Field(description="Rotation about y [deg].")
    gamma_deg: float = Field(description="Rotation about z [deg].")
    X_mm: float
    Y_mm: float
    Z_mm: float = Field(description="Distance along the optical axis [mm].")


class QualityOut(_Open):
    """The pipeline's verdict on the camera-frame pose."""

    ok: bool = Field(description="The pose may be used.")
    reason: str = Field(description="Why it was refused (empty when ok).")
    rms_residual_px: float | None = Field(None, description="RMS residual [ideal px]: of the "
                                          "corners, or of the edge segments' design-edge "
                                          "points for dm+b.")
    ambiguity_ratio: float | None = Field(None, description="Best / second-best pose error.")


class MeasurementOut(_Open):
    """``Measurement.to_dict()`` of :func:`cutterpose.pipeline.measure` (as ``cutterpose
    measure --json``)."""

    method: str = Field(description="Pose method, e.g. dm+.")
    quality: QualityOut
    pose: PoseOut | None = Field(description="Camera-frame pose, null when none was found.")
    std: dict[str, float | None] = Field(description="1-sigma per DOF: alpha_deg, beta_deg, "
                                         "gamma_deg [deg], X_mm, Y_mm, Z_mm [mm].")
    corners_px: list[list[float | None]] | None = Field(description="The 20 detected corners "
                                                        "(observed px, contour order).")
    timings_ms: dict[str, float] = Field(description="Wall time per pipeline stage [ms].")


class RobotOut(_Open):
    """The base-frame step (cutterpose.robot.locate; PROTOCOL.md "Measurement JSON");
    ``available`` is false without a flange pose in the request or a hand-eye file in the
    cell. The other fields are those of ``RobotResult.to_dict()`` (``poses_ros``: every pose in
    ROS form, m and quaternion, with its 6x6 covariance)."""

    available: bool
    reason: str = Field("", description="Why it is not available.")
    T_base_flange: list[list[float]] | None = Field(None, description="4x4, mm: the flange "
                                                    "pose sent.")
    T_flange_cam: list[list[float]] | None = Field(None, description="4x4, mm: the hand-eye "
                                                   "calibration.")
    T_base_holder: list[list[float]] | None = Field(None, description="4x4, mm: the holder "
                                                    "in the robot's base frame (null when the "
                                                    "measurement has no pose).")
    T_base_grasp: list[list[float]] | None = Field(None, description="4x4, mm: where the "
                                                   "gripper's TCP must be to take the cutter.")
    grasp: dict | None = Field(None, description="verdict (grasp | retake), reason, hint, "
                               "position_3sigma_mm, angle_3sigma_deg, position_tolerance_mm, "
                               "angle_tolerance_deg, error_shares (measurement, hand-eye, "
                               "robot).")


class ImageOut(_Model):
    sha256: str = Field(description="SHA-256 of the body as received (hex).")
    bytes: int = Field(description="Body size [bytes].")
    format: Literal["png", "tiff", "jpeg", "raw"]
    width_px: int
    height_px: int


class TimingsOut(_Model):
    queue_ms: float = Field(description="Waiting for a worker [ms].")
    decode_ms: float = Field(description="Image decoding in the worker [ms].")
    measure_ms: float = Field(description="cutterpose.pipeline.measure in the worker [ms].")
    total_ms: float = Field(description="From the end of the upload to the answer, storage "
                            "excluded [ms].")


class MeasurementRecord(_Model):
    """One measurement, as answered and as stored (``GET`` returns it unchanged)."""

    id: str = Field(description="Measurement id (32 hex digits).")
    request_id: str | None = Field(description="The client's request id, if given.")
    created_at: str = Field(description="When it was measured, ISO 8601 UTC.")
    cell: str = Field(description="The cell file's name.")
    holder: str = Field(description="Holder model used.")
    flange_pose: list[float] | None = Field(description="T_base_flange as sent (row x_mm, y_mm, "
                                            "z_mm, qx, qy, qz, qw, quaternion normalised).")
    ok: bool = Field(description="Usable: the pose passed the quality verdict (and the grasp "
                     "check when the robot frame is available).")
    verdict: Literal["grasp", "retake"] = Field(description="What the robot should do.")
    verdict_basis: Literal["grasp_check", "camera_quality"] = Field(
        description="grasp_check: from the base-frame grasp verdict; camera_quality: from the "
                    "camera-frame quality only (no robot frame available).")
    measurement: MeasurementOut
    robot: RobotOut
    image: ImageOut
    timings_ms: TimingsOut


class MeasurementList(_Model):
    measurements: list[MeasurementRecord]
    next_since: str | None = Field(description="created_at of the last one: pass it as `since` "
                                   "for the next page (inclusive: skip ids already seen).")


class Health(_Model):
    status: Literal["alive"]


class Ready(_Model):
    ready: bool = Field(description="Cell loaded, every worker up.")
    workers: list[dict] = Field(description="Per worker: pid, alive, ready, busy, restarts.")
    queued: int = Field(description="Requests waiting for a worker.")
    cell: dict = Field(description="Camera, holders, method of the cell file.")


# -- tracking sessions (:mod:`.tracks`) ---------------------------------------------------
class TrackCreate(_Model):
    """``POST /v1/tracks``: a tracking session for one approach."""

    holder: str | None = Field(None, max_length=64, description="Holder model name from the "
                               "cell file (default: the cell's default_holder).")
    filter: bool = Field(True, description="Also report the temporal filter's pose "
                         "(constant velocity on SE(3)) beside the raw per-frame pose.")
    anchor_lag: int | None = Field(None, ge=0, le=30, description="dm+b: re-anchors (the band "
                                   "fit, ~120 ms) run beside the tracking and are applied this "
                                   "many frames later (0: on their frame, which then waits; "
                                   "default: the tracker's); > 0 also measures a frame the "
                                   "tracker cannot follow beside it: that frame answers at "
                                   "once with mode 'lost', the next ones are tracked "
                                   "meanwhile.")


class TrackInfo(_Model):
    """A tracking session."""

    id: str = Field(description="Session id (32 hex digits).")
    created_at: str = Field(description="ISO 8601 UTC.")
    holder: str
    method: str = Field(description="The full measurement's pose method (first frame, "
                        "fall-backs).")
    frames: int = Field(description="Frames answered so far.")
    last_mode: Literal["track", "full", "lost"] | None = Field(description="The last frame's "
                                                               "mode.")
    idle_timeout_s: float = Field(description="The session is closed after this long "
                                  "without a frame.")
    filter: bool
    anchor_lag: int


class TrackFrameOut(_Open):
    """One frame's answer: ``TrackResult.to_dict()`` (as ``cutterpose track --json-lines``)
    and the base frame."""

    track_id: str
    frame: int = Field(description="0-based index of the frame in the session.")
    frame_id: int = Field(description="The camera's frame number sent with the frame "
                          "(``frame_id``), else ``frame``.")
    mode: Literal["track", "full", "lost"] = Field(description="track: from the predicted "
                                                   "edges; full: measured in full (first "
                                                   "frame, fall-back); lost: no pose.")
    ok: bool
    fallback_reason: str = Field(description="Why the frame was measured in full (or lost).")
    pose: PoseOut | None
    std: dict[str, float | None] = Field(description="1-sigma per DOF [deg, mm].")
    filtered_pose: PoseOut | None = Field(None, description="The temporal filter's pose "
                                          "(never instead of the raw one).")
    anchor: str = Field("", description="dm+b: re-anchoring of the edges' offsets from the "
                        "design edge on this frame.")
    robot: RobotOut
    timings_ms: dict[str, float] = Field(description="The tracker's stages, and decode_ms, "
                                         "track_ms, total_ms of the request [ms].")
