"""The ``cutterpose`` command line.

Results go to stdout (tables, or one JSON object with ``--json``); logs and progress bars go to
stderr. Every expected failure exits non-zero with a one-line message, never a traceback.
"""

from __future__ import annotations

import sys
from functools import wraps

import typer

from .errors import CutterposeError

app = typer.Typer(add_completion=False, no_args_is_help=True,
                  help="Pose of a disc cutter holder from one camera image.")
experiment_app = typer.Typer(no_args_is_help=True, help="Run the paper's experiments.")
camera_app = typer.Typer(no_args_is_help=True, help="Camera files: convert between formats.")
app.add_typer(experiment_app, name="experiment")
app.add_typer(camera_app, name="camera")


def fail(message: str, code: int = 2) -> None:
    typer.echo(f"error: {message}", err=True)
    raise typer.Exit(code)


def friendly(fn):
    """Turn expected errors into a message on stderr and a non-zero exit code."""

    @wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except CutterposeError as e:
            fail(str(e))
        except (FileNotFoundError, IsADirectoryError, PermissionError) as e:
            fail(str(e))

    return wrapper


def log(message: str) -> None:
    typer.echo(message, err=True)


# ---- section: experiment synthetic (issue 2) ---------------------------------------------
@experiment_app.command("synthetic")
@friendly
def experiment_synthetic(
    methods: str = typer.Option("opencv-ippe-lm,opencv-sqpnp", help="Comma-separated method "
                                "names (see `cutterpose methods`)."),
    trials: int = typer.Option(1000, min=1, help="Trials per noise level."),
    sigmas: str = typer.Option("0:5:0.5", help="Noise levels in px: start:stop:step or a,b,c."),
    out: str = typer.Option("results/synthetic", help="Output folder."),
    trials_file: str = typer.Option(None, "--trials-file", help="Run a PROTOCOL trial file "
                                    "(.npz) instead of drawing trials."),
    workers: int = typer.Option(1, min=1, help="Worker processes (results are identical)."),
    seed: int = typer.Option(0, help="Base seed of the trial generator."),
    progress: bool = typer.Option(True, help="Show a progress bar on stderr."),
):
    """The paper's synthetic noise sweep (Fig. 5): writes trials.csv, summary.md, fig5.png."""
    from .experiments.synthetic import parse_sigmas, run_synthetic
    from .methods import parse_methods

    meths = parse_methods(methods)
    res = run_synthetic(meths, parse_sigmas(sigmas), trials, out, seed=seed, workers=workers,
                        trials_file=trials_file, show_progress=progress)
    typer.echo((res.out_dir / "summary.md").read_text())
    log(f"wrote {res.out_dir}/trials.csv, summary.md, summary.json, fig5.png")


@app.command("methods")
def list_methods():
    """List the pose methods this build provides."""
    from .methods import _ENTRIES, available_methods

    avail = set(available_methods())
    for name, entry in _ENTRIES.items():
        mark = "" if name in avail else "  (not available)"
        typer.echo(f"{name:16s} {entry[3]}{mark}")
    typer.echo("<pnp-method>+lm   any correspondence method refined by Levenberg-Marquardt")


# ---- section: demo ------------------------------------------------------------------------
@app.command("demo")
@friendly
def demo(out: str = typer.Option("results/demo", help="Output folder.")):
    """The main job on the bundled default data: render the seeded example image through the
    Table 1 camera, measure it with dm+, print the pose and write the overlay."""
    from .pipeline import demo as pipeline_demo

    pipeline_demo(out)


# ---- section: measure, render, render-set, experiment images (issue 5) --------------------
def _render_camera(spec: str | None):
    """``table1`` / ``synthetic`` (bundled cameras) or a camera file; default Table 1."""
    from .geometry.camera import default_camera
    from .geometry.camera_files import load_camera

    if spec is None or spec in ("table1", "synthetic"):
        return default_camera(spec or "table1")
    return load_camera(spec)


