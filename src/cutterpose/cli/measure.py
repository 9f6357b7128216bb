"""Measuring: ``measure`` (one image), ``methods`` (the registry), ``demo``."""

from __future__ import annotations

import typer

from .app import (
    CAMERA,
    IMAGE,
    OUTPUT,
    ROBOT,
    VERDICT,
    app,
    budget_deg_option,
    budget_mm_option,
    budget_tolerance,
    camera_from_option,
    edge_break_option,
    edge_look_option,
    fail,
    friendly,
    load_edge_look,
    log,
    old_name_option,
    pixel_format_option,
    renamed,
)


@app.command("measure")
@friendly
def measure_cmd(
    image: str = typer.Argument(..., metavar="IMAGE", show_default=False,
                                help="Image file, or a raw frame (--raw)."),
    raw: str = typer.Option(None, "--raw", metavar="WxH", rich_help_panel=IMAGE,
                            help="IMAGE is a raw frame of W x H pixels."),
    pixel_format: str = pixel_format_option(IMAGE),
    camera: str = typer.Option(None, metavar="FILE", rich_help_panel=CAMERA,
                               help="Camera file, or table1 (default), synthetic."),
    holder: str = typer.Option(None, metavar="FILE", rich_help_panel=CAMERA,
                               help="Holder file (default: the bundled holder)."),
    distance_mm: float = typer.Option(None, "--distance-mm", metavar="MM",
                                      rich_help_panel=CAMERA,
                                      help="Station: camera to holder (default 600)."),
    method: str = typer.Option("dm+b", metavar="NAME", rich_help_panel=VERDICT,
                               show_default=False,
                               help="Pose method (default dm+b; see `methods`)."),
    edge_look: str = edge_look_option(VERDICT),
    edge_break_mm: float = edge_break_option(VERDICT),
    budget_tol_mm: float = budget_mm_option(VERDICT),
    budget_tol_deg: float = budget_deg_option(VERDICT),
    handeye: str = typer.Option(None, "--handeye", metavar="FILE", rich_help_panel=ROBOT,
                                help="Hand-eye file: answer in the robot's base frame too, "
                                "with the grasp verdict (exit 4: retake)."),
    flange_pose: str = typer.Option(None, "--flange-pose", metavar="POSE",
                                    rich_help_panel=ROBOT,
                                    help="T_base_flange at the picture: a pose file or "
                                    "x,y,z,qx,qy,qz,qw (mm)."),
    position_tol_mm: float = typer.Option(None, "--grasp-tol-mm", metavar="MM",
                                          rich_help_panel=ROBOT,
                                          help="Grasp: 3-sigma position tolerance (default 1)."),
    angle_tol_deg: float = typer.Option(None, "--grasp-tol-deg", metavar="DEG",
                                        rich_help_panel=ROBOT,
                                        help="Grasp: 3-sigma angle tolerance (default "
                                        "0.265)."),
    as_json: bool = typer.Option(False, "--json", rich_help_panel=OUTPUT,
                                 help="One JSON object on stdout."),
    overlay: str = typer.Option(None, "--overlay", metavar="PNG", rich_help_panel=OUTPUT,
                                help="Write a picture of the measurement."),
    # rarely used: hidden from the help, listed in its last line
    chain: str = typer.Option("field", hidden=True, help="Image chain: field (gradient outline, "
                              "robust lines; default) or paper (section 2.1: threshold 70, "
                              "contour)."),
    edge_shape: str = typer.Option("unknown", hidden=True, help="The pocket edge's break as "
                                   "the holder's drawing gives it: round, chamfer, or unknown "
                                   "(default: dm+b tells them apart; dm+r's verdict then carries "
                                   "the chamfer's depth the contour cannot see)."),
    corners: bool = typer.Option(False, "--corners", hidden=True, help="Detect the corners "
                                 "even when the method does not need them (dm+b starts from the "
                                 "pocket outline: without this its JSON has no corners_px)."),
    convention: str = typer.Option(None, hidden=True, help="Pose convention of a --flange-pose "
                                   "file that does not state it (docs/robot.md)."),
    length_unit: str = typer.Option(None, hidden=True, help="mm or m, for a --flange-pose "
                                    "file that does not state it."),
    angle_unit: str = typer.Option(None, hidden=True, help="deg or rad, for a --flange-pose "
                                   "file that does not state it."),
    robot_accuracy_mm: float = typer.Option(0.05, hidden=True, help="Robot position error, mm "
                                            "per axis (1 sigma)."),
    robot_accuracy_deg: float = typer.Option(0.01, hidden=True, help="Robot angle error, deg "
                                             "per axis (1 sigma)."),
    # former names, kept working
    old_budget_tol_mm: float = old_name_option("--budget-tol-mm"),
    old_budget_tol_deg: float = old_name_option("--budget-tol-deg"),
    old_position_tol_mm: float = old_name_option("--position-tol-mm"),
    old_angle_tol_deg: float = old_name_option("--angle-tol-deg"),
):
    """Measure one image: the verdict (ACCEPTED / REFUSED: why), then the pose.

    More: --chain --edge-shape --corners --convention --length-unit --angle-unit
    --robot-accuracy-mm --robot-accuracy-deg (docs/robot.md).
    """
    import json as _json
    import time

    from ..errors import InputError
    from ..frames import load_frame, parse_raw_size
    from ..robot import GraspTolerance, RobotAccuracy, load_flange_pose
    from ..station import build_station

    if (handeye is None) != (flange_pose is None):
        raise InputError("the base frame needs both --handeye and --flange-pose")
    if chain not in ("field", "paper"):
        fail(f"--chain must be 'field' or 'paper', got {chain!r}")
    station = build_station(
        camera_from_option(camera), holder, method, chain=chain, distance_mm=distance_mm,
        edge_shape=edge_shape, edge_break_mm=edge_break_mm,
        tolerance=budget_tolerance(budget_tol_mm, budget_tol_deg, old_budget_tol_mm,
                                   old_budget_tol_deg),
        edge_look=load_edge_look(edge_look), handeye=handeye,
        robot_accuracy=RobotAccuracy(robot_accuracy_mm, robot_accuracy_deg),
        grasp_tolerance=GraspTolerance(
            renamed(position_tol_mm, old_position_tol_mm, "--grasp-tol-mm",
                    "--position-tol-mm") or 1.0,
            angle_deg=renamed(angle_tol_deg, old_angle_tol_deg, "--grasp-tol-deg",
                              "--angle-tol-deg")))
    flange = (load_flange_pose(flange_pose, convention, length_unit, angle_unit)
              if flange_pose is not None else None)
    t0 = time.perf_counter()
    img = load_frame(image, station.camera, parse_raw_size(raw) if raw else None, pixel_format)
    load_ms = (time.perf_counter() - t0) * 1e3
    m = station.measure(img, T_base_flange=flange, corners=True if corners else None)
    m.timings_ms = {"load": load_ms} | m.timings_ms
    if overlay:
        from ..overlay import write_overlay

        write_overlay(img, m, station.camera, station.holder, overlay)
        log(f"wrote {overlay}")
    if as_json:
        typer.echo(_json.dumps(m.to_dict()))
    else:
        typer.echo("\n".join(_plain_lines(m)))
    if not m.ok:
        fail(f"pose refused: {m.quality.reason}", code=3)
    if m.robot is not None and not m.robot.grasp.ok:
        fail(f"retake: {m.robot.grasp.reason} -- {m.robot.grasp.hint}", code=4)


