"""A simulated robot cell with known truth: camera on the flange, a fixed plate, a holder.

The cell knows the true ``T_flange_cam`` (the hand-eye transform), ``T_base_plate`` and, for
the end-to-end check, ``T_base_holder``. A station is a true flange pose; the robot *reports*
it with its repeatability error (what a real controller gives), while the images are rendered
from the true pose. So a hand-eye calibration or a base-frame measurement made from the
reported poses and the images can be compared with the truth.

Stations for the hand-eye calibration follow the advice given to users (``docs/robot.md``):
the plate seen from 400-700 mm, the camera tilted 20-45 deg against the plate in directions
that turn by the golden angle from station to station, turned about its axis at random, the
whole plate in view (:func:`cutterpose.calibration.plate.sample_plate_poses` draws these
camera-to-plate poses; the flange pose follows). Stations for a holder measurement put the
holder in the measurement's working range (+-10 deg, +-20 mm around 600 mm in front of the
camera, PROTOCOL.md, real-image experiment).

Convention:
    ``T_a_b`` maps frame b into frame a, mm (PROTOCOL.md, "Robot cell"). Robot error: the
    reported flange pose is ``t + e_t``, ``Exp(e_phi) R`` with ``e_t ~ N(0, rep_mm^2 I)`` and
    ``e_phi ~ N(0, rep_rad^2 I)`` in base axes (the convention of
    :mod:`cutterpose.robot.frames`).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from ..calibration.plate import CirclePlate, render_plate, sample_plate_poses
from ..geometry.camera import Camera
from ..geometry.pose import Pose

__all__ = ["RobotCell", "perturb_pose"]


def perturb_pose(pose: Pose, rng: np.random.Generator, sigma_mm: float,
                 sigma_deg: float) -> Pose:
    """``pose`` moved by N(0, sigma_mm) per axis and turned by N(0, sigma_deg) per base axis."""
    dphi = np.radians(rng.normal(0.0, sigma_deg, 3))
    return Pose(Rotation.from_rotvec(dphi).as_matrix() @ pose.R,
                pose.t_mm + rng.normal(0.0, sigma_mm, 3), pose.to_frame, pose.from_frame)


def _mount(rng: np.random.Generator | None) -> Pose:
    """A camera on the flange: 150 mm ahead of it, 80 mm aside, its axis along the flange's z,
    turned 90 deg about it; with ``rng`` a random mount within +-5 deg and +-20 mm of that."""
    R = Rotation.from_euler("z", 90, degrees=True)
    t = np.array([80.0, -40.0, 150.0])
    if rng is not None:
        R = Rotation.from_euler("xyz", rng.uniform(-5, 5, 3), degrees=True) * R
        t = t + rng.uniform(-20, 20, 3)
    return Pose(R.as_matrix(), t, "flange", "cam")


@dataclass
class RobotCell:
    """The simulated cell (module doc).

    Attributes
    ----------
    camera : the camera on the flange.
    T_flange_cam : the true hand-eye transform.
    T_base_plate : the plate, lying on a table in front of the robot.
    repeatability_mm, repeatability_deg : the robot's reporting error, 1 sigma per axis.
    plate : the circle plate.
    """

    camera: Camera
    T_flange_cam: Pose = field(default_factory=lambda: _mount(None))
    T_base_plate: Pose = field(default_factory=lambda: Pose(
        Rotation.from_euler("x", 180, degrees=True).as_matrix(), [1000.0, 0.0, 0.0],
        "base", "plate"))
    repeatability_mm: float = 0.03
    repeatability_deg: float = 0.005
    plate: CirclePlate = field(default_factory=CirclePlate)

    @classmethod
    def random(cls, camera: Camera, seed: int, **kwargs) -> RobotCell:
        """A cell with a random camera mount and plate yaw (one per seed)."""
        rng = np.random.default_rng([seed, 11])
        R = Rotation.from_euler("zx", [rng.uniform(-180, 180), 180], degrees=True).as_matrix()
        plate_pose = Pose(R, [rng.uniform(800, 1200), rng.uniform(-300, 300), 0.0],
                          "base", "plate")
        return cls(camera, _mount(rng), plate_pose, **kwargs)

    # ---- stations ----------------------------------------------------------------------------
    def flange_for(self, T_cam_x: Pose, T_base_x: Pose) -> Pose:
        """The true flange pose at which the camera sees frame x at ``T_cam_x``."""
        return T_base_x @ T_cam_x.inverse() @ self.T_flange_cam.inverse()

    def camera_view(self, T_base_flange: Pose, T_base_x: Pose) -> Pose:
        """``T_cam_x`` seen from the true flange pose."""
        return self.T_flange_cam.inverse() @ T_base_flange.inverse() @ T_base_x

    def plate_stations(self, count: int, seed: int, distance_mm=(400.0, 700.0),
                       tilt_deg=(20.0, 45.0)) -> list[Pose]:
        """True flange poses of ``count`` hand-eye stations (module doc)."""
        views = sample_plate_poses(self.camera, count, self.plate, distance_mm=distance_mm,
                                   tilt_deg=tilt_deg, seed=seed)
        return [self.flange_for(v, self.T_base_plate) for v in views]

    def holder_stations(self, T_base_holder: Pose, count: int, seed: int,
                        max_angle_deg: float = 8.0, max_shift_mm: float = 15.0) -> list[Pose]:
        """True flange poses from which the holder lies in the measurement's working range."""
        from ..render.analytic import random_pose

        rng = np.random.default_rng([seed, 12])
        return [self.flange_for(random_pose(rng, max_angle_deg, max_shift_mm), T_base_holder)
                for _ in range(count)]

    @staticmethod
    def holder_in_base() -> Pose:
        """A holder on the cutterhead in front of the robot: its Z along base +x (its face
        towards the robot), X along base y, 1.5 m ahead and 0.8 m up."""
        R = np.column_stack([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
        return Pose(R, [1500.0, 100.0, 800.0], "base", "holder")

    def report(self, T_base_flange: list[Pose], rng: np.random.Generator) -> list[Pose]:
        """What the controller reports for the true flange poses (repeatability error)."""
        return [perturb_pose(p, rng, self.repeatability_mm, self.repeatability_deg)
                for p in T_base_flange]

    # ---- images ------------------------------------------------------------------------------
    def plate_image(self, T_base_flange: Pose, rng: np.random.Generator,
                    settings=None) -> np.ndarray:
        return render_plate(self.camera, self.camera_view(T_base_flange, self.T_base_plate),
                            self.plate, settings=settings, rng=rng)

    def plate_points(self, T_base_flange: list[Pose], rng: np.random.Generator | None = None,
                     sigma_px: float = 0.0) -> np.ndarray:
        """(n, N, 2) circle centres the detector would give, without rendering: each circle's
        image-ellipse centre (projected centre + perspective bias,
        :func:`cutterpose.calibration.plate.ellipse_center_bias_px`) seen from the true flange
        poses, plus N(0, sigma_px) per coordinate (the measured detection noise). For Monte
        Carlo studies of the hand-eye calibration (``benchmarks/handeye_floor.py``)."""
        from ..calibration.plate import ellipse_center_bias_px

        out = []
        for a in T_base_flange:
            view = self.camera_view(a, self.T_base_plate)
            ctr = self.camera.project(view.apply(self.plate.points_mm))
            out.append(ctr + ellipse_center_bias_px(self.camera, view, self.plate))
        pts = np.stack(out)
        if sigma_px > 0:
            pts = pts + (rng or np.random.default_rng()).normal(0.0, sigma_px, pts.shape)
        return pts

    def truth_dict(self) -> dict:
        return {"T_flange_cam": self.T_flange_cam.matrix.tolist(),
                "T_base_plate": self.T_base_plate.matrix.tolist(),
                "robot_repeatability_mm": self.repeatability_mm,
                "robot_repeatability_deg": self.repeatability_deg,
                "camera": self.camera.to_dict(), "plate": self.plate.to_dict()}

    def write_handeye_set(self, out_dir, count: int, seed: int, settings=None,
                          progress=None) -> Path:
        """Render ``count`` stations into ``out_dir``: ``plate_NNNN.png``, the reported flange
        poses ``robot_poses.csv`` (PROTOCOL pose file), ``plate.json``, ``camera.json`` and
        ``cell_truth.json`` (true transforms and flange poses); and, for a holder measurement,
        ``holder_base_pose.csv`` (the true ``T_base_holder``), ``holder_station_true.csv`` and
        ``holder_station.csv`` (the true and the reported flange pose of a station that sees
        it), ``handeye_true.json`` (the true hand-eye transform, zero covariance, to render
        with). Returns the folder."""
        from ..calibration.plate import save_plate
        from ..robot.poses import write_poses

        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        true = self.plate_stations(count, seed)
        rng = np.random.default_rng([seed, 13])
        reported = self.report(true, rng)
        img_rng = np.random.default_rng([seed, 14])
        import cv2

        for k, a in enumerate(true):
            cv2.imwrite(str(out / f"plate_{k:04d}.png"), self.plate_image(a, img_rng, settings))
            if progress is not None:
                progress(k + 1, count)
        write_poses(out / "robot_poses.csv", reported)
        # a holder on the cutterhead and a station that sees it at the nominal pose, for the
        # worked example of docs/robot.md (true and reported flange pose)
        T_bh = self.holder_in_base()
        station = self.flange_for(Pose.from_euler(2.0, -3.0, 4.0, 8.0, -6.0, 612.0), T_bh)
        write_poses(out / "holder_base_pose.csv", [T_bh])
        write_poses(out / "holder_station_true.csv", [station])
        write_poses(out / "holder_station.csv", self.report([station], rng))
        save_plate(self.plate, out / "plate.json")
        (out / "camera.json").write_text(json.dumps(self.camera.to_dict(), indent=1) + "\n")
        doc = self.truth_dict() | {"seed": seed,
                                   "T_base_flange_true": [a.matrix.tolist() for a in true]}
        (out / "cell_truth.json").write_text(json.dumps(doc, indent=1) + "\n")
        from ..calibration.handeye import HandEye, save_handeye

        save_handeye(HandEye(self.T_flange_cam, self.T_base_plate, np.zeros((6, 6))),
                     out / "handeye_true.json")
        return out
