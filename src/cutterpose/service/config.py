"""The cell file of ``cutterpose serve``: camera, holder model(s), hand-eye file, tolerances and
service settings, read once at start and validated (a bad field stops the start with a message
naming it).

A cell file is TOML (read with :mod:`tomllib`); every key is optional and defaults to the
bundled Table 1 cell (``cutterpose/data/cell_table1.toml``)::

    name = "cell 1"
    camera = "camera.json"            # a camera file, or "table1" / "synthetic" (bundled)
    distance_mm = 600                 # the robot's measuring station: camera to holder, mm
                                      # (the region search's scale and the working range's
                                      # centre; [tolerances] range_center_dof wins)
    method = "dm+b"                   # pose method (cutterpose.methods)
    chain = "field"                   # image chain: field (default) or paper (section 2.1)
    handeye = "handeye.json"          # eye-in-hand calibration (PROTOCOL.md "Hand-eye file")
    edge_look = "look.json"           # dm+b's edge look calibrated in the cell
                                      # (`cutterpose calibrate-edge-look`); absent: generic
    default_holder = "default"

    [holders]                         # holder models by name; "default" = the bundled one
    default = "default"

    [tolerances]                      # when a pose is refused (pipeline.QualityLimits fields)
    max_rms_px = 1.5

    [robot]                           # the base-frame step (cutterpose.robot.locate)
    accuracy_mm = 0.05                # robot's position error, 1 sigma per axis
    accuracy_deg = 0.01               # robot's angle error, 1 sigma per axis
    grasp_tolerance_mm = 1.0          # grasp verdict: 3-sigma position bound
    grasp_tolerance_deg = 0.265       # 3-sigma angle bound (default: position / cutter radius)

    [service]
    data_dir = "/var/lib/cutterpose"  # SQLite database and images; CUTTERPOSE_DATA_DIR wins
    workers = 0                       # worker processes; 0 = one per core
    queue_size = 32                   # requests waiting beyond the busy workers, then 503
    deadline_s = 30                   # per request, queue wait included, then 504
    max_body_mb = 64                  # larger bodies get 413
    image_cap_mb = 2048               # stored images, oldest evicted first; 0 = keep none
    token_file = "token.txt"          # bearer token; CUTTERPOSE_TOKEN wins
    header_timeout_s = 10             # a request head not complete by then: connection closed
    body_idle_timeout_s = 10          # no body byte for this long: 408, connection closed
    upload_timeout_s = 120            # the whole body not in by then: 408, connection closed
    keep_alive_s = 5                  # an idle keep-alive connection is closed after this
    max_header_kb = 16                # a larger request head: 400, connection closed
    max_connections = 1000            # connections beyond this are closed at once
    auth_max_failures = 20            # wrong tokens from one address within auth_window_s,
    auth_window_s = 60                #   then 429 for that address until the window clears

Relative paths are relative to the cell file's folder, except ``data_dir``, which is relative to
the current directory (default ``./cutterpose-data``), so that the bundled cell file never
writes into the installed package.

Convention:
    Units in key names (``_px``, ``_deg``, ``_mm``, ``_s``, ``_mb`` = 2**20 bytes); six-element
    tolerances are per DOF in the order alpha, beta, gamma [deg], X, Y, Z [mm] (pipeline.py).
"""

from __future__ import annotations

import dataclasses
import os
import tomllib
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from ..calibration.edge_look import EdgeLookCalibration, load_edge_look
from ..calibration.handeye import HandEye, load_handeye
from ..errors import CellFileError, CutterposeError
from ..geometry.camera import Camera, default_camera
from ..geometry.camera_files import load_camera
from ..geometry.holder import Holder, default_holder, load_holder
from ..image import FeatureParams
from ..methods import get_method
from ..pipeline import QualityLimits, station_params
from ..robot import GraspTolerance, RobotAccuracy
from ..station import Station, build_station

__all__ = ["Cell", "ServiceSettings", "load_cell", "bundled_cell_path", "TOKEN_ENV",
           "DATA_DIR_ENV"]

TOKEN_ENV = "CUTTERPOSE_TOKEN"
DATA_DIR_ENV = "CUTTERPOSE_DATA_DIR"
BUNDLED_CELL = "cell_table1.toml"