def _plain_lines(m) -> list[str]:
    """The plain answer: the verdict on the first line (``ACCEPTED`` or ``REFUSED: reason``),
    then the pose only when it was accepted; a refused pose is no measurement, so it is not
    printed as one (``--json`` keeps it, marked ``"ok": false``)."""
    timing = "time: " + ", ".join(f"{k} {v:.0f} ms" for k, v in m.timings_ms.items())
    if not m.ok:
        return [f"REFUSED: {m.quality.reason}",
                "no pose given (--json shows the refused estimate, marked ok: false)", timing]
    robot = _robot_lines(m.robot) if m.robot is not None else []
    if m.robot is not None and not m.robot.grasp.ok:
        g = m.robot.grasp
        return [f"REFUSED: retake: {g.reason}", *robot, timing]
    return ["ACCEPTED", *m.pose_lines(), timing, *robot]


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
    from ..methods import describe_methods

    for name, description in describe_methods().items():
        typer.echo(f"{name:16s} {description}")
    typer.echo("<pnp-method>+lm   any correspondence method refined by Levenberg-Marquardt")


@app.command("demo")
@friendly
def demo(out: str = typer.Option("results/demo", help="Output folder.")):
    """The main job on the bundled default data: render the seeded example image through the
    Table 1 camera, measure it (dm+b), print the pose and write the overlay."""
    from ..pipeline import demo as pipeline_demo

    pipeline_demo(out)