@app.command("render")
@friendly
def render_cmd(
    out: str = typer.Option(..., "--out", help="Output image (.png)."),
    pose: str = typer.Option("0,0,0,0,0,600", help="alpha,beta,gamma [deg],X,Y,Z [mm] of the "
                             "holder in the camera frame."),
    preset: str = typer.Option("easy", help="easy, dim, worn, occluded, blurred or hard."),
    seed: int = typer.Option(0, help="Seed of textures, occluders and noise."),
    camera: str = typer.Option(None, help="table1 (default), synthetic, or a camera file."),
    holder: str = typer.Option(None, help="Holder JSON file (default: the bundled holder)."),
    pocket_depth: float = typer.Option(None, help="Pocket depth in mm (preset: 80)."),
    truth: bool = typer.Option(True, help="Also write <stem>.truth.json beside the image."),
):
    """Render one realistic image of the holder at a pose."""
    from .errors import InputError
    from .geometry.holder import load_holder
    from .geometry.pose import Pose
    from .render.analytic import preset as get_preset
    from .render.analytic import render_holder, save_rendered

    try:
        dof = [float(x) for x in pose.split(",")]
    except ValueError:
        dof = []
    if len(dof) != 6:
        raise InputError(f"--pose needs six comma-separated numbers alpha,beta,gamma,X,Y,Z; "
                         f"got {pose!r}")
    cam = _render_camera(camera)
    settings = get_preset(preset)
    if pocket_depth is not None:
        settings = settings.with_(pocket_depth_mm=pocket_depth)
    r = render_holder(Pose.from_euler(*dof), cam, load_holder(holder) if holder else None,
                      settings, seed=seed)
    path = save_rendered(r, out, cam, truth=truth)
    typer.echo(f"wrote {path}" + (f" and {path.with_suffix('.truth.json')}" if truth else ""))


@app.command("render-set")
@friendly
def render_set_cmd(
    out: str = typer.Option(..., "--out", help="Output folder (images and truth.json)."),
    count: int = typer.Option(100, min=1, help="Number of images."),
    seed: int = typer.Option(0, help="Seed of the poses, difficulties and images."),
    camera: str = typer.Option(None, help="table1 (default), synthetic, or a camera file."),
    preset: str = typer.Option(None, help="Use this preset for every image (default: a mix "
                               "of easy, dim, worn, occluded, blurred, hard)."),
    workers: int = typer.Option(1, min=1, help="Worker processes (the set does not change)."),
):
    """Render an image set with its truth.json (PROTOCOL.md, exchange formats)."""
    from rich.progress import Progress

    from .render.analytic import DEFAULT_MIX, render_set
    from .render.analytic import preset as get_preset

    mix = DEFAULT_MIX
    if preset is not None:
        get_preset(preset)
        mix = ((preset, 1.0),)
    cam = _render_camera(camera)
    with Progress(transient=True, console=None) as bar:
        task = bar.add_task("rendering", total=count)
        path = render_set(count, seed, out, cam, mix=mix, workers=workers,
                          progress=lambda done, n: bar.update(task, completed=done))
    typer.echo(f"wrote {count} images and {path}")


@app.command("measure")
@friendly
def measure_cmd(
    image: str = typer.Argument(..., help="Image of the holder (PNG, JPEG, TIFF...)."),
    camera: str = typer.Option(None, help="table1 (default), synthetic, or a camera file."),
    holder: str = typer.Option(None, help="Holder JSON file (default: the bundled holder)."),
    method: str = typer.Option("dm+", help="Pose method (cutterpose.methods)."),
    overlay: str = typer.Option(None, "--overlay", help="Write an overlay PNG here."),
    as_json: bool = typer.Option(False, "--json", help="One JSON object on stdout."),
):
    """Measure the holder's pose in one image (exit 3 when the pose is refused)."""
    import json as _json

    from .geometry.holder import load_holder
    from .image import load_image
    from .pipeline import measure

    cam = _render_camera(camera)
    hol = load_holder(holder) if holder else None
    img = load_image(image)
    m = measure(img, cam, hol, method)
    if overlay:
        from .geometry.holder import default_holder
        from .overlay import write_overlay

        write_overlay(img, m, cam, hol or default_holder(), overlay)
        log(f"wrote {overlay}")
    if as_json:
        typer.echo(_json.dumps(m.to_dict()))
    elif m.pose is not None:
        typer.echo("\n".join(m.pose_lines()))
        typer.echo("time: " + ", ".join(f"{k} {v:.0f} ms" for k, v in m.timings_ms.items()))
    if not m.ok:
        fail(f"pose refused: {m.quality.reason}", code=3)


