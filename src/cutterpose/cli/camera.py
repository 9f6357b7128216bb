"""Camera files: ``camera convert``."""

from __future__ import annotations

import typer

from .app import (
    camera_app,
    friendly,
)


@camera_app.command("convert")
@friendly
def camera_convert_cmd(
    src: str = typer.Argument(..., help="Camera file (.json, .yml/.yaml/.xml, ROS camera_info "
                              ".yaml, HALCON .dat)."),
    dst: str = typer.Argument(..., help="Output file; the format follows the suffix (.json, "
                              ".yml, .ros.yaml, .dat) unless --to is given."),
    to: str = typer.Option(None, help="Output format: json, opencv, ros or halcon."),
    pixel_height_um: float = typer.Option(None, help="Pixel height Sy when converting to a "
                                          "HALCON model (default 3.45)."),
    halcon_model: str = typer.Option(None, help="HALCON model of a .dat output: division or "
                                     "polynomial (default: polynomial for a polynomial camera, "
                                     "else division)."),
):
    """Convert a camera file between formats and models (says when it is approximate)."""
    from ..errors import InputError
    from ..geometry.camera_files import (
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
    conv = convert_camera(cam, fmt, None if pixel_height_um is None else pixel_height_um * 1e-6,
                          halcon_model)
    write_camera(conv.camera, dst, fmt)
    if conv.exact:
        typer.echo(f"wrote {dst} ({fmt}, {conv.camera.model} model): exact")
    else:
        typer.echo(f"wrote {dst} ({fmt}, {conv.camera.model} model): APPROXIMATE, the "
                   f"{conv.camera.model} model was fitted to the {cam.model} camera over the "
                   f"image; worst pixel error {conv.max_error_px:.2g} px, RMS "
                   f"{conv.rms_error_px:.2g} px")
