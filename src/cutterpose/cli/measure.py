"""Measuring: ``measure`` (one image), ``methods`` (the registry), ``demo``."""

from __future__ import annotations

import typer

from .app import (
    angle_unit_option,
    app,
    budget_deg_option,
    budget_mm_option,
    budget_tolerance,
    camera_from_option,
    convention_option,
    edge_break_option,
    edge_look_option,
    fail,
    friendly,
    length_unit_option,
    load_edge_look,
    log,
    pixel_format_option,
)


@app.command("measure")
@friendly
def measure_cmd(
    image: str = typer.Argument(..., help="Image of the holder (PNG, JPEG, TIFF...), or a raw "
                                "frame (.raw with a sidecar <file>.json, or --raw)."),
    camera: str = typer.Option(None, help="table1 (default), synthetic, or a camera file."),
    raw: str = typer.Option(None, "--raw", help="Read IMAGE as a raw frame of WIDTHxHEIGHT "
                            "pixels (as a GigE camera delivers it; Mono8: no decode)."),
    pixel_format: str = pixel_format_option(),
    holder: str = typer.Option(None, help="Holder JSON file (default: the bundled holder)."),
    method: str = typer.Option("dm+b", help="Pose method (cutterpose.methods; dm+b: the design "
                               "edge's pose from the band across each broken edge; dm+r: from "
                               "the corners and one radius; dm: the paper's chain)."),
    overlay: str = typer.Option(None, "--overlay", help="Write an overlay PNG here."),
    as_json: bool = typer.Option(False, "--json", help="One JSON object on stdout."),
    chain: str = typer.Option("field", help="Image chain: field (gradient outline, robust "
                              "lines; default) or paper (section 2.1: threshold 70, contour)."),
    edge_shape: str = typer.Option("unknown", help="The pocket edge's break as the holder's "
                                   "drawing gives it: round, chamfer, or unknown (default: dm+b "
                                   "tells them apart; dm+r's verdict then carries the chamfer's "
                                   "depth the contour cannot see)."),
    edge_break_mm: float = edge_break_option(),
    edge_look: str = edge_look_option(),
    budget_tol_mm: float = budget_mm_option(),
    budget_tol_deg: float = budget_deg_option(),
    distance_mm: float = typer.Option(None, "--distance-mm", help="The measuring station: "
                                      "camera to holder, mm (default: the paper's 600). The "
                                      "region search looks for the holder at this size and the "
                                      "working range (+-20 mm) is centred on it."),
    corners: bool = typer.Option(False, "--corners", help="Detect the corners even when the "
                                 "method does not need them (dm+b starts from the pocket "
                                 "outline: without this its JSON has no corners_px; ~14 ms)."),
    handeye: str = typer.Option(None, "--handeye", help="handeye.json: also answer in the "
                                "robot's base frame (needs --flange-pose)."),
    flange_pose: str = typer.Option(None, "--flange-pose", help="T_base_flange at the "
                                    "picture: a one-row pose file or x_mm,y_mm,z_mm,qx,qy,qz,"
                                    "qw inline."),
    convention: str = convention_option("a --flange-pose file"),
    length_unit: str = length_unit_option("a --flange-pose file"),
    angle_unit: str = angle_unit_option("a --flange-pose file"),
    robot_accuracy_mm: float = typer.Option(0.05, help="Robot position error, mm per axis "
                                            "(1 sigma)."),
    robot_accuracy_deg: float = typer.Option(0.01, help="Robot angle error, deg per axis "
                                             "(1 sigma)."),
    position_tol_mm: float = typer.Option(1.0, help="Grasp tolerance on the 3-sigma "
                                          "position bound, mm."),
    angle_tol_deg: float = typer.Option(None, help="Grasp tolerance on the 3-sigma angle "
                                        "bound, deg (default: position tolerance at the "
                                        "17-inch cutter's 216 mm radius, 0.265 deg)."),
):
    """Measure the holder's pose in one image (exit 3 when the pose is refused); with
    --handeye and --flange-pose also in the robot's base frame with the grasp verdict (exit 4
    on retake)."""
    import json as _json
    import time

    from ..errors import InputError
    from ..frames import load_frame, parse_raw_size
    from ..geometry.holder import default_holder, load_holder
    from ..pipeline import measure

    cam = camera_from_option(camera)
    hol = load_holder(holder) if holder else None
    look = load_edge_look(edge_look)
    if (handeye is None) != (flange_pose is None):
        raise InputError("the base frame needs both --handeye and --flange-pose")
    robot = None
    if handeye is not None:
        from ..robot import GraspTolerance, RobotAccuracy, load_flange_pose, load_handeye

        robot = (load_handeye(handeye),
                 load_flange_pose(flange_pose, convention, length_unit, angle_unit),
                 RobotAccuracy(robot_accuracy_mm, robot_accuracy_deg),
                 GraspTolerance(position_tol_mm, angle_deg=angle_tol_deg))

    if chain not in ("field", "paper"):
        fail(f"--chain must be 'field' or 'paper', got {chain!r}")
    t0 = time.perf_counter()
    img = load_frame(image, cam, parse_raw_size(raw) if raw else None, pixel_format)
    load_ms = (time.perf_counter() - t0) * 1e3
    from ..pipeline import QualityLimits, station_center_dof, station_params

    m = measure(img, cam, hol, method, params=station_params(cam, chain, distance_mm),
                limits=QualityLimits(edge_shape=edge_shape, edge_break_mm=edge_break_mm,
                                     tolerance=budget_tolerance(budget_tol_mm, budget_tol_deg),
                                     range_center_dof=station_center_dof(distance_mm)),
                edge_look=look, corners=True if corners else None)
    m.timings_ms = {"load": load_ms} | m.timings_ms
    if robot is not None:
        from ..robot import locate

        m.robot = locate(m, robot[0], robot[1], robot[2], camera=cam,
                         holder=hol or default_holder(), tolerance=robot[3])
    if overlay:
        from ..geometry.holder import default_holder
        from ..overlay import write_overlay

        write_overlay(img, m, cam, hol or default_holder(), overlay)
        log(f"wrote {overlay}")
    if as_json:
        typer.echo(_json.dumps(m.to_dict()))
    else:
        if m.pose is not None:
            typer.echo("\n".join(m.pose_lines()))
            typer.echo("time: " + ", ".join(f"{k} {v:.0f} ms" for k, v in m.timings_ms.items()))
        if m.robot is not None:
            typer.echo("\n".join(_robot_lines(m.robot)))
    if not m.ok:
        fail(f"pose refused: {m.quality.reason}", code=3)
    if m.robot is not None and not m.robot.grasp.ok:
        fail(f"retake: {m.robot.grasp.reason} -- {m.robot.grasp.hint}", code=4)