Positive = Annotated[float, Field(gt=0, allow_inf_nan=False)]
Six = Annotated[tuple[float, float, float, float, float, float], Field()]
Finite = Annotated[float, Field(allow_inf_nan=False)]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class _BudgetTolerance(_Strict):
    """The error budget's tolerance (:class:`cutterpose.budget.Tolerance`): 3-sigma position at
    the grasp point [mm] and rotation [deg] above which a measurement is refused."""

    position_mm: Positive = 1.0
    angle_deg: Positive = 0.3
    k_sigma: Positive = 3.0


class _Tolerances(_Strict):
    """Overrides of :class:`cutterpose.pipeline.QualityLimits` (absent: the pipeline's default)."""

    max_rms_px: Positive | None = None
    max_corner_residual_px: Positive | None = None
    max_ambiguity_ratio: Positive | None = None
    range_center_dof: Six | None = None
    range_half_width_dof: Six | None = None
    range_tolerance_dof: Six | None = None
    max_std_dof: Six | None = None
    max_edge_bias_dof: Six | None = None
    tolerance: _BudgetTolerance | None = None
    grasp_point_mm: tuple[Finite, Finite, Finite] | None = None
    edge_shape: Literal["unknown", "round", "chamfer"] | None = None
    #: the pocket edge's largest break for the corner methods' verdict (absent: not known)
    edge_break_mm: float | None = Field(None, ge=0, allow_inf_nan=False)

    @field_validator("range_half_width_dof", "range_tolerance_dof", "max_std_dof",
                     "max_edge_bias_dof")
    @classmethod
    def _non_negative(cls, v):
        if v is not None and not all(0 <= x < float("inf") for x in v):
            raise ValueError("every element must be finite and >= 0")
        return v


class _Robot(_Strict):
    accuracy_mm: float = Field(0.05, ge=0, allow_inf_nan=False)
    accuracy_deg: float = Field(0.01, ge=0, allow_inf_nan=False)
    grasp_tolerance_mm: Positive = 1.0
    grasp_tolerance_deg: Positive | None = None


class _Service(_Strict):
    data_dir: str | None = None
    workers: int = Field(0, ge=0, le=256)
    queue_size: int = Field(32, ge=0, le=100_000)
    deadline_s: Positive = 30.0
    max_body_mb: Positive = 64.0
    image_cap_mb: float = Field(2048.0, ge=0, allow_inf_nan=False)
    token_file: str | None = None
    max_tracks: int = Field(4, ge=0, le=1024)
    track_idle_s: Positive = 60.0
    header_timeout_s: Positive = 10.0
    body_idle_timeout_s: Positive = 10.0
    upload_timeout_s: Positive = 120.0
    keep_alive_s: float = Field(5.0, ge=1, le=3600, allow_inf_nan=False)
    max_header_kb: float = Field(16.0, ge=1, le=1024, allow_inf_nan=False)
    max_connections: int = Field(1000, ge=1, le=100_000)
    auth_max_failures: int = Field(20, ge=1, le=1_000_000)
    auth_window_s: Positive = 60.0


class _CellFile(_Strict):
    name: str = "cell"
    camera: str = "table1"
    distance_mm: Positive | None = None
    method: str = "dm+b"
    chain: Literal["field", "paper"] = "field"
    handeye: str | None = None
    edge_look: str | None = None
    default_holder: str = "default"
    holders: dict[str, str] = Field(default_factory=lambda: {"default": "default"})
    tolerances: _Tolerances = _Tolerances()
    robot: _Robot = _Robot()
    service: _Service = _Service()


@dataclass(frozen=True)
class ServiceSettings:
    """The ``[service]`` section, resolved (paths absolute, sizes in bytes)."""

    data_dir: Path
    workers: int
    queue_size: int
    deadline_s: float
    max_body_bytes: int
    image_cap_bytes: int
    max_tracks: int = 4            #: tracking sessions open at once (:mod:`.tracks`)
    track_idle_s: float = 60.0     #: a session unused this long is closed
    #: hostile-client limits (:mod:`.server`, :func:`.bodies.read_body`, :mod:`.deps`)
    header_timeout_s: float = 10.0
    body_idle_timeout_s: float = 10.0
    upload_timeout_s: float = 120.0
    keep_alive_s: float = 5.0
    max_header_bytes: int = 16 * 1024
    max_connections: int = 1000
    auth_max_failures: int = 20
    auth_window_s: float = 60.0


