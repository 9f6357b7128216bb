"""The measuring station: everything a measurement needs, assembled in one place.

A :class:`Station` holds the camera, the holder model, the pose method, the image stage's
parameters, the quality limits, the edge look calibrated in the cell and the robot path
(hand-eye calibration, robot accuracy, grasp tolerance). :func:`build_station` makes one from
arguments (objects, or the names and files the CLI and the cell file give); the cell file of
``cutterpose serve`` (:func:`cutterpose.service.config.load_cell`), the CLI's ``measure`` and
``track``, the tracker and the Python API all build theirs with it, so that the same arguments
measure the same way everywhere::

    from cutterpose.station import build_station

    station = build_station(camera="table1", method="dm+b", edge_break_mm=0.5)
    m = station.measure("holder.png")                 # camera frame
    m = station.measure("holder.png", T_base_flange=flange_pose)   # + the base frame

The station's limits and image parameters follow from its arguments:

>>> from cutterpose.station import build_station
>>> s = build_station("table1", method="dm+", distance_mm=700, edge_break_mm=0)
>>> s.method, s.limits.range_center_dof[5], s.limits.edge_break_mm, s.params.roi_depths_mm
('dm+', 700.0, 0, (700.0,))

Convention:
    Poses as in :mod:`cutterpose.geometry.pose`; ``distance_mm`` the camera-to-holder distance
    of the station (the working range's centre and the region search's scale).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

from .budget import Tolerance
from .errors import InputError
from .geometry.camera import Camera, default_camera
from .geometry.holder import Holder, default_holder
from .image import FeatureParams
from .methods import get_method
from .pipeline import Measurement, measure, station_center_dof, station_params
from .robot import GraspTolerance, RobotAccuracy
from .verdict import QualityLimits

__all__ = ["Station", "build_station"]


@dataclass(frozen=True)
class Station:
    """A measuring station (module doc; picklable: worker processes get it whole).

    Attributes
    ----------
    camera, holder : the camera model and the (default) holder model.
    method : the pose method's registered name (:mod:`cutterpose.methods`).
    params : the image stage's parameters (:func:`cutterpose.pipeline.station_params`).
    limits : when a pose is refused (:class:`cutterpose.verdict.QualityLimits`).
    edge_look : the edge look calibrated in the cell (None: the generic looks).
    handeye : the hand-eye calibration (:class:`cutterpose.robot.HandEye`), None without a
        robot path.
    robot_accuracy, grasp_tolerance : the robot path's flange-pose error and grasp verdict.
    chain, distance_mm : the image chain (field or paper) and the camera-to-holder distance
        (None: the paper's 600 mm) the parameters and limits were made for.
    """

    camera: Camera
    holder: Holder
    method: str = "dm+b"
    params: FeatureParams | None = None
    limits: QualityLimits = field(default_factory=QualityLimits)
    edge_look: object = None
    handeye: object = None
    robot_accuracy: RobotAccuracy = field(default_factory=RobotAccuracy)
    grasp_tolerance: GraspTolerance = field(default_factory=GraspTolerance)
    chain: str = "field"
    distance_mm: float | None = None

    def measure(self, image, *, holder: Holder | None = None, T_base_flange=None,
                corners: bool | None = None) -> Measurement:
        """Measure ``image`` (a path, a raw buffer or an array: :func:`cutterpose.pipeline.
        measure`) at this station; with ``T_base_flange`` (the flange pose at the picture) also
        in the robot's base frame with the grasp verdict (``.robot``: :meth:`locate`).
        ``holder``: another of the cell's holder models."""
        hol = holder or self.holder
        if T_base_flange is not None:
            self._check_robot_path()
        m = measure(image, self.camera, hol, self.method, self.params, self.limits,
                    edge_look=self.edge_look, corners=corners)
        if T_base_flange is not None:
            m.robot = self.locate(m, T_base_flange, holder=hol)
        return m

    def _check_robot_path(self) -> None:
        if self.handeye is None:
            raise InputError("the base frame needs a hand-eye calibration (--handeye, or "
                             "handeye in the cell file)")

    def locate(self, measurement: Measurement, T_base_flange, *, holder: Holder | None = None):
        """The robot path: ``measurement``'s holder and grasp frame in the base frame, with the
        covariance and the grasp verdict (:func:`cutterpose.robot.locate` with this station's
        hand-eye calibration, robot accuracy and grasp tolerance)."""
        self._check_robot_path()
        from .robot import locate

        return locate(measurement, self.handeye, T_base_flange, self.robot_accuracy,
                      camera=self.camera, holder=holder or self.holder,
                      tolerance=self.grasp_tolerance)


def _camera(camera) -> Camera:
    if camera is None or isinstance(camera, str) and camera in ("table1", "synthetic"):
        return default_camera(camera or "table1")
    if isinstance(camera, (str, Path)):
        from .geometry.camera_files import load_camera

        return load_camera(camera)
    return camera


def _loaded(obj, loader_module: str, loader: str):
    """``obj`` itself, or loaded from the file it names."""
    if obj is None or not isinstance(obj, (str, Path)):
        return obj
    import importlib

    return getattr(importlib.import_module(loader_module), loader)(obj)


def build_station(camera=None, holder=None, method: str = "dm+b", *, chain: str = "field",
                  distance_mm: float | None = None, params: FeatureParams | None = None,
                  limits: QualityLimits | dict | None = None,
                  edge_shape: str | None = None, edge_break_mm: float | None = None,
                  tolerance: Tolerance | None = None, edge_look=None, handeye=None,
                  robot_accuracy: RobotAccuracy | None = None,
                  grasp_tolerance: GraspTolerance | None = None) -> Station:
    """The measuring station from arguments (module doc).

    Parameters
    ----------
    camera : a :class:`Camera`, ``"table1"`` / ``"synthetic"`` (bundled), or a camera file;
        default Table 1.
    holder : a :class:`Holder` or a holder file; default the bundled holder.
    method : a registered pose method (an unknown name fails here, before any work).
    chain : the image chain, ``"field"`` or ``"paper"`` (paper section 2.1).
    distance_mm : the camera-to-holder distance (None: the paper's 600 mm): the region search's
        scale and the working range's centre (unless ``limits`` gives ``range_center_dof``).
    params : the image stage's parameters, when not those of ``chain`` at ``distance_mm``
        (the tracker's approach parameters).
    limits : a :class:`QualityLimits`, or a dict of its fields (a cell file's
        ``[tolerances]``, its ``tolerance`` a dict of :class:`~cutterpose.budget.Tolerance`'s
        fields); ``edge_shape``, ``edge_break_mm`` and ``tolerance`` (the error budget's
        :class:`~cutterpose.budget.Tolerance`) override its fields when given.
    edge_look : the cell's calibrated edge look, or its file (``calibrate-edge-look``).
    handeye : the hand-eye calibration, or ``handeye.json``: the robot path.
    robot_accuracy, grasp_tolerance : the robot path's flange-pose error and grasp tolerance.

    Raises
    ------
    InputError
        An unknown method or chain, a bad limit; camera, holder, edge look or hand-eye files
        that cannot be read raise their own typed errors (:mod:`cutterpose.errors`).
    """
    get_method(method)
    if chain not in ("field", "paper"):
        raise InputError(f"the image chain must be 'field' or 'paper', got {chain!r}")
    cam = _camera(camera)
    hol = _loaded(holder, "cutterpose.geometry.holder", "load_holder") or default_holder()
    overrides = dict(limits) if isinstance(limits, dict) else {}
    base = limits if isinstance(limits, QualityLimits) else QualityLimits()
    if "range_center_dof" not in overrides and not isinstance(limits, QualityLimits):
        overrides["range_center_dof"] = station_center_dof(distance_mm)
    for key, v in (("edge_shape", edge_shape), ("edge_break_mm", edge_break_mm),
                   ("tolerance", tolerance)):
        if v is not None:
            overrides[key] = v
    if isinstance(overrides.get("tolerance"), dict):
        overrides["tolerance"] = Tolerance(**overrides["tolerance"])
    try:
        lim = replace(base, **overrides)
    except TypeError as e:
        raise InputError(f"quality limits: {e}") from None
    return Station(
        camera=cam, holder=hol, method=method,
        params=params if params is not None else station_params(cam, chain, distance_mm),
        limits=lim,
        edge_look=_loaded(edge_look, "cutterpose.calibration.edge_look", "load_edge_look"),
        handeye=_loaded(handeye, "cutterpose.calibration.handeye", "load_handeye"),
        robot_accuracy=robot_accuracy or RobotAccuracy(),
        grasp_tolerance=grasp_tolerance or GraspTolerance(), chain=chain,
        distance_mm=distance_mm)
