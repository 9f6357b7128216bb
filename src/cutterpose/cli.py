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


def _edge_break_option():
    return typer.Option(None, "--edge-break-mm", help="The pocket edge's largest break (mm) "
                        "for the corner methods (dm, dm+, PnP), which see the broken edge, not "
                        "the design edge: their verdict carries the pose shift of an edge seen "
                        "anywhere up to this far outside it (default: not known, 1.5 mm; 0: a "
                        "sharp edge). dm+b and dm+r measure the break and ignore it.")


def _holder_render_option():
    """``--holder`` of the renderers: the design to render (written into truth.json, so that
    the experiments measure with it)."""
    return typer.Option(None, "--holder", help="Holder JSON file to render (default: the "
                        "bundled holder); truth.json carries it, so experiments measure with it.")


def _pixel_format_option():
    """``--pixel-format`` of raw frames, the same in ``measure`` and ``track``."""
    return typer.Option(None, "--pixel-format", help="Raw frames' pixel format: Mono8 "
                        "(default), Mono10, Mono12, Mono14, Mono16 (2 bytes, LSB-aligned), "
                        "Mono12Packed (GigE Vision) or Mono12p (PFNC); a sidecar's "
                        "pixel_format is used when this is not given.")


def _budget_mm_option():
    """``--budget-tol-mm``: the measurement's own verdict (not the grasp's)."""
    return typer.Option(None, "--budget-tol-mm", help="Refuse the measurement when its error "
                        "budget's 3-sigma position at the grasp point (the pocket's centre) "
                        "exceeds this (mm; default the robot's 1 mm).")


def _budget_deg_option():
    return typer.Option(None, "--budget-tol-deg", help="Refuse the measurement when its error "
                        "budget's 3-sigma rotation exceeds this (deg; default 0.3: 1 mm at the "
                        "pocket's ends, 200 mm from the origin; `experiment acceptance` shows "
                        "what another value accepts on a measured set).")


def _budget_tolerance(position_mm: float | None, angle_deg: float | None):
    """The error budget's :class:`~cutterpose.budget.Tolerance` with the options given."""
    import math

    from .budget import Tolerance
    from .errors import InputError

    given = {}
    for key, name, v in (("position_mm", "--budget-tol-mm", position_mm),
                         ("angle_deg", "--budget-tol-deg", angle_deg)):
        if v is not None:
            if not (math.isfinite(v) and v > 0):
                raise InputError(f"{name} {v}: give a positive number")
            given[key] = float(v)
    return Tolerance(**given)


def _edge_look_option():
    """``--edge-look``, the same in every command that measures with ``dm+b``."""
    return typer.Option(None, "--edge-look", help="Edge look file from `calibrate-edge-look` "
                        "(dm+b fits the calibrated look).")


def _load_edge_look(path: str | None):
    """The calibrated look of ``--edge-look`` (None: the generic looks)."""
    if not path:
        return None
    from .calibration.edge_look import load_edge_look

    return load_edge_look(path)


def _convention_option(what: str):
    """``--convention`` of a pose file (``what``: which file)."""
    return typer.Option(None, help=f"Pose convention of {what} that does not state it: "
                        "protocol, quat-xyzw, quat-wxyz, abb, ur, rotvec, kuka, fanuc, matrix.")


def _length_unit_option(what: str):
    return typer.Option(None, help=f"mm or m, for {what} that does not state it.")