@dataclass(frozen=True)
class Cell:
    """A loaded and validated cell: what every worker needs to measure (picklable; the bearer
    token is kept apart in :attr:`token` and not sent to the workers, see :meth:`for_worker`)."""

    path: Path
    name: str
    camera: Camera
    camera_source: str
    holders: dict[str, Holder]
    default_holder: str
    method: str
    chain: str
    limits: QualityLimits
    handeye: HandEye | None
    handeye_path: Path | None
    robot_accuracy: RobotAccuracy
    grasp_tolerance: GraspTolerance
    service: ServiceSettings
    token: str = field(default="", repr=False)
    #: dm+b's edge look calibrated in the cell (None: the generic looks)
    edge_look: EdgeLookCalibration | None = None
    #: the measuring station's camera-to-holder distance (None: the paper's 600 mm)
    distance_mm: float | None = None
    #: the measuring station these fields make (:func:`cutterpose.station.build_station`)
    station: Station | None = None

    def holder(self, name: str | None) -> Holder:
        return self.holders[name or self.default_holder]

    def feature_params(self) -> FeatureParams:
        """The image processing parameters, as ``cutterpose measure --chain --distance-mm``
        uses them."""
        if self.station is not None:
            return self.station.params
        return station_params(self.camera, self.chain, self.distance_mm)

    def for_worker(self) -> Cell:
        """This cell without the token (what is pickled to the worker processes)."""
        return dataclasses.replace(self, token="")

    def describe(self) -> dict:
        """Public summary (``/ready``): no secrets, no absolute paths of the host."""
        w, h = self.camera.image_size_px
        return {"name": self.name, "camera": self.camera_source, "image_size_px": [w, h],
                "holders": sorted(self.holders), "default_holder": self.default_holder,
                "method": self.method, "chain": self.chain,
                "handeye": self.handeye is not None,
                "edge_look": self.edge_look is not None}


def bundled_cell_path() -> Path:
    """The bundled default cell file (Table 1 camera, bundled holder, no hand-eye file)."""
    return Path(str(resources.files("cutterpose.data").joinpath(BUNDLED_CELL)))


def _where(loc) -> str:
    return ".".join(str(p) for p in loc) or "(top level)"


def _resolve(base: Path, name: str) -> Path:
    p = Path(name).expanduser()
    return p if p.is_absolute() else base / p


def _read_token(cell_dir: Path, token_file: str | None, env: dict) -> str:
    tok = env.get(TOKEN_ENV)
    where = f"environment variable {TOKEN_ENV}"
    if not tok and token_file:
        p = _resolve(cell_dir, token_file)
        try:
            tok = p.read_text().strip()
        except OSError as e:
            raise CellFileError(f"service.token_file: {p}: cannot be read ({e.strerror})"
                                ) from None
        where = f"service.token_file {p}"
    if not tok:
        raise CellFileError(f"no bearer token: set {TOKEN_ENV} or name a file in "
                            "service.token_file (a token is never taken from the command line)")
    tok = tok.strip()
    if not tok or any(c.isspace() for c in tok) or not tok.isprintable():
        raise CellFileError(f"{where}: the token must be printable and without spaces")
    return tok


