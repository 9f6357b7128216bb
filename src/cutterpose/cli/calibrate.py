"""Camera calibration: ``calibrate`` and ``render-plate``."""

from __future__ import annotations

import typer

from .app import (
    angle_unit_option,
    app,
    camera_from_option,
    convention_option,
    friendly,
    image_paths,
    length_unit_option,
    log,
)


def _plate_from_options(plate_file: str | None, grid: str | None, spacing_mm: float | None,
                        diameter_mm: float | None):
    """The plate from ``--plate plate.json`` or from ``--grid RxC --spacing-mm S``."""
    from ..calibration.plate import CirclePlate, load_plate
    from ..errors import InputError

    if plate_file is not None:
        if grid is not None or spacing_mm is not None:
            raise InputError("give either --plate or --grid/--spacing-mm, not both")
        return load_plate(plate_file)
    if grid is None and spacing_mm is None:
        return CirclePlate()
    try:
        rows, cols = (int(v) for v in (grid or "7x7").lower().split("x"))
    except ValueError:
        raise InputError(f"--grid must look like 7x7, got {grid!r}") from None
    s = 30.0 if spacing_mm is None else float(spacing_mm)
    d = 0.5 * s if diameter_mm is None else float(diameter_mm)
    return CirclePlate(rows=rows, cols=cols, spacing_mm=s, diameter_mm=d)


def _target_from_options(target: str | None, plate_file: str | None, grid: str | None,
                         spacing_mm: float | None, diameter_mm: float | None):
    """``--target SPEC`` (any kind) or the project's plate from --plate / --grid."""
    from ..calibration.circle_grids import CaltabTarget
    from ..calibration.targets import target_from_spec
    from ..errors import InputError

    if target is not None:
        if plate_file is not None or grid is not None or spacing_mm is not None or \
                diameter_mm is not None:
            raise InputError("give either --target or --plate/--grid/--spacing-mm/"
                             "--diameter-mm, not both")
        return target_from_spec(target)
    return CaltabTarget(_plate_from_options(plate_file, grid, spacing_mm, diameter_mm))


TARGET_HELP = ("Calibration target: caltab:7x7:30 (default), circles:COLSxROWS:SPACING_MM, "
               "acircles:COLSxROWS:SPACING_MM (each with :light, :origin-dot), "
               "chessboard:COLSxROWS:SQUARE_MM, charuco:COLSxROWS:SQUARE_MM:MARKER_MM:DICT, or a "
               "target file (.yaml/.json, HALCON .descr/.cpd); see "
               "docs/calibration_targets.md.")
_TARGET, _MODEL, _OUTPUT, _CELL = "Target", "Camera model", "Output", "Robot cell"


def _auto_distance(cam, target) -> tuple[float, float]:
    """Distances at which the target spans 45-85 % of the image width."""
    x0, x1, y0, y1 = target.bounds_mm
    extent = max(x1 - x0, y1 - y0)
    w = cam.image_size_px[0]
    return (cam.focal_px * extent / (0.85 * w), cam.focal_px * extent / (0.45 * w))