def _angle_unit_option(what: str):
    return typer.Option(None, help=f"deg or rad, for {what} that does not state it.")


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
    scheduler: str = typer.Option(None, "--scheduler", help="Run on the Dask distributed "
                                  "cluster at this address (tcp://host:8786) instead of local "
                                  "processes; needs cutterpose[cluster]."),
    seed: int = typer.Option(0, help="Base seed of the trial generator."),
    progress: bool = typer.Option(True, help="Show a progress bar on stderr."),
):
    """The paper's synthetic noise sweep (Fig. 5): writes trials.csv, summary.md, fig5.png."""
    from .experiments.synthetic import parse_sigmas, run_synthetic
    from .methods import parse_methods

    meths = parse_methods(methods)
    res = run_synthetic(meths, parse_sigmas(sigmas), trials, out, seed=seed, workers=workers,
                        trials_file=trials_file, show_progress=progress, scheduler=scheduler)
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
    Table 1 camera, measure it (dm+b), print the pose and write the overlay."""
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


# robot-cell options shared by render and render-set (issue 11)
_CELL_HANDEYE = typer.Option(None, "--handeye", help="Robot cell: handeye.json with the true "
                             "T_flange_cam.")
_CELL_HOLDER = typer.Option(None, "--holder-base-pose", help="Robot cell: the holder in the "
                            "base frame, x_mm,y_mm,z_mm,qx,qy,qz,qw or a one-row pose file.")


@app.command("render")
@friendly
def render_cmd(
    out: str = typer.Option(..., "--out", help="Output image (.png)."),
    pose: str = typer.Option("0,0,0,0,0,600", help="alpha,beta,gamma [deg],X,Y,Z [mm] of the "
                             "holder in the camera frame."),
    preset: str = typer.Option(None, help="analytic: easy (default), dim, worn, occluded, "
                               "blurred or hard; pbr: sharp, new (default) or worn."),
    seed: int = typer.Option(0, help="Seed of textures, occluders and noise."),
    camera: str = typer.Option(None, help="table1 (default), synthetic, or a camera file."),
    holder: str = typer.Option(None, help="Holder JSON file (default: the bundled holder)."),
    pocket_depth: float = typer.Option(None, help="Pocket depth in mm (preset: 80)."),
    truth: bool = typer.Option(True, help="Also write <stem>.truth.json beside the image."),
    flange_pose: str = typer.Option(None, "--flange-pose", help="Robot cell: the true "
                                    "T_base_flange (pose file row or x_mm,y_mm,z_mm,qx,qy,qz,"
                                    "qw); needs --handeye and --holder-base-pose, replaces "
                                    "--pose."),
    handeye: str = _CELL_HANDEYE,
    holder_base_pose: str = _CELL_HOLDER,
    engine: str = typer.Option("analytic", help="analytic (closed-form ray casting) or pbr "
                               "(Mitsuba 3 path tracing of field conditions; extra [field])."),
    spp: int = typer.Option(None, min=1, help="pbr: samples per pixel (preset: 12)."),
    variant: str = typer.Option(None, help="pbr: Mitsuba variant (default: llvm_ad_mono if "
                                "it works here, else scalar_rgb)."),
):
    """Render one realistic image of the holder at a pose (camera frame), or as the camera on
    a robot's flange sees a holder at a known base-frame pose."""
    from .errors import InputError
    from .geometry.holder import load_holder
    from .geometry.pose import Pose

    cell = (flange_pose, handeye, holder_base_pose)
    if any(v is not None for v in cell):
        from .calibration.handeye import load_handeye
        from .robot.poses import load_flange_pose, read_poses

        if any(v is None for v in cell):
            raise InputError("a robot-cell render needs --flange-pose, --handeye and "
                             "--holder-base-pose together")
        X = load_handeye(handeye).T_flange_cam
        hp = holder_base_pose
        T_bh = (parse_row_or_file(hp, read_poses, "holder") if hp.lower().endswith(
            (".csv", ".json")) else load_flange_pose(hp).with_frames("base", "holder"))
        T_ch = X.inverse() @ load_flange_pose(flange_pose).inverse() @ T_bh
    else:
        try:
            dof = [float(x) for x in pose.split(",")]
        except ValueError:
            dof = []
        if len(dof) != 6:
            raise InputError(f"--pose needs six comma-separated numbers alpha,beta,gamma,X,Y,"
                             f"Z; got {pose!r}")
        T_ch = Pose.from_euler(*dof)
    cam = _render_camera(camera)
    if engine == "pbr":
        from .render.pbr import field_preset, render_field, save_field_rendered

        fp = field_preset(preset or "new")
        if pocket_depth is not None:
            fp = fp.with_(pocket_depth_mm=pocket_depth)
        r = render_field(T_ch, cam, load_holder(holder) if holder else None,
                         fp, seed=seed, variant=variant, spp=spp)
        path = save_field_rendered(r, out, cam, truth=truth)
        log(f"pbr {r.variant}, {r.spp} spp: {r.timings_s['total']:.1f} s "
            f"(render {r.timings_s['render_crop'] + r.timings_s['render_background']:.1f} s)")
        typer.echo(f"wrote {path}" + (f" and {path.with_suffix('.truth.json')}" if truth else ""))
        return
    if engine != "analytic":
        raise InputError(f"--engine must be 'analytic' or 'pbr', got {engine!r}")
    from .render.analytic import preset as get_preset
    from .render.analytic import render_holder, save_rendered

    preset = preset or "easy"
    settings = get_preset(preset)
    if pocket_depth is not None:
        settings = settings.with_(pocket_depth_mm=pocket_depth)
    r = render_holder(T_ch.with_frames("cam", "holder"), cam,
                      load_holder(holder) if holder else None, settings, seed=seed)
    path = save_rendered(r, out, cam, truth=truth)
    typer.echo(f"wrote {path}" + (f" and {path.with_suffix('.truth.json')}" if truth else ""))


def parse_row_or_file(path: str, read_poses, frame: str):
    """The single pose of a one-row pose file, as ``T_base_<frame>``."""
    from .errors import InputError

    poses = read_poses(path, to_frame="base", from_frame=frame)
    if len(poses) != 1:
        raise InputError(f"{path}: expected one pose, got {len(poses)}")
    return poses[0]