@experiment_app.command("images")
@friendly
def experiment_images_cmd(
    folder: str = typer.Argument(..., help="Image set: a folder with truth.json."),
    methods: str = typer.Option("dm,dm+,dlt,epnp,rpnp,aspnp,opnp",
                                help="Comma-separated methods."),
    out: str = typer.Option("results/images", help="Output folder."),
    workers: int = typer.Option(1, min=1, help="Worker processes."),
    limit: int = typer.Option(None, help="Only the first N images."),
    no_refine: bool = typer.Option(False, "--no-refine",
                                   help="The paper's lines only (no gradient refinement)."),
):
    """Table 2 figures of every method on an image set (trials.csv, summary.md)."""
    from rich.progress import Progress

    from .experiments.images import run_images
    from .image import FeatureParams
    from .methods import parse_methods

    names = [m.name for m in parse_methods(methods)]
    with Progress(transient=True) as bar:
        task = bar.add_task("images", total=None)
        run_images(folder, names, out, workers=workers, limit=limit,
                   params=FeatureParams(refine=not no_refine),
                   progress=lambda done, n: bar.update(task, completed=done, total=n))
    typer.echo(f"wrote {out}/trials.csv, summary.md, corners.csv, failures.csv")
    typer.echo((__import__("pathlib").Path(out) / "summary.md").read_text())



# ---- section: calibrate, render-plate, camera convert (issue 6) ---------------------------
def _plate_from_options(plate_file: str | None, grid: str | None, spacing_mm: float | None,
                        diameter_mm: float | None):
    """The plate from ``--plate plate.json`` or from ``--grid RxC --spacing-mm S``."""
    from .calibration.plate import CirclePlate, load_plate
    from .errors import InputError

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


@app.command("render-plate")
@friendly
def render_plate_cmd(
    out: str = typer.Option(..., "--out", help="Output folder (images, plate.json, truth.json)."),
    count: int = typer.Option(15, min=1, help="Number of plate images."),
    camera: str = typer.Option(None, help="table1 (default), synthetic, or a camera file."),
    seed: int = typer.Option(0, help="Seed of the poses and the sensor noise."),
    preset: str = typer.Option("easy", help="Sensor/blur preset of the holder renderer "
                               "(easy, dim, blurred, ...)."),
    grid: str = typer.Option("7x7", help="Circle grid, rows x cols."),
    spacing_mm: float = typer.Option(30.0, help="Circle spacing in mm."),
    diameter_mm: float = typer.Option(15.0, help="Circle diameter in mm."),
    distance_mm: str = typer.Option("400,700", help="Range of plate distances in mm."),
):
    """Render images of the circle calibration plate at poses that cover the field."""
    import json
    from pathlib import Path

    import cv2
    import numpy as np

    from .calibration.plate import render_plate, sample_plate_poses, save_plate
    from .errors import InputError
    from .render.analytic import preset as get_preset

    plate = _plate_from_options(None, grid, spacing_mm, diameter_mm)
    settings = get_preset(preset)
    try:
        dist = tuple(float(v) for v in distance_mm.split(","))
        assert len(dist) == 2 and 0 < dist[0] <= dist[1]
    except (ValueError, AssertionError):
        raise InputError(f"--distance-mm must be MIN,MAX in mm, got {distance_mm!r}") from None
    cam = _render_camera(camera)
    folder = Path(out)
    folder.mkdir(parents=True, exist_ok=True)
    poses = sample_plate_poses(cam, count, plate, distance_mm=dist, seed=seed)
    rng = np.random.default_rng(seed)
    images = []
    for k, pose in enumerate(poses):
        name = f"plate_{k:04d}.png"
        cv2.imwrite(str(folder / name), render_plate(cam, pose, plate, settings=settings,
                                                     rng=rng))
        centres = cam.project(pose.apply(plate.points_mm))
        images.append({"file": name, "R_cam_plate": pose.R.tolist(),
                       "t_cam_plate_mm": pose.t_mm.tolist(), "centers_px": centres.tolist()})
        log(f"{name}: plate at {np.linalg.norm(pose.t_mm):.0f} mm")
    save_plate(plate, folder / "plate.json")
    truth = {"camera": cam.to_dict(), "plate": plate.to_dict(), "preset": settings.name,
             "images": images}
    (folder / "truth.json").write_text(json.dumps(truth, indent=1) + "\n")
    typer.echo(f"wrote {count} images, plate.json and truth.json to {folder}")


