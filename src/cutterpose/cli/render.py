"""Rendering images with known poses: ``render``, ``render-set``, ``render-sequence``."""

from __future__ import annotations

import typer

from .app import (
    app,
    camera_from_option,
    fail,
    friendly,
    holder_render_option,
    log,
)

# robot-cell options shared by render and render-set (issue 11)
_SCENE, _ENGINE, _CELL = "Pose and scene", "Renderer", "Robot cell"
_CELL_HANDEYE = typer.Option(None, "--handeye", metavar="FILE", rich_help_panel=_CELL,
                             help="handeye.json with the true T_flange_cam.")
_CELL_HOLDER = typer.Option(None, "--holder-base-pose", metavar="POSE", rich_help_panel=_CELL,
                            help="The holder in the base frame: x,y,z,qx,qy,qz,qw (mm) or a "
                            "one-row pose file.")


@app.command("render")
@friendly
def render_cmd(
    out: str = typer.Option(..., "--out", metavar="PNG", help="Output image (.png)."),
    truth: bool = typer.Option(True, help="Also write <stem>.truth.json beside the image."),
    pose: str = typer.Option("0,0,0,0,0,600", metavar="POSE", rich_help_panel=_SCENE,
                             help="alpha,beta,gamma (deg),X,Y,Z (mm) of the holder in the "
                             "camera frame."),
    preset: str = typer.Option(None, metavar="NAME", rich_help_panel=_SCENE,
                               help="analytic: easy (default), dim, worn, occluded, blurred or "
                               "hard; pbr: sharp, new (default) or worn."),
    seed: int = typer.Option(0, rich_help_panel=_SCENE,
                             help="Seed of textures, occluders and noise."),
    camera: str = typer.Option(None, metavar="FILE", rich_help_panel=_SCENE,
                               help="Camera file, or table1 (default), synthetic."),
    holder: str = typer.Option(None, metavar="FILE", rich_help_panel=_SCENE,
                               help="Holder file (default: the bundled holder)."),
    pocket_depth: float = typer.Option(None, metavar="MM", rich_help_panel=_SCENE,
                                       help="Pocket depth (preset: 80)."),
    engine: str = typer.Option("analytic", rich_help_panel=_ENGINE,
                               help="analytic (closed-form ray casting) or pbr (Mitsuba 3 path "
                               "tracing of field conditions; extra \\[field])."),
    spp: int = typer.Option(None, min=1, metavar="N", rich_help_panel=_ENGINE,
                            help="pbr: samples per pixel (preset: 12)."),
    variant: str = typer.Option(None, metavar="NAME", rich_help_panel=_ENGINE,
                                help="pbr: Mitsuba variant (default: llvm_ad_mono if it works "
                                "here, else scalar_rgb)."),
    flange_pose: str = typer.Option(None, "--flange-pose", metavar="POSE", rich_help_panel=_CELL,
                                    help="The true T_base_flange: x,y,z,qx,qy,qz,qw (mm) or a "
                                    "pose file row; with --handeye and --holder-base-pose, "
                                    "instead of --pose."),
    handeye: str = _CELL_HANDEYE,
    holder_base_pose: str = _CELL_HOLDER,
):
    """Render one realistic image of the holder at a pose (camera frame), or as the camera on
    a robot's flange sees a holder at a known base-frame pose."""
    from ..errors import InputError
    from ..geometry.holder import load_holder
    from ..geometry.pose import Pose

    cell = (flange_pose, handeye, holder_base_pose)
    if any(v is not None for v in cell):
        from ..calibration.handeye import load_handeye
        from ..robot.poses import load_flange_pose, read_poses

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
    cam = camera_from_option(camera)
    if engine == "pbr":
        from ..render.pbr import field_preset, render_field, save_field_rendered

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
    from ..render.analytic import preset as get_preset
    from ..render.analytic import render_holder, save_rendered

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
    from ..errors import InputError

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
                                  "processes; needs cutterpose\\[cluster]."),
    engine: str = typer.Option("analytic", help="analytic or pbr (Mitsuba 3; extra \\[field])."),
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
    holder: str = holder_render_option(),
):
    """Render an image set with its truth.json (PROTOCOL.md, exchange formats)."""
    from rich.progress import Progress

    from ..errors import InputError
    from ..geometry.holder import load_holder

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
        from ..calibration.handeye import load_handeye
        from ..robot.poses import load_flange_pose, read_poses

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
        from ..render.pbr import field_preset
        from ..render.sets import render_field_set

        if scheduler is not None or workers > 1:
            fail("--engine pbr renders in one process (Mitsuba uses every core itself); "
                 "drop --workers / --scheduler")

        fp = field_preset(preset or "new")
        cam = camera_from_option(camera)
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
    from ..render.analytic import preset as get_preset
    from ..render.sets import DEFAULT_MIX, render_set

    mix = DEFAULT_MIX
    if preset is not None:
        get_preset(preset)
        mix = ((preset, 1.0),)
    cam = camera_from_option(camera)
    with Progress(transient=True, console=None) as bar:
        task = bar.add_task("rendering", total=count)
        path = render_set(count, seed, out, cam, hol, mix=mix, workers=workers,
                          scheduler=scheduler,
                          progress=lambda done, n: bar.update(task, completed=done),
                          poses=poses, distance_mm=dist)
    typer.echo(f"wrote {count} images and {path}")




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
                               "extra \\[field]; one process)."),
    spp: int = typer.Option(None, min=1, help="pbr: samples per pixel (preset: 12)."),
    seed: int = typer.Option(0, help="Seed of the surface and the noise."),
    camera: str = typer.Option(None, help="table1 (default), synthetic, or a camera file."),
    drop: str = typer.Option("", help="Comma-separated frame indices to drop."),
    jump_at: int = typer.Option(None, help="From this frame on, shift the holder by --jump-mm."),
    jump_mm: str = typer.Option("30,0,0", help="The jump X,Y,Z in mm."),
    workers: int = typer.Option(1, min=1, help="Worker processes."),
    scheduler: str = typer.Option(None, "--scheduler", help="Dask scheduler address."),
    holder: str = holder_render_option(),
):
    """Render an approach sequence: the camera moving from --z-start to --z-end mm."""
    from rich.progress import Progress

    from ..errors import InputError
    from ..geometry.holder import load_holder
    from ..render.sequence import render_sequence

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
        path = render_sequence(out, frames, z_start, z_end, camera_from_option(camera), hol,
                               settings=preset, seed=seed, engine_name=engine, drop=dropped,
                               jump_at=jump_at, jump_mm=jump, workers=workers,
                               scheduler=scheduler, spp=spp,
                               progress=lambda done, n: bar.update(task, completed=done))
    typer.echo(f"wrote {frames - len(dropped)} frames and {path}")