@app.command("render-set")
@friendly
def render_set_cmd(
    out: str = typer.Option(..., "--out", help="Output folder (images and truth.json)."),
    count: int = typer.Option(100, min=1, help="Number of images."),
    seed: int = typer.Option(0, help="Seed of the poses, difficulties and images."),
    camera: str = typer.Option(None, help="table1 (default), synthetic, or a camera file."),
    preset: str = typer.Option(None, help="Use this preset for every image (analytic default: "
                               "a mix of easy, dim, worn, occluded, blurred, hard; pbr: sharp, "
                               "new (default) or worn)."),
    workers: int = typer.Option(1, min=1, help="Worker processes (the set does not change)."),
    scheduler: str = typer.Option(None, "--scheduler", help="Run on the Dask distributed "
                                  "cluster at this address (tcp://host:8786) instead of local "
                                  "processes; needs cutterpose[cluster]."),
    engine: str = typer.Option("analytic", help="analytic or pbr (Mitsuba 3; extra [field])."),
    spp: int = typer.Option(None, min=1, help="pbr: samples per pixel (preset: 12)."),
    variant: str = typer.Option(None, help="pbr: Mitsuba variant."),
    resume: bool = typer.Option(False, "--resume", help="pbr: keep the images of an "
                                "interrupted run of the same set and render the rest."),
    flange_poses: str = typer.Option(None, "--flange-poses", help="Robot cell: a pose file of "
                                     "T_base_flange, one image per row (replaces --count); "
                                     "needs --handeye and --holder-base-pose."),
    handeye: str = _CELL_HANDEYE,
    holder_base_pose: str = _CELL_HOLDER,
    distance_mm: str = typer.Option(None, "--distance-mm", help="NEAR:FAR: draw the camera "
                                    "distance uniformly in it (mm) instead of 600 +- 20, the "
                                    "light auto-exposed as in render-sequence (e.g. an edge "
                                    "look reference over an approach: 580:920)."),
    views: int = typer.Option(1, min=1, help="pbr: each holder seen from this many random "
                              "poses (a retake's views: the same wear and slurry, another "
                              "viewpoint); --count images in all."),
    holder: str = _holder_render_option(),
):
    """Render an image set with its truth.json (PROTOCOL.md, exchange formats)."""
    from rich.progress import Progress

    from .errors import InputError
    from .geometry.holder import load_holder

    hol = load_holder(holder) if holder else None

    dist = None
    if distance_mm is not None:
        try:
            dist = tuple(float(v) for v in distance_mm.split(":"))
        except ValueError:
            dist = ()
        if len(dist) != 2 or not 0 < dist[0] <= dist[1]:
            raise InputError(f"--distance-mm must be NEAR:FAR in mm with 0 < NEAR <= FAR, got "
                             f"{distance_mm!r}")
    poses = None
    cell = (flange_poses, handeye, holder_base_pose)
    if any(v is not None for v in cell):
        from .calibration.handeye import load_handeye
        from .robot.poses import load_flange_pose, read_poses

        if any(v is None for v in cell) or engine != "analytic":
            raise InputError("a robot-cell set needs --flange-poses, --handeye and "
                             "--holder-base-pose together (analytic engine)")
        X = load_handeye(handeye).T_flange_cam
        hp = holder_base_pose
        T_bh = (parse_row_or_file(hp, read_poses, "holder") if hp.lower().endswith(
            (".csv", ".json")) else load_flange_pose(hp).with_frames("base", "holder"))
        poses = [(X.inverse() @ T_bf.inverse() @ T_bh).with_frames("cam", "holder")
                 for T_bf in read_poses(flange_poses)]
        count = len(poses)

    if engine == "pbr":
        from .render.pbr import field_preset, render_field_set

        if scheduler is not None or workers > 1:
            fail("--engine pbr renders in one process (Mitsuba uses every core itself); "
                 "drop --workers / --scheduler")

        fp = field_preset(preset or "new")
        cam = _render_camera(camera)
        with Progress(transient=True, console=None) as bar:
            task = bar.add_task(f"rendering ({fp.name}, pbr)", total=count)
            path = render_field_set(count, seed, out, fp, cam, hol, variant=variant, spp=spp,
                                    progress=lambda done, n: bar.update(task, completed=done),
                                    resume=resume, distance_mm=dist, views=views)
        typer.echo(f"wrote {count} images and {path}")
        return
    if views != 1:
        fail("--views is for --engine pbr (the analytic renderer draws each image's holder "
             "afresh)")
    if engine != "analytic":
        raise InputError(f"--engine must be 'analytic' or 'pbr', got {engine!r}")
    from .render.analytic import DEFAULT_MIX, render_set
    from .render.analytic import preset as get_preset

    mix = DEFAULT_MIX
    if preset is not None:
        get_preset(preset)
        mix = ((preset, 1.0),)
    cam = _render_camera(camera)
    with Progress(transient=True, console=None) as bar:
        task = bar.add_task("rendering", total=count)
        path = render_set(count, seed, out, cam, hol, mix=mix, workers=workers,
                          scheduler=scheduler,
                          progress=lambda done, n: bar.update(task, completed=done),
                          poses=poses, distance_mm=dist)
    typer.echo(f"wrote {count} images and {path}")