@app.command("calibrate")
@friendly
def calibrate_cmd(
    images: list[str] = typer.Argument(..., help="Plate images (files or folders)."),
    out: str = typer.Option(..., "--out", help="Camera file to write (.json, .yml, .dat, "
                            ".ros.yaml)."),
    plate_file: str = typer.Option(None, "--plate", help="plate.json (from render-plate)."),
    grid: str = typer.Option(None, help="Circle grid rows x cols, e.g. 7x7 (without --plate)."),
    spacing_mm: float = typer.Option(None, help="Circle spacing in mm (without --plate)."),
    diameter_mm: float = typer.Option(None, help="Circle diameter in mm (default: spacing/2)."),
    model: str = typer.Option("division", help="division (HALCON, our least squares) or "
                              "opencv (cv2.calibrateCamera)."),
    pixel_height_um: float = typer.Option(3.45, help="Fixed pixel height Sy of the division "
                                          "model, from the sensor's datasheet."),
    bias_rounds: int = typer.Option(2, min=0, help="Rounds of the ellipse-centre bias "
                                    "correction (0: plain ellipse centres)."),
    report: str = typer.Option(None, help="Report JSON (default: <out stem>.report.json)."),
    json_out: bool = typer.Option(False, "--json", help="Print the report as JSON."),
):
    """Calibrate a camera from images of the circle plate (Zhang + Levenberg-Marquardt)."""
    import json
    from pathlib import Path

    from .calibration.intrinsics import calibrate_images
    from .geometry.camera_files import convert_camera, detect_format, write_camera

    plate = _plate_from_options(plate_file, grid, spacing_mm, diameter_mm)
    paths = []
    for a in images:
        p = Path(a)
        if p.is_dir():
            paths += sorted(q for q in p.iterdir()
                            if q.suffix.lower() in (".png", ".jpg", ".jpeg", ".bmp", ".tif",
                                                    ".tiff"))
        else:
            paths.append(p)
    fmt = detect_format(out, for_writing=True)

    def progress(name, reason):
        if reason:
            log(f"warning: {name} skipped: {reason}")

    res = calibrate_images(paths, plate, model=model, pixel_height_m=pixel_height_um * 1e-6,
                           bias_rounds=bias_rounds, progress=progress)
    conv = convert_camera(res.camera, fmt, pixel_height_um * 1e-6)
    write_camera(conv.camera, out, fmt)
    rep = res.to_dict()
    rep["written"] = {"file": str(out), "format": fmt, "exact": conv.exact,
                      "max_conversion_error_px": conv.max_error_px}
    rep_path = Path(report) if report else Path(out).with_name(Path(out).stem + ".report.json")
    rep_path.write_text(json.dumps(rep, indent=1, default=float) + "\n")
    if json_out:
        typer.echo(json.dumps(rep, indent=1, default=float))
        return
    cam = res.camera.to_dict()
    typer.echo(f"model: {res.camera.model}; {len(res.used)} images used, "
               f"{len(res.skipped)} skipped")
    for k, v in cam.items():
        if k not in ("name", "model"):
            typer.echo(f"  {k}: {v}")
    typer.echo("standard deviations:")
    for k, v in res.std.items():
        typer.echo(f"  {k}: {v:.4g}")
    typer.echo(f"RMS reprojection error: {res.rms_px:.4f} px")
    for n, e in zip(res.used, res.per_image_rms_px):
        typer.echo(f"  {n}: {e:.4f} px")
    for n, why in res.skipped.items():
        typer.echo(f"  {n}: skipped ({why})")
    if not conv.exact:
        typer.echo(f"note: {fmt} cannot hold the {res.camera.model} model; wrote the nearest "
                   f"{conv.camera.model} camera (worst pixel error {conv.max_error_px:.4f} px)")
    typer.echo(f"wrote {out} and {rep_path}")


@camera_app.command("convert")
@friendly
def camera_convert_cmd(
    src: str = typer.Argument(..., help="Camera file (.json, .yml/.yaml/.xml, ROS camera_info "
                              ".yaml, HALCON .dat)."),
    dst: str = typer.Argument(..., help="Output file; the format follows the suffix (.json, "
                              ".yml, .ros.yaml, .dat) unless --to is given."),
    to: str = typer.Option(None, help="Output format: json, opencv, ros or halcon."),
    pixel_height_um: float = typer.Option(None, help="Pixel height Sy when converting to the "
                                          "division model (default 3.45)."),
):
    """Convert a camera file between formats and models (says when it is approximate)."""
    from .errors import InputError
    from .geometry.camera_files import (
        FORMATS,
        convert_camera,
        detect_format,
        load_camera,
        write_camera,
    )

    cam = load_camera(src)
    fmt = to or detect_format(dst, for_writing=True)
    if fmt not in FORMATS:
        raise InputError(f"--to must be one of {', '.join(FORMATS)}, got {fmt!r}")
    conv = convert_camera(cam, fmt, None if pixel_height_um is None else pixel_height_um * 1e-6)
    write_camera(conv.camera, dst, fmt)
    if conv.exact:
        typer.echo(f"wrote {dst} ({fmt}, {conv.camera.model} model): exact")
    else:
        typer.echo(f"wrote {dst} ({fmt}, {conv.camera.model} model): APPROXIMATE, the "
                   f"{conv.camera.model} model was fitted to the {cam.model} camera over the "
                   f"image; worst pixel error {conv.max_error_px:.2g} px, RMS "
                   f"{conv.rms_error_px:.2g} px")




