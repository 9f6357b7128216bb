"""Calibrating the edge look in the cell: ``calibrate-edge-look``."""

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


@app.command("calibrate-edge-look")
@friendly
def calibrate_edge_look_cmd(
    source: list[str] = typer.Argument(..., help="Rendered sets (folders with truth.json; "
                                       "several are pooled, e.g. poses near and far), or "
                                       "images of the reference holder (files or folders) "
                                       "with --poses."),
    out: str = typer.Option(..., "--out", help="Edge look file to write (JSON)."),
    poses: str = typer.Option(None, "--poses", help="T_cam_holder of each image, in order: a "
                              "pose file (CSV or JSON, the conventions of docs/robot.md)."),
    camera: str = typer.Option(None, help="table1 (default), synthetic, or a camera file "
                               "(with --poses)."),
    holder: str = typer.Option(None, help="Holder JSON file (with --poses; default: bundled)."),
    convention: str = convention_option("a --poses file"),
    length_unit: str = length_unit_option("a --poses file"),
    angle_unit: str = angle_unit_option("a --poses file"),
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

    from ..calibration.edge_look import save_edge_look
    from ..calibration.edge_look_cell import (
        EDGE_SHAPE_CHOICES,
        calibrate_in_cell,
        reference_images,
    )

    if edge_shape not in EDGE_SHAPE_CHOICES:
        fail(f"--edge-shape must be round, chamfer, unknown or truth, got {edge_shape!r}")
    if poses is None:
        refs = reference_images(source, edge_shape=edge_shape, limit=limit)
    else:
        from ..geometry.holder import load_holder
        from ..robot.poses import read_poses

        if edge_shape == "truth":
            fail("--edge-shape truth needs a rendered set")
        ps = read_poses(poses, convention, length_unit, angle_unit, to_frame="cam",
                        from_frame="holder")
        refs = reference_images(image_paths(source), ps, camera_from_option(camera),
                                load_holder(holder) if holder else None, edge_shape, limit)
    from rich.progress import Progress

    with Progress(transient=True, console=None) as bar:
        task = bar.add_task("fitting the look", total=None)

        def tick(k, n, n_max):
            bar.update(task, description=f"fitting the look, round {k}", completed=n,
                       total=n_max)

        cal = calibrate_in_cell(refs, offsets=offsets, workers=workers, progress=log,
                                tick=tick)
    check = cal.report["shift_at_truth"]
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