@app.command("measure")
@friendly
def measure_cmd(
    image: str = typer.Argument(..., help="Image of the holder (PNG, JPEG, TIFF...), or a raw "
                                "frame (.raw with a sidecar <file>.json, or --raw)."),
    camera: str = typer.Option(None, help="table1 (default), synthetic, or a camera file."),
    raw: str = typer.Option(None, "--raw", help="Read IMAGE as a raw frame of WIDTHxHEIGHT "
                            "pixels (as a GigE camera delivers it; Mono8: no decode)."),
    pixel_format: str = _pixel_format_option(),
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
    edge_break_mm: float = _edge_break_option(),
    edge_look: str = _edge_look_option(),
    budget_tol_mm: float = _budget_mm_option(),
    budget_tol_deg: float = _budget_deg_option(),
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
    convention: str = _convention_option("a --flange-pose file"),
    length_unit: str = _length_unit_option("a --flange-pose file"),
    angle_unit: str = _angle_unit_option("a --flange-pose file"),
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

    from .errors import InputError
    from .frames import load_frame, parse_raw_size
    from .geometry.holder import default_holder, load_holder
    from .pipeline import measure

    cam = _render_camera(camera)
    hol = load_holder(holder) if holder else None
    look = _load_edge_look(edge_look)
    if (handeye is None) != (flange_pose is None):
        raise InputError("the base frame needs both --handeye and --flange-pose")
    robot = None
    if handeye is not None:
        from .robot import GraspTolerance, RobotAccuracy, load_flange_pose, load_handeye

        robot = (load_handeye(handeye),
                 load_flange_pose(flange_pose, convention, length_unit, angle_unit),
                 RobotAccuracy(robot_accuracy_mm, robot_accuracy_deg),
                 GraspTolerance(position_tol_mm, angle_deg=angle_tol_deg))

    if chain not in ("field", "paper"):
        fail(f"--chain must be 'field' or 'paper', got {chain!r}")
    t0 = time.perf_counter()
    img = load_frame(image, cam, parse_raw_size(raw) if raw else None, pixel_format)
    load_ms = (time.perf_counter() - t0) * 1e3
    from .pipeline import QualityLimits, station_center_dof, station_params

    m = measure(img, cam, hol, method, params=station_params(cam, chain, distance_mm),
                limits=QualityLimits(edge_shape=edge_shape, edge_break_mm=edge_break_mm,
                                     tolerance=_budget_tolerance(budget_tol_mm, budget_tol_deg),
                                     range_center_dof=station_center_dof(distance_mm)),
                edge_look=look, corners=True if corners else None)
    m.timings_ms = {"load": load_ms} | m.timings_ms
    if robot is not None:
        from .robot import locate

        m.robot = locate(m, robot[0], robot[1], robot[2], camera=cam,
                         holder=hol or default_holder(), tolerance=robot[3])
    if overlay:
        from .geometry.holder import default_holder
        from .overlay import write_overlay

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


@experiment_app.command("images")
@friendly
def experiment_images_cmd(
    folder: str = typer.Argument(..., help="Image set: a folder with truth.json."),
    methods: str = typer.Option("dm,dm+,dlt,epnp,rpnp,aspnp,opnp",
                                help="Comma-separated methods."),
    out: str = typer.Option("results/images", help="Output folder."),
    workers: int = typer.Option(1, min=1, help="Worker processes."),
    scheduler: str = typer.Option(None, "--scheduler", help="Run on the Dask distributed "
                                  "cluster at this address (tcp://host:8786) instead of local "
                                  "processes; the set must be at the same path on every worker."),
    limit: int = typer.Option(None, help="Only the first N images."),
    no_refine: bool = typer.Option(False, "--no-refine",
                                   help="The paper's lines only (no gradient refinement)."),
    chain: str = typer.Option("field", help="Image chain: field (default), paper (section "
                              "2.1 with this package's refinements and fall-backs) or "
                              "as-written (section 2.1 exactly: threshold 70, contour lines, "
                              "no refinement, no fall-back)."),
    edge_shape: str = typer.Option("unknown", help="The pocket edge's break (holder drawing): "
                                   "round, chamfer or unknown (default: both shapes fitted)."),
    edge_break_mm: float = _edge_break_option(),
    edge_look: str = _edge_look_option(),
    budget_tol_mm: float = _budget_mm_option(),
    budget_tol_deg: float = _budget_deg_option(),
):
    """Table 2 figures of every method on an image set (trials.csv, summary.md)."""
    from rich.progress import Progress

    from .experiments.images import run_images
    from .image import FeatureParams
    from .methods import parse_methods

    names = [m.name for m in parse_methods(methods)]
    chains = {"field": lambda: FeatureParams(refine=not no_refine),
              "paper": lambda: FeatureParams.paper(refine=not no_refine),
              "as-written": lambda: FeatureParams.paper(refine=False, threshold_fallback="none",
                                                        model_fallback="none")}
    if chain not in chains:
        fail(f"--chain must be one of {', '.join(chains)}, got {chain!r}")
    tol = _budget_tolerance(budget_tol_mm, budget_tol_deg)
    with Progress(transient=True) as bar:
        task = bar.add_task("images", total=None)
        from .pipeline import QualityLimits

        look = _load_edge_look(edge_look)
        run_images(folder, names, out, workers=workers, limit=limit, scheduler=scheduler,
                   params=chains[chain](),
                   limits=QualityLimits(edge_shape=edge_shape, edge_break_mm=edge_break_mm,
                                        tolerance=tol),
                   progress=lambda done, n: bar.update(task, completed=done, total=n),
                   edge_look=look)
    typer.echo(f"wrote {out}/trials.csv, summary.md, corners.csv, failures.csv")
    typer.echo((__import__("pathlib").Path(out) / "summary.md").read_text())



def _named_folders(sets: list[str]) -> dict:
    """``NAME=FOLDER`` arguments as {name: Path}; a typed error for anything else."""
    from pathlib import Path

    from .errors import InputError

    pairs = {}
    for s in sets:
        name, sep, folder = s.partition("=")
        if not sep or not name or not folder:
            raise InputError(f"{s!r}: give each set as NAME=RESULTS_DIR")
        pairs[name] = Path(folder)
    return pairs


@experiment_app.command("field-table")
@friendly
def experiment_field_cmd(
    sets: list[str] = typer.Argument(..., help="NAME=RESULTS_DIR of `experiment images`, "
                                     "one per image set (e.g. sharp=results/sharp)."),
    out: str = typer.Option("results/field", help="Output folder (field.md, field.json)."),
):
    """The field table: accepted/refused, bias, std, p95 errors and wrong accepted poses."""
    from pathlib import Path

    from .experiments.field import write_field

    write_field(_named_folders(sets), out)
    typer.echo((Path(out) / "field.md").read_text())


@experiment_app.command("acceptance")
@friendly
def experiment_acceptance_cmd(
    sets: list[str] = typer.Argument(..., help="NAME=RESULTS_DIR of `experiment images`."),
    method: str = typer.Option("dm+b", help="The method whose verdicts are re-applied."),
    tolerances: str = typer.Option(None, help="Angle tolerances to try (3 sigma, deg, "
                                   "comma-separated; default 0.2 to 0.5 in steps of 0.05)."),
    position_tol_mm: float = typer.Option(None, help="Position tolerance at the grasp point "
                                          "(3 sigma, mm; default the verdict's 1 mm)."),
    out: str = typer.Option("results/acceptance",
                            help="Output folder (acceptance.md, .json, .png)."),
):
    """Acceptance and the accepted errors against the verdict's angle tolerance, from runs of
    `experiment images` (no new measurement), with the ceilings the poses set."""
    import math
    from pathlib import Path

    from .errors import InputError
    from .experiments.acceptance import DEFAULT_TOLERANCES_DEG, write_acceptance

    pairs = _named_folders(sets)
    tols = DEFAULT_TOLERANCES_DEG
    if tolerances is not None:
        try:
            tols = [float(x) for x in tolerances.split(",") if x.strip()]
        except ValueError:
            raise InputError(f"--tolerances {tolerances!r}: give degrees separated by "
                             "commas") from None
        if not tols or not all(t > 0 and math.isfinite(t) for t in tols):
            raise InputError(f"--tolerances {tolerances!r}: give positive degrees")
    write_acceptance(pairs, out, method, tols,
                     _budget_tolerance(position_tol_mm, None).position_mm)
    typer.echo((Path(out) / "acceptance.md").read_text())


# ---- section: track, render-sequence (issue 13) -------------------------------------------
FRAME_SUFFIXES = (".png", ".tif", ".tiff", ".bmp", ".jpg", ".jpeg", ".pgm", ".raw", ".mono8")


def _frames(source: str, raw_size, pixel_format=None):
    """(name, frame) of a folder of frames (sorted names) or of a video file."""
    from pathlib import Path

    from .errors import InputError
    from .frames import load_frame

    p = Path(source)
    if p.is_dir():
        files = sorted(q for q in p.iterdir() if q.suffix.lower() in FRAME_SUFFIXES)
        if not files:
            raise InputError(f"{p}: no frames ({', '.join(FRAME_SUFFIXES)})")
        for q in files:
            yield q.name, load_frame(q, raw_size=raw_size, pixel_format=pixel_format)
        return
    if not p.is_file():
        raise InputError(f"{p}: neither a folder of frames nor a video file")
    import cv2

    cap = cv2.VideoCapture(str(p))
    if not cap.isOpened():
        raise InputError(f"{p}: not a readable video")
    k = 0
    try:
        while True:
            ok, frame = cap.read()
            if not ok:
                break
            yield f"{p.name}#{k}", frame
            k += 1
    finally:
        cap.release()
    if k == 0:
        raise InputError(f"{p}: the video has no frames")


@app.command("track")
@friendly
def track_cmd(
    source: str = typer.Argument(..., help="Folder of frames (sorted by name) or a video."),
    camera: str = typer.Option(None, help="table1 (default), synthetic, or a camera file."),
    holder: str = typer.Option(None, help="Holder JSON file (default: the bundled holder)."),
    method: str = typer.Option("dm+b", help="Pose method of the full measurement (first "
                               "frame and fall-backs; dm+b, the default: the tracked frames fit "
                               "the design edge of a broken edge, its offsets measured again by "
                               "a band fit as the view changes, 'anchor' per frame; dm+: the "
                               "seen edges, for a sharp edge (--edge-break-mm 0) or a binned "
                               "camera)."),
    raw: str = typer.Option(None, "--raw", help="Frames are raw files of WIDTHxHEIGHT."),
    pixel_format: str = _pixel_format_option(),
    filter_: bool = typer.Option(False, "--filter", help="Also report a constant-velocity "
                                 "filtered pose (beside the raw one)."),
    json_lines: bool = typer.Option(False, "--json-lines", help="One JSON object per frame."),
    edge_break_mm: float = _edge_break_option(),
    edge_look: str = _edge_look_option(),
    anchor_lag: int = typer.Option(None, min=0, help="dm+b: run the re-anchors' band fits "
                                   "(~120 ms) beside the tracking and apply them this many "
                                   "frames later (0: on their frame, which waits; default: "
                                   "the tracker's); > 0 also measures a frame tracking "
                                   "cannot follow beside it (that frame has no pose and says "
                                   "so; the next ones are tracked meanwhile)."),
):
    """Track the holder through a sequence: edges predicted from the previous pose, the full
    measurement on the first frame and whenever tracking fails (said per frame)."""
    from dataclasses import replace

    import numpy as np

    from .frames import parse_raw_size
    from .geometry.holder import load_holder
    from .tracking import Tracker, TrackParams, approach_limits

    cam = _render_camera(camera)
    look = _load_edge_look(edge_look)
    limits = replace(approach_limits(), edge_break_mm=edge_break_mm)
    tp = TrackParams() if anchor_lag is None else TrackParams(anchor_lag=anchor_lag)
    tracker = Tracker(cam, load_holder(holder) if holder else None, method, limits=limits,
                      filter=filter_, edge_look=look, track=tp)
    size = parse_raw_size(raw) if raw else None
    modes, times, anchors, beside = {}, [], 0, 0
    with tracker:
        results = ((name, tracker.update(frame))
                   for name, frame in _frames(source, size, pixel_format))
        for name, r in results:
            _track_line(r, name, modes, times, json_lines)
            anchors += r.anchor.startswith("re-anchored")
            beside += "full measurement started (applied at frame" in r.fallback_reason
    med = f", tracking median {np.median(times):.1f} ms/frame" if times else ""
    log(f"{sum(modes.values())} frames: {modes.get('track', 0)} tracked, "
        f"{modes.get('full', 0)} full measurements (first + fall-backs), "
        f"{modes.get('lost', 0)} lost{med}"
        + (f"; {beside} fall-backs measured beside the tracking" if beside else "")
        + (f"; {anchors} re-anchored (band fit)" if anchors else ""))


def _track_line(r, name: str, modes: dict, times: list, json_lines: bool) -> None:
    """One frame of ``cutterpose track``: counted, and printed (a line, or JSON)."""
    import json as _json

    modes[r.mode] = modes.get(r.mode, 0) + 1
    if r.mode == "track":
        times.append(r.timings_ms["total"])
    if json_lines:
        typer.echo(_json.dumps({"file": name} | r.to_dict()))
        return
    pose = "  ".join(f"{v:8.3f}" for v in r.pose.dof) if r.pose is not None else "no pose"
    note = f"  ({r.fallback_reason})" if r.fallback_reason and r.frame else ""
    note += f"  ({r.anchor})" if r.anchor else ""
    typer.echo(f"{name:24s} {r.mode:5s} {pose}  {r.timings_ms['total']:6.1f} ms{note}")


@app.command("render-sequence")
@friendly
def render_sequence_cmd(
    out: str = typer.Option(..., "--out", help="Output folder (frames and truth.json)."),
    frames: int = typer.Option(60, min=2, help="Number of frames of the approach."),
    z_start: float = typer.Option(900.0, help="Camera-holder distance at the first frame, mm."),
    z_end: float = typer.Option(600.0, help="Distance at the last frame, mm."),
    preset: str = typer.Option(None, help="Render preset: analytic easy (default), dim, worn, "
                               "field, new, rounded, ...; pbr sharp, new (default), worn."),
    engine: str = typer.Option("analytic", help="analytic or pbr (Mitsuba 3 path tracing, "
                               "extra [field]; one process)."),
    spp: int = typer.Option(None, min=1, help="pbr: samples per pixel (preset: 12)."),
    seed: int = typer.Option(0, help="Seed of the surface and the noise."),
    camera: str = typer.Option(None, help="table1 (default), synthetic, or a camera file."),
    drop: str = typer.Option("", help="Comma-separated frame indices to drop."),
    jump_at: int = typer.Option(None, help="From this frame on, shift the holder by --jump-mm."),
    jump_mm: str = typer.Option("30,0,0", help="The jump X,Y,Z in mm."),
    workers: int = typer.Option(1, min=1, help="Worker processes."),
    scheduler: str = typer.Option(None, "--scheduler", help="Dask scheduler address."),
    holder: str = _holder_render_option(),
):
    """Render an approach sequence: the camera moving from --z-start to --z-end mm."""
    from rich.progress import Progress

    from .errors import InputError
    from .geometry.holder import load_holder
    from .render.sequence import render_sequence

    hol = load_holder(holder) if holder else None

    try:
        dropped = tuple(int(x) for x in drop.split(",") if x.strip())
        jump = tuple(float(x) for x in jump_mm.split(","))
        assert len(jump) == 3
    except (ValueError, AssertionError):
        raise InputError(f"--drop must be integers and --jump-mm X,Y,Z; got {drop!r}, "
                         f"{jump_mm!r}") from None
    with Progress(transient=True) as bar:
        task = bar.add_task("rendering", total=frames - len(dropped))
        path = render_sequence(out, frames, z_start, z_end, _render_camera(camera), hol,
                               settings=preset, seed=seed, engine_name=engine, drop=dropped,
                               jump_at=jump_at, jump_mm=jump, workers=workers,
                               scheduler=scheduler, spp=spp,
                               progress=lambda done, n: bar.update(task, completed=done))
    typer.echo(f"wrote {frames - len(dropped)} frames and {path}")


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
    robot_cell: bool = typer.Option(False, "--robot-cell", help="Hand-eye mode: a simulated "
                                    "robot cell (random camera mount, fixed plate) moves the "
                                    "camera through COUNT stations; writes robot_poses.csv "
                                    "(reported flange poses) and cell_truth.json."),
    repeatability_mm: float = typer.Option(0.03, help="--robot-cell: robot position noise, "
                                           "mm per axis (1 sigma)."),
    repeatability_deg: float = typer.Option(0.005, help="--robot-cell: robot rotation noise, "
                                            "deg per axis (1 sigma)."),
    plate_poses: str = typer.Option(None, "--plate-poses", help="Render one image per pose "
                                    "of this pose file (T_cam_plate, any convention of "
                                    "`cutterpose.robot.poses`) instead of drawing poses."),
    convention: str = _convention_option("a --plate-poses file"),
    length_unit: str = _length_unit_option("a --plate-poses file"),
    angle_unit: str = _angle_unit_option("a --plate-poses file"),
):
    """Render images of the circle calibration plate at poses that cover the field, at given
    poses (--plate-poses), or from the stations of a simulated robot cell (--robot-cell)."""
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
    if robot_cell:
        from .robot.cell import RobotCell

        if plate_poses:
            raise InputError("give either --robot-cell or --plate-poses, not both")
        cell = RobotCell.random(cam, seed, repeatability_mm=repeatability_mm,
                                repeatability_deg=repeatability_deg)
        cell.plate = plate
        cell.write_handeye_set(folder, count, seed, settings,
                               progress=lambda k, n: log(f"station {k}/{n}"))
        typer.echo(f"wrote {count} plate images, robot_poses.csv, plate.json, camera.json and "
                   f"cell_truth.json to {folder}")
        return
    if plate_poses:
        from .robot.poses import read_poses

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
    paths = _image_paths(images)
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