# ---- section: serve, records export (issue 12) ---------------------------------------------
records_app = typer.Typer(no_args_is_help=True, help="The service's measurement records.")
app.add_typer(records_app, name="records")


@app.command("serve")
@friendly
def serve_cmd(
    config: str = typer.Option(None, "--config", help="Cell file (TOML); default: the bundled "
                               "Table 1 cell (cutterpose/data/cell_table1.toml)."),
    host: str = typer.Option("127.0.0.1", help="Address to bind (0.0.0.0: every interface; "
                             "then use TLS and a strong token)."),
    port: int = typer.Option(8000, min=0, max=65535, help="Port."),
    workers: int = typer.Option(None, min=1, help="Worker processes (default: the cell file's, "
                                "0 there = one per core)."),
    ssl_certfile: str = typer.Option(None, help="TLS certificate (PEM); with --ssl-keyfile "
                                     "the service speaks HTTPS."),
    ssl_keyfile: str = typer.Option(None, help="TLS private key (PEM, unencrypted)."),
    ssl_ca_certs: str = typer.Option(None, help="CA bundle to verify client certificates."),
    ssl_cert_reqs: int = typer.Option(0, min=0, max=2, help="Client certificates: 0 none, "
                                      "1 optional, 2 required (mutual TLS)."),
    log_level: str = typer.Option("info", help="uvicorn log level."),
):
    """The measurement service for the robot controller (HTTP API, docs/service.md). The bearer
    token comes from the environment variable CUTTERPOSE_TOKEN or the cell file's
    service.token_file, never from the command line."""
    import dataclasses

    try:
        import uvicorn

        from .service.app import create_app
    except ImportError as e:
        fail(f"the service needs its extra: pip install 'cutterpose[service]' ({e})")
    from .service.config import load_cell

    cell = load_cell(config)
    if workers:
        cell = dataclasses.replace(cell, service=dataclasses.replace(cell.service,
                                                                     workers=workers))
    if bool(ssl_certfile) != bool(ssl_keyfile):
        fail("TLS needs both --ssl-certfile and --ssl-keyfile")
    log(f"cell {cell.name!r}: camera {cell.camera_source} "
        f"{cell.camera.image_size_px[0]} x {cell.camera.image_size_px[1]} px, "
        f"{cell.service.workers} workers, data in {cell.service.data_dir}")
    uvicorn.run(create_app(cell), host=host, port=port, log_level=log_level,
                ssl_certfile=ssl_certfile, ssl_keyfile=ssl_keyfile, ssl_ca_certs=ssl_ca_certs,
                ssl_cert_reqs=ssl_cert_reqs, timeout_graceful_shutdown=10)


@records_app.command("export")
@friendly
def records_export_cmd(
    since: str = typer.Option(None, help="ISO 8601 time (UTC if no zone), inclusive; default "
                              "everything."),
    fmt: str = typer.Option("csv", "--format", help="csv (one row per measurement) or json."),
    out: str = typer.Option(None, "--out", help="Output file (default stdout)."),
    config: str = typer.Option(None, "--config", help="Cell file naming the data directory."),
    data_dir: str = typer.Option(None, "--data-dir", help="Data directory (wins over the cell "
                                 "file and CUTTERPOSE_DATA_DIR)."),
):
    """Write the service's measurement records for the quality engineer."""
    from pathlib import Path

    from .service.config import load_cell
    from .service.records import export_records

    folder = Path(data_dir) if data_dir else load_cell(config, need_token=False).service.data_dir
    text, n = export_records(folder, since, fmt)
    if out:
        Path(out).write_text(text)
        log(f"wrote {n} records to {out}")
    else:
        typer.echo(text, nl=False)


def main() -> None:  # pragma: no cover
    app(prog_name="cutterpose")


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