def load_cell(path: str | Path | None = None, env: dict | None = None,
              need_token: bool = True) -> Cell:
    """Read and validate a cell file (``None``: the bundled one).

    Parameters
    ----------
    path : the TOML cell file.
    env : environment to read ``CUTTERPOSE_TOKEN`` / ``CUTTERPOSE_DATA_DIR`` from
        (default ``os.environ``).
    need_token : refuse a cell without a bearer token (the service always needs one).

    Raises
    ------
    CellFileError
        Missing file, bad TOML, an unknown key or a bad value (the message names the field),
        an unknown method, an unreadable camera / holder / hand-eye file, or no token.
    """
    env = os.environ if env is None else env
    path = bundled_cell_path() if path is None else Path(path)
    if not path.is_file():
        raise CellFileError(f"{path}: cell file not found")
    try:
        raw = tomllib.loads(path.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise CellFileError(f"{path}: not valid TOML ({e})") from None
    try:
        cf = _CellFile.model_validate(raw)
    except ValidationError as e:
        err = e.errors()[0]
        more = f" (and {e.error_count() - 1} more)" if e.error_count() > 1 else ""
        raise CellFileError(f"{path}: {_where(err['loc'])}: {err['msg']}{more}") from None
    base = path.resolve().parent

    def field_error(name: str, e: Exception) -> CellFileError:
        return CellFileError(f"{path}: {name}: {e}")

    try:
        get_method(cf.method)
    except CutterposeError as e:
        raise field_error("method", e) from None
    try:
        camera = (default_camera(cf.camera) if cf.camera in ("table1", "synthetic")
                  else load_camera(_resolve(base, cf.camera)))
    except CutterposeError as e:
        raise field_error("camera", e) from None
    holders = {}
    for name, src in cf.holders.items():
        try:
            holders[name] = (default_holder() if src == "default"
                             else load_holder(_resolve(base, src)))
        except CutterposeError as e:
            raise field_error(f"holders.{name}", e) from None
    if cf.default_holder not in holders:
        raise CellFileError(f"{path}: default_holder: {cf.default_holder!r} is not in "
                            f"[holders] ({', '.join(sorted(holders))})")
    handeye_path = _resolve(base, cf.handeye) if cf.handeye else None
    try:
        handeye = load_handeye(handeye_path) if handeye_path else None
    except CutterposeError as e:
        raise field_error("handeye", e) from None
    try:
        edge_look = load_edge_look(_resolve(base, cf.edge_look)) if cf.edge_look else None
    except CutterposeError as e:
        raise field_error("edge_look", e) from None
    try:
        accuracy = RobotAccuracy(cf.robot.accuracy_mm, cf.robot.accuracy_deg)
        tolerance = GraspTolerance(cf.robot.grasp_tolerance_mm,
                                   angle_deg=cf.robot.grasp_tolerance_deg)
    except (CutterposeError, ValueError) as e:
        raise field_error("robot", e) from None
    overrides = {k: v for k, v in cf.tolerances.model_dump().items() if v is not None}
    try:
        station = build_station(camera, holders[cf.default_holder], cf.method, chain=cf.chain,
                                distance_mm=cf.distance_mm, limits=overrides,
                                edge_look=edge_look, handeye=handeye, robot_accuracy=accuracy,
                                grasp_tolerance=tolerance)
    except CutterposeError as e:
        raise field_error("tolerances", e) from None
    s = cf.service
    data_dir = env.get(DATA_DIR_ENV) or s.data_dir or "cutterpose-data"
    workers = s.workers or (os.cpu_count() or 1)
    service = ServiceSettings(
        data_dir=Path(data_dir).expanduser().resolve(), workers=workers,
        queue_size=s.queue_size, deadline_s=float(s.deadline_s),
        max_body_bytes=int(s.max_body_mb * 2 ** 20),
        image_cap_bytes=int(s.image_cap_mb * 2 ** 20),
        max_tracks=s.max_tracks, track_idle_s=float(s.track_idle_s),
        header_timeout_s=float(s.header_timeout_s),
        body_idle_timeout_s=float(s.body_idle_timeout_s),
        upload_timeout_s=float(s.upload_timeout_s), keep_alive_s=float(s.keep_alive_s),
        max_header_bytes=int(s.max_header_kb * 1024), max_connections=s.max_connections,
        auth_max_failures=s.auth_max_failures, auth_window_s=float(s.auth_window_s))
    token = ""
    if need_token:
        try:
            token = _read_token(base, s.token_file, env)
        except CellFileError as e:
            raise CellFileError(f"{path}: {e}") from None
    return Cell(path=path, name=cf.name, camera=camera, camera_source=cf.camera,
                distance_mm=cf.distance_mm,
                holders=holders, default_holder=cf.default_holder, method=cf.method,
                chain=cf.chain, limits=station.limits, handeye=handeye,
                handeye_path=handeye_path, robot_accuracy=accuracy, grasp_tolerance=tolerance,
                service=service, token=token, edge_look=edge_look, station=station)
