"""The frames of the robot cell, drawn for docs/robot.md (docs/img/robot_frames.png).

    python benchmarks/robot_figure.py docs/img/robot_frames.png

The cell is the simulated one (:class:`cutterpose.robot.cell.RobotCell`): the camera on the
flange, the plate on a table, the holder on the cutterhead seen from its nominal station.
"""

from __future__ import annotations

import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from cutterpose.geometry.camera import default_camera  # noqa: E402
from cutterpose.geometry.holder import default_holder  # noqa: E402
from cutterpose.geometry.pose import Pose  # noqa: E402
from cutterpose.robot.cell import RobotCell  # noqa: E402


def draw_frame(ax, T: Pose, name: str, length: float = 120.0) -> None:
    o = T.t_mm
    for k, c in enumerate("rgb"):
        d = T.R[:, k] * length
        ax.quiver(*o, *d, color=c, linewidth=1.5, arrow_length_ratio=0.15)
    ax.text(*(o + [0, 0, 40]), name, fontsize=9, weight="bold")


def main(out: str) -> None:
    cell = RobotCell(default_camera("table1"))
    T_bh = cell.holder_in_base()
    A = cell.flange_for(Pose.from_euler(2.0, -3.0, 4.0, 8.0, -6.0, 612.0), T_bh)
    T_bc = A @ cell.T_flange_cam
    base = Pose(np.eye(3), np.zeros(3), "base", "base")
    fig = plt.figure(figsize=(8, 6))
    ax = fig.add_subplot(projection="3d")
    for T, n in ((base, "base"), (A, "flange"), (T_bc, "cam"), (cell.T_base_plate, "plate"),
                 (T_bh, "holder = grasp (default)")):
        draw_frame(ax, T, n)
    # the holder's outline and the plate, in the base frame
    h = default_holder()
    rect = np.c_[h.outer_rectangle_mm, np.zeros(4)]
    ring = T_bh.apply(np.vstack([rect, rect[:1]]))
    ax.plot(*ring.T, color="k", linewidth=1)
    inner = T_bh.apply(np.vstack([h.points_holder_mm, h.points_holder_mm[:1]]))
    ax.plot(*inner.T, color="0.4", linewidth=0.8)
    ex, ey = cell.plate.half_extent_mm
    sq = np.array([[-ex, -ey, 0], [ex, -ey, 0], [ex, ey, 0], [-ex, ey, 0], [-ex, -ey, 0]])
    ax.plot(*cell.T_base_plate.apply(sq).T, color="tab:purple", linewidth=1)
    # the robot's arm, schematically, and the camera's line of sight
    ax.plot(*np.stack([np.zeros(3), [0, 0, 600], A.t_mm]).T, color="0.6", linewidth=4,
            alpha=0.6)
    ax.plot(*np.stack([T_bc.t_mm, T_bh.t_mm]).T, "k--", linewidth=0.8)
    ax.set_xlabel("base x [mm]")
    ax.set_ylabel("base y [mm]")
    ax.set_zlabel("base z [mm]")
    ax.set_box_aspect((1.6, 1.0, 1.0))
    ax.view_init(elev=22, azim=-60)
    ax.set_title("T_base_holder = T_base_flange @ T_flange_cam @ T_cam_holder\n"
                 "axes: x red, y green, z blue; camera z = line of sight", fontsize=9)
    fig.tight_layout()
    fig.savefig(out, dpi=110)


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "docs/img/robot_frames.png")