def _robot_lines(r) -> list[str]:
    """The base-frame answer in a few lines."""
    out = []
    for name, pc in (("T_base_holder", r.T_base_holder), ("T_base_grasp", r.T_base_grasp)):
        if pc is not None:
            a, b, g = pc.pose.euler_deg
            x, y, z = pc.pose.t_mm
            out.append(f"{name}: X {x:9.2f}  Y {y:9.2f}  Z {z:9.2f} mm   alpha {a:8.3f}  beta "
                       f"{b:8.3f}  gamma {g:8.3f} deg")
    v = r.grasp
    out.append(f"grasp verdict: {v.verdict.upper()}  (3-sigma {v.position_3sigma_mm:.3f} mm / "
               f"{v.angle_3sigma_deg:.3f} deg; tolerance {v.tolerance.position_mm:g} mm / "
               f"{v.tolerance.angle_limit_deg:.3f} deg)")
    if v.reason:
        out.append(f"  reason: {v.reason}")
    if v.hint:
        out.append(f"  hint: {v.hint}")
    return out


@app.command("methods")
def list_methods():
    """List the pose methods this build provides."""
    from ..methods import _ENTRIES, available_methods

    avail = set(available_methods())
    for name, entry in _ENTRIES.items():
        mark = "" if name in avail else "  (not available)"
        typer.echo(f"{name:16s} {entry[3]}{mark}")
    typer.echo("<pnp-method>+lm   any correspondence method refined by Levenberg-Marquardt")


@app.command("demo")
@friendly
def demo(out: str = typer.Option("results/demo", help="Output folder.")):
    """The main job on the bundled default data: render the seeded example image through the
    Table 1 camera, measure it (dm+b), print the pose and write the overlay."""
    from ..pipeline import demo as pipeline_demo

    pipeline_demo(out)