@app.command("render-plate")
@friendly
def render_plate_cmd(
    out: str = typer.Option(..., "--out", help="Output folder (images, target file, "
                            "truth.json)."),
    count: int = typer.Option(15, min=1, help="Number of plate images."),
    camera: str = typer.Option(None, help="table1 (default), synthetic, or a camera file."),
    seed: int = typer.Option(0, help="Seed of the poses and the sensor noise."),
    preset: str = typer.Option("easy", help="Sensor/blur preset of the holder renderer "
                               "(easy, dim, blurred, ...)."),
    target: str = typer.Option(None, "--target", rich_help_panel=_TARGET,
        help=TARGET_HELP + " Default: the plate of "
                               "--grid/--spacing-mm/--diameter-mm."),
    grid: str = typer.Option(None, rich_help_panel=_TARGET,
        help="Circle grid of the project's plate, rows x cols "
                             "(default 7x7)."),
    spacing_mm: float = typer.Option(None, rich_help_panel=_TARGET,
        help="Circle spacing in mm (default 30)."),
    diameter_mm: float = typer.Option(None, rich_help_panel=_TARGET,
        help="Circle diameter in mm (default 15)."),
    distance_mm: str = typer.Option(None, help="Range of plate distances in mm, MIN,MAX "
                                    "(default 400,700 for the project's plate; for other "
                                    "targets where it spans 45-85 % of the image width)."),
    robot_cell: bool = typer.Option(False, "--robot-cell", rich_help_panel=_CELL,
        help="Hand-eye mode: a simulated "
                                    "robot cell (random camera mount, fixed plate) moves the "
                                    "camera through COUNT stations; writes robot_poses.csv "
                                    "(reported flange poses) and cell_truth.json."),
    repeatability_mm: float = typer.Option(0.03, rich_help_panel=_CELL,
        help="--robot-cell: robot position noise, "
                                           "mm per axis (1 sigma)."),
    repeatability_deg: float = typer.Option(0.005, rich_help_panel=_CELL,
        help="--robot-cell: robot rotation noise, "
                                            "deg per axis (1 sigma)."),
    plate_poses: str = typer.Option(None, "--plate-poses", help="Render one image per pose "
                                    "of this pose file (T_cam_plate, any convention of "
                                    "`cutterpose.robot.poses`) instead of drawing poses."),
    convention: str = convention_option("a --plate-poses file"),
    length_unit: str = length_unit_option("a --plate-poses file"),
    angle_unit: str = angle_unit_option("a --plate-poses file"),
):
    """Render images of a calibration target (the project's circle plate by default) through
    the camera and the holder renderer's sensor model, at poses that cover the field, at given
    poses (--plate-poses), or from the stations of a simulated robot cell (--robot-cell)."""
    import json
    from pathlib import Path

    import cv2
    import numpy as np

    from ..calibration.circle_grids import CaltabTarget
    from ..calibration.plate import render_plate, sample_plate_poses, save_plate
    from ..calibration.targets import save_target
    from ..errors import InputError
    from ..render.analytic import preset as get_preset

    tgt = _target_from_options(target, None, grid, spacing_mm,
                               15.0 if target is None and diameter_mm is None else diameter_mm)
    # the project's plate renders as before (its own poses and plate.json)
    plate = tgt.plate if isinstance(tgt, CaltabTarget) else tgt
    settings = get_preset(preset)
    cam = camera_from_option(camera)
    if distance_mm is None:
        dist = (400.0, 700.0) if isinstance(tgt, CaltabTarget) else _auto_distance(cam, tgt)
    else:
        try:
            dist = tuple(float(v) for v in distance_mm.split(","))
            assert len(dist) == 2 and 0 < dist[0] <= dist[1]
        except (ValueError, AssertionError):
            raise InputError(f"--distance-mm must be MIN,MAX in mm, got {distance_mm!r}") \
                from None
    folder = Path(out)
    folder.mkdir(parents=True, exist_ok=True)
    if robot_cell:
        from ..robot.cell import RobotCell

        if plate_poses:
            raise InputError("give either --robot-cell or --plate-poses, not both")
        if not isinstance(tgt, CaltabTarget):
            raise InputError("--robot-cell renders the project's plate only (not --target)")
        cell = RobotCell.random(cam, seed, repeatability_mm=repeatability_mm,
                                repeatability_deg=repeatability_deg)
        cell.plate = plate
        cell.write_handeye_set(folder, count, seed, settings,
                               progress=lambda k, n: log(f"station {k}/{n}"))
        typer.echo(f"wrote {count} plate images, robot_poses.csv, plate.json, camera.json and "
                   f"cell_truth.json to {folder}")
        return
    if plate_poses:
        from ..robot.poses import read_poses

        poses = read_poses(plate_poses, convention, length_unit, angle_unit, "cam", "plate")
        count = len(poses)
    else:
        poses = sample_plate_poses(cam, count, plate, distance_mm=dist, seed=seed)
    rng = np.random.default_rng(seed)
    images = []
    for k, pose in enumerate(poses):
        name = f"plate_{k:04d}.png"
        cv2.imwrite(str(folder / name), render_plate(cam, pose, plate, settings=settings,
                                                     rng=rng))
        centres = cam.project(pose.apply(tgt.points_target_mm))
        images.append({"file": name, "R_cam_plate": pose.R.tolist(),
                       "t_cam_plate_mm": pose.t_mm.tolist(), "centers_px": centres.tolist()})
        log(f"{name}: target at {np.linalg.norm(pose.t_mm):.0f} mm")
    if isinstance(tgt, CaltabTarget):
        save_plate(plate, folder / "plate.json")
        written = "plate.json"
    else:
        save_target(tgt, folder / "target.yaml")
        written = "target.yaml"
    truth = {"camera": cam.to_dict(), "plate": tgt.to_dict(), "target": tgt.spec(),
             "preset": settings.name, "images": images}
    (folder / "truth.json").write_text(json.dumps(truth, indent=1) + "\n")
    typer.echo(f"wrote {count} images of {tgt.describe()}, {written} and truth.json to {folder}")


