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


@app.command("handeye")
@friendly
def handeye_cmd(
    images: list[str] = typer.Argument(..., help="Plate images, one per station (files or "
                                       "folders; sorted by name)."),
    robot_poses: str = typer.Option(..., "--robot-poses", help="Flange poses T_base_flange, "
                                    "one per image in the images' order (PROTOCOL pose file "
                                    "or a vendor convention, see docs/robot.md)."),
    out: str = typer.Option(..., "--out", help="Hand-eye file to write (handeye.json)."),
    camera: str = typer.Option(None, help="table1 (default), synthetic, or a camera file."),
    plate_file: str = typer.Option(None, "--plate", help="plate.json (default: the 7x7 "
                                   "30 mm plate)."),
    convention: str = convention_option("the --robot-poses file"),
    length_unit: str = length_unit_option("the --robot-poses file"),
    angle_unit: str = angle_unit_option("the --robot-poses file"),
    repeatability_mm: float = typer.Option(0.03, help="Robot position noise, mm per axis."),
    repeatability_deg: float = typer.Option(0.005, help="Robot rotation noise, deg per axis."),
    refinement: str = typer.Option("marginal", help="marginal (robot errors integrated out) "
                                   "or bundle (robot errors as unknowns; same estimate, "
                                   "slower): both maximum likelihood, docs/robot.md."),
    as_json: bool = typer.Option(False, "--json", help="Print the result as JSON."),
):
    """Eye-in-hand calibration: T_flange_cam and T_base_plate from plate images and flange
    poses (OpenCV starts, joint refinement on the reprojection error); exit 3 if poor."""
    import json

    from ..calibration.handeye import handeye_from_images, save_handeye
    from ..calibration.plate import CirclePlate, load_plate
    from ..robot.poses import read_poses

    cam = camera_from_option(camera)
    plate = load_plate(plate_file) if plate_file else CirclePlate()
    poses = read_poses(robot_poses, convention, length_unit, angle_unit)

    def progress(name, reason):
        if reason:
            log(f"warning: {name} skipped (and its robot pose): {reason}")

    res = handeye_from_images(image_paths(images), poses, cam, plate, progress=progress,
                              repeatability_mm=repeatability_mm,
                              repeatability_deg=repeatability_deg, refinement=refinement)
    save_handeye(res, out)
    if as_json:
        typer.echo(json.dumps(res.to_dict(), indent=1))
    else:
        X = res.T_flange_cam
        a, b, g = X.euler_deg
        typer.echo(f"T_flange_cam: t = {X.t_mm.round(3).tolist()} mm, alpha/beta/gamma = "
                   f"{a:.4f} {b:.4f} {g:.4f} deg (start: {res.start_method})")
        sd = res.handeye.covariance.diagonal() ** 0.5
        typer.echo(f"std: {sd[:3].round(4).tolist()} mm, "
                   f"{(sd[3:] * 57.29577951308232).round(5).tolist()} deg")
        typer.echo(f"{'station':24s} {'used':>4s} {'rms px':>7s} {'plate mm':>9s} "
                   f"{'plate deg':>9s}  distrust")
        for st in res.stations:
            typer.echo(f"{st.name:24s} {'yes' if st.used else 'NO':>4s} {st.rms_px:7.3f} "
                       f"{st.position_mm:9.3f} {st.angle_deg:9.4f}  {st.distrust}")
        typer.echo(res.verdict)
        log(f"wrote {out}")
    if not res.ok:
        fail(f"hand-eye calibration {res.verdict}", code=3)
