"""Hand-eye calibration: ``handeye``."""

from __future__ import annotations

import typer

from .app import (
    angle_unit_option,
    app,
    camera_from_option,
    convention_option,
    fail,
    friendly,
    image_paths,
    length_unit_option,
    log,
)


def _target(spec: str | None, plate_file: str | None):
    """The target: ``--target SPEC`` (docs/calibration targets), ``--plate plate.json`` or the
    default 7x7 plate."""
    from ..calibration.plate import CirclePlate, load_plate
    from ..errors import InputError

    if spec and plate_file:
        raise InputError("give either --target or --plate, not both")
    if spec:
        from ..calibration.targets import target_from_spec

        return target_from_spec(spec)
    return load_plate(plate_file) if plate_file else CirclePlate()


def _print_result(res, out: str) -> None:
    X = res.T_flange_cam
    a, b, g = X.euler_deg
    typer.echo(f"T_flange_cam: t = {X.t_mm.round(3).tolist()} mm, alpha/beta/gamma = "
               f"{a:.4f} {b:.4f} {g:.4f} deg (start: {res.start_method})")
    sd = res.handeye.covariance.diagonal() ** 0.5
    typer.echo(f"std: {sd[:3].round(4).tolist()} mm, "
               f"{(sd[3:] * 57.29577951308232).round(5).tolist()} deg")
    typer.echo(f"{'station':24s} {'used':>4s} {'rms px':>7s} {'plate mm':>9s} "
               f"{'plate deg':>9s} {'motion deg':>10s}  distrust")
    for st in res.stations:
        typer.echo(f"{st.name:24s} {'yes' if st.used else 'NO':>4s} {st.rms_px:7.3f} "
                   f"{st.position_mm:9.3f} {st.angle_deg:9.4f} {st.motion_deg:10.3f}  "
                   f"{st.distrust}")
    if res.plate_spread:
        typer.echo(f"target in the base frame: {res.plate_spread['verdict']}")
    for n in res.notes:
        typer.echo(f"note: {n}")
    typer.echo(res.verdict)
    log(f"wrote {out}")


@app.command("handeye")
@friendly
def handeye_cmd(
    images: list[str] = typer.Argument(..., help="Target images, one per station (files or "
                                       "folders; sorted by name)."),
    poses: str = typer.Option(..., "--poses", "--robot-poses", help="Flange poses "
                              "T_base_flange: a pose file or a folder of them (one station per "
                              "file, paired with the images by the number in their names); "
                              "docs/robot.md."),
    pose_format: str = typer.Option("auto", "--pose-format", help="auto (from the suffix and "
                                    "content), csv, json, ros-yaml, visp-yaml or yaskawa (a "
                                    ".JBI job file, or X,Y,Z,Rx,Ry,Rz rows)."),
    out: str = typer.Option(..., "--out", help="Hand-eye file to write (handeye.json)."),
    target: str = typer.Option(None, "--target", help="The calibration target, e.g. "
                               "circles:10x10:25.4:origin-dot, chessboard:9x6:25 "
                               "(docs/calibration.md); default the 7x7 plate."),
    camera: str = typer.Option(None, help="table1 (default), synthetic, or a camera file."),
    plate_file: str = typer.Option(None, "--plate", help="plate.json (the 7x7 plate with "
                                   "other dimensions)."),
    convention: str = convention_option("the pose file"),
    length_unit: str = length_unit_option("the pose file"),
    angle_unit: str = angle_unit_option("the pose file"),
    repeatability_mm: float = typer.Option(0.03, help="The robot's pose error, mm per axis "
                                           "(1 sigma): its repeatability, or its accuracy "
                                           "when that limits the poses."),
    repeatability_deg: float = typer.Option(0.005, help="The robot's pose error, deg per "
                                            "axis (1 sigma)."),
    refinement: str = typer.Option("marginal", help="marginal (robot errors integrated out) "
                                   "or bundle (robot errors as unknowns; same estimate, "
                                   "slower): both maximum likelihood, docs/robot.md."),
    report: str = typer.Option(None, "--report", help="Also write a Markdown report (per-"
                               "station residuals, flagged stations, the OpenCV methods)."),
    as_json: bool = typer.Option(False, "--json", help="Print the result as JSON."),
):
    """Eye-in-hand calibration: T_flange_cam and T_base_plate from target images and flange
    poses (OpenCV starts, joint refinement on the reprojection error, per-station residuals,
    outlier stations flagged); exit 3 if poor."""
    import json
    from pathlib import Path

    from ..calibration.handeye import handeye_from_images, save_handeye
    from ..calibration.handeye_report import report_markdown
    from ..robot.pose_files import check_flange_units, pair_with_images, read_pose_set

    cam = camera_from_option(camera)
    tgt = _target(target, plate_file)
    pose_set = read_pose_set(poses, pose_format, convention, length_unit, angle_unit)
    check_flange_units(pose_set.poses, poses)
    paths = image_paths(images)
    order = pair_with_images([p.name for p in paths], pose_set.names)
    flange = [pose_set.poses[j] for j in order]

    def progress(name, reason):
        if reason:
            log(f"warning: {name} skipped (and its robot pose): {reason}")

    res = handeye_from_images(paths, flange, cam, tgt, progress=progress,
                              repeatability_mm=repeatability_mm,
                              repeatability_deg=repeatability_deg, refinement=refinement)
    save_handeye(res, out)
    if report:
        Path(report).write_text(report_markdown(res))
    if as_json:
        typer.echo(json.dumps(res.to_dict(), indent=1))
    else:
        _print_result(res, out)
    if not res.ok:
        fail(f"hand-eye calibration {res.verdict}", code=3)