@app.command("calibrate")
@friendly
def calibrate_cmd(
    images: list[str] = typer.Argument(..., help="Target images (files or folders)."),
    out: str = typer.Option(..., "--out", help="Camera file to write (.json, .yml, .dat, "
                            ".ros.yaml)."),
    target: str = typer.Option(None, "--target", rich_help_panel=_TARGET,
        help=TARGET_HELP),
    plate_file: str = typer.Option(None, "--plate", rich_help_panel=_TARGET,
        help="plate.json (from render-plate)."),
    grid: str = typer.Option(None, rich_help_panel=_TARGET,
        help="The project's plate: rows x cols, e.g. 7x7 (without "
                             "--plate)."),
    spacing_mm: float = typer.Option(None, rich_help_panel=_TARGET,
        help="The project's plate: circle spacing in mm."),
    diameter_mm: float = typer.Option(None, rich_help_panel=_TARGET,
        help="The project's plate: circle diameter in mm "
                                      "(default: spacing/2)."),
    model: str = typer.Option("division", rich_help_panel=_MODEL,
        help="division (HALCON area_scan_division), "
                              "polynomial (HALCON area_scan_polynomial) or opencv "
                              "(cv2.calibrateCamera, see --coefficients)."),
    coefficients: str = typer.Option(None, rich_help_panel=_MODEL,
        help="--model opencv: the distortion coefficients "
                                     "to estimate, e.g. k1,k2,p1,p2,k3 (default), k1,k2, "
                                     "rational, none."),
    pixel_height_um: float = typer.Option(3.45, rich_help_panel=_MODEL,
        help="Fixed pixel height Sy of the HALCON "
                                          "models, from the sensor's datasheet."),
    bias_rounds: int = typer.Option(2, min=0, rich_help_panel=_MODEL,
        help="Rounds of the ellipse-centre bias "
                                    "correction of circle targets (0: plain ellipse centres)."),
    report: str = typer.Option(None, rich_help_panel=_OUTPUT,
        help="Report JSON (default: <out stem>.report.json)."),
    overlays: str = typer.Option(None, rich_help_panel=_OUTPUT,
        help="Folder for an overlay per used image (points, "
                                 "their order, residuals; default: <out stem>.overlays)."),
    coverage: str = typer.Option(None, rich_help_panel=_OUTPUT,
        help="Coverage and residual map, PNG (default: "
                                 "<out stem>.coverage.png)."),
    pictures: bool = typer.Option(True, "--pictures/--no-pictures", rich_help_panel=_OUTPUT,
        help="Write the overlays "
                                  "and the coverage map."),
    json_out: bool = typer.Option(False, "--json", rich_help_panel=_OUTPUT,
        help="Print the report as JSON."),
):
    """Calibrate a camera from images of a calibration target: every image used or skipped
    with its reason, per-image RMS, flagged images, the parameters' standard deviations."""
    import json
    from pathlib import Path

    from ..calibration.calib_report import write_calibration_pictures
    from ..calibration.target_calibration import calibrate_target_images
    from ..geometry.camera_files import convert_camera, detect_format, write_camera

    tgt = _target_from_options(target, plate_file, grid, spacing_mm, diameter_mm)
    paths = image_paths(images)
    fmt = detect_format(out, for_writing=True)

    def progress(name, reason):
        if reason:
            log(f"warning: {name} skipped: {reason}")

    res = calibrate_target_images(paths, tgt, model=model, coefficients=coefficients,
                                  pixel_height_m=pixel_height_um * 1e-6,
                                  bias_rounds=bias_rounds, progress=progress)
    conv = convert_camera(res.camera, fmt, pixel_height_um * 1e-6)
    write_camera(conv.camera, out, fmt)
    rep = res.to_dict()
    rep["written"] = {"file": str(out), "format": fmt, "exact": conv.exact,
                      "max_conversion_error_px": conv.max_error_px}
    stem = Path(out).with_name(Path(out).stem)
    if pictures:
        rep["pictures"] = write_calibration_pictures(
            res, paths, tgt, overlays or f"{stem}.overlays", coverage or f"{stem}.coverage.png")
    rep_path = Path(report) if report else Path(f"{stem}.report.json")
    rep_path.write_text(json.dumps(rep, indent=1, default=_json_default) + "\n")
    if json_out:
        typer.echo(json.dumps(rep, indent=1, default=_json_default))
        return
    _print_result(res, conv, fmt)
    typer.echo(f"wrote {out} and {rep_path}" + (f"; overlays in {rep['pictures']['overlays'][0]}"
                                                 f"..., coverage map "
                                                 f"{rep['pictures']['coverage']}"
                                                 if pictures and rep["pictures"]["overlays"]
                                                 else ""))


def _json_default(v):
    import numpy as np

    return v.tolist() if isinstance(v, np.ndarray) else float(v)


def _print_result(res, conv, fmt) -> None:
    cam = res.camera.to_dict()
    typer.echo(f"target: {res.target}; model: {res.camera.model}; {len(res.used)} images used, "
               f"{len(res.skipped)} skipped")
    for k, v in cam.items():
        if k not in ("name", "model"):
            typer.echo(f"  {k}: {v}")
    typer.echo("standard deviations:")
    for k, v in res.std.items():
        typer.echo(f"  {k}: {v:.4g}")
    typer.echo(f"RMS reprojection error: {res.rms_px:.4f} px")
    for v, e in zip(res.views or [], res.per_image_rms_px):
        amb = v["rotation_ambiguity_deg"]
        flag = res.flagged.get(v["name"])
        typer.echo(f"  {v['name']}: {e:.4f} px, {len(v['ids'])} points"
                   + (f" (order known up to {amb} deg)" if amb else "")
                   + (f"  FLAGGED: {flag}" if flag else ""))
    for n, why in res.skipped.items():
        typer.echo(f"  {n}: skipped ({why})")
    for w in res.warnings:
        typer.echo(f"warning: {w}")
    if not conv.exact:
        typer.echo(f"note: {fmt} cannot hold the {res.camera.model} model; wrote the nearest "
                   f"{conv.camera.model} camera (worst pixel error {conv.max_error_px:.4f} px)")