@app.command("calibrate-edge-look")
@friendly
def calibrate_edge_look_cmd(
    source: list[str] = typer.Argument(..., help="Rendered sets (folders with truth.json; "
                                       "several are pooled, e.g. poses near and far), or "
                                       "images of the reference holder (files or folders) "
                                       "with --poses."),
    out: str = typer.Option(..., "--out", help="Edge look file to write (JSON)."),
    poses: str = typer.Option(None, "--poses", help="T_cam_holder of each image, in order: a "
                              "pose file (CSV or JSON, cutterpose.robot.poses conventions)."),
    camera: str = typer.Option(None, help="table1 (default), synthetic, or a camera file "
                               "(with --poses)."),
    holder: str = typer.Option(None, help="Holder JSON file (with --poses; default: bundled)."),
    convention: str = _convention_option("a --poses file"),
    length_unit: str = _length_unit_option("a --poses file"),
    angle_unit: str = _angle_unit_option("a --poses file"),
    edge_shape: str = typer.Option("unknown", help="The reference holder's break: round, "
                                   "chamfer, or unknown (chosen per image by cost); with a "
                                   "rendered set, 'truth' takes each image's from truth.json."),
    limit: int = typer.Option(None, help="Only the first N images of each set."),
    workers: int = typer.Option(1, min=1, help="Processes that evaluate the look's cost (the "
                                "result does not change; ~1.8x faster with 2)."),
    offsets: bool = typer.Option(True, "--offsets/--no-offsets", help="Also calibrate, per "
                                 "shape, the design-edge offset the look still leaves at the "
                                 "known poses."),
    json_out: bool = typer.Option(False, "--json", help="Print the file's content as JSON."),
):
    """Calibrate dm+b's edge look on a reference holder at known poses (docs/notes/edge_band.md):
    the look's photometry fitted so that the measured band profiles put the design edge where
    the known pose does; then the design-edge shift at the known poses, generic vs calibrated."""
    import json
    from pathlib import Path

    from .calibration.edge_look import (
        calibrate_edge_look,
        calibrate_offsets,
        load_reference_images,
        load_reference_set,
        save_edge_look,
        shift_at_truth,
    )
    from .errors import InputError

    if edge_shape not in ("unknown", "round", "chamfer", "truth"):
        fail(f"--edge-shape must be round, chamfer, unknown or truth, got {edge_shape!r}")
    shape = edge_shape if edge_shape in ("round", "chamfer") else None
    if poses is None:
        missing = [s for s in source if not (Path(s) / "truth.json").is_file()]
        if missing:
            raise InputError(f"{missing[0]}: not a rendered set (no truth.json); give rendered "
                             "sets, or images and --poses")
        refs = [r for s in source
                for r in load_reference_set(s, limit=limit, use_shape=edge_shape == "truth")]
        if shape is not None:
            for r in refs:
                r.shape = shape
    else:
        from .geometry.holder import default_holder, load_holder
        from .robot.poses import read_poses

        if edge_shape == "truth":
            fail("--edge-shape truth needs a rendered set")
        ps = read_poses(poses, convention, length_unit, angle_unit, to_frame="cam",
                        from_frame="holder")
        refs = load_reference_images(_image_paths(source)[:limit], ps[:limit] if limit else ps,
                                     _render_camera(camera),
                                     load_holder(holder) if holder else default_holder(), shape)
    log(f"{len(refs)} reference images; fitting the look with the design edge at the known "
        "poses")
    from rich.progress import Progress

    with Progress(transient=True, console=None) as bar:
        task = bar.add_task("fitting the look", total=None)

        def tick(k, n, n_max):
            bar.update(task, description=f"fitting the look, round {k}", completed=n,
                       total=n_max)

        cal = calibrate_edge_look(refs, progress=log, tick=tick, workers=workers)
    if offsets:
        log("the design-edge offset per shape at the known poses")
        cal = calibrate_offsets(refs, cal)
    log("checking: the design-edge shift at the known poses, generic and calibrated looks")
    check = {"generic": shift_at_truth(refs), "calibrated": shift_at_truth(refs,
                                                                            cal.band_looks())}
    cal.report["shift_at_truth"] = check
    save_edge_look(cal, out)
    if json_out:
        typer.echo(json.dumps(cal.to_dict(), indent=1))
        return
    lk, sd = cal.look, cal.sd()
    typer.echo(f"calibrated look on {cal.report['images']} images, {cal.report['segments']} "
               "segments:")
    for k in ("specular", "shininess", "wall_albedo", "pocket_level"):
        typer.echo(f"  {k}: {getattr(lk, k):.4g} +- {sd[k]:.2g}")
    typer.echo(f"  residual cost: {cal.report['cost_ratio_to_start']:.3f} of the nominal look's "
               "(shift 0)")
    offs = cal.offsets
    depth = dict(offs.depth_mm)
    for shape, o in offs.offset_mm:
        sd_o, sd_d = offs.sd(shape)
        d = (f", depth {depth[shape]:+.3f} +- {sd_d:.3f} mm below the face"
             if shape in depth else "")
        typer.echo(f"  design-edge offset ({shape}): {o:+.4f} +- {sd_o:.4f} mm{d}")
    for name, c in check.items():
        typer.echo(f"  {name} look at the known poses: design-edge shift {c['mean_px']:+.3f} px "
                   f"({c['mean_mm']:+.4f} mm), sd of image means {c['sd_of_image_means_px']:.3f}"
                   f" px, segment sd {c['segment_sd_px']:.3f} px; Z error of the pose fitted "
                   f"from the known pose {c['z_error_mean_mm']:+.3f} +- "
                   f"{c['z_error_sd_mm'] or 0.0:.3f} mm")
    typer.echo(f"wrote {out}")


def _image_paths(items) -> list:
    """Image files from files and folders (a folder's images in sorted order)."""
    from pathlib import Path

    paths = []
    for a in items:
        p = Path(a)
        if p.is_dir():
            paths += sorted(q for q in p.iterdir()
                            if q.suffix.lower() in (".png", ".jpg", ".jpeg", ".bmp", ".tif",
                                                    ".tiff"))
        else:
            paths.append(p)
    return paths


# ---- section: handeye (issue 11) ----------------------------------------------------------
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
    convention: str = _convention_option("the --robot-poses file"),
    length_unit: str = _length_unit_option("the --robot-poses file"),
    angle_unit: str = _angle_unit_option("the --robot-poses file"),
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

    from .calibration.handeye import handeye_from_images, save_handeye
    from .calibration.plate import CirclePlate, load_plate
    from .robot.poses import read_poses

    cam = _render_camera(camera)
    plate = load_plate(plate_file) if plate_file else CirclePlate()
    poses = read_poses(robot_poses, convention, length_unit, angle_unit)

    def progress(name, reason):
        if reason:
            log(f"warning: {name} skipped (and its robot pose): {reason}")

    res = handeye_from_images(_image_paths(images), poses, cam, plate, progress=progress,
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
