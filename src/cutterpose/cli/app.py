"""The Typer apps of the ``cutterpose`` command line and what its commands share:
failing with a one-line message, logging to stderr, the common options.
"""

from __future__ import annotations

from functools import wraps

import typer

from ..errors import CutterposeError

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


def edge_break_option():
    return typer.Option(None, "--edge-break-mm", help="The pocket edge's largest break (mm) "
                        "for the corner methods (dm, dm+, PnP), which see the broken edge, not "
                        "the design edge: their verdict carries the pose shift of an edge seen "
                        "anywhere up to this far outside it (default: not known, 1.5 mm; 0: a "
                        "sharp edge). dm+b and dm+r measure the break and ignore it.")


def holder_render_option():
    """``--holder`` of the renderers: the design to render (written into truth.json, so that
    the experiments measure with it)."""
    return typer.Option(None, "--holder", help="Holder JSON file to render (default: the "
                        "bundled holder); truth.json carries it, so experiments measure with it.")


def pixel_format_option():
    """``--pixel-format`` of raw frames, the same in ``measure`` and ``track``."""
    return typer.Option(None, "--pixel-format", help="Raw frames' pixel format: Mono8 "
                        "(default), Mono10, Mono12, Mono14, Mono16 (2 bytes, LSB-aligned), "
                        "Mono12Packed (GigE Vision) or Mono12p (PFNC); a sidecar's "
                        "pixel_format is used when this is not given.")


def budget_mm_option():
    """``--budget-tol-mm``: the measurement's own verdict (not the grasp's)."""
    return typer.Option(None, "--budget-tol-mm", help="Refuse the measurement when its error "
                        "budget's 3-sigma position at the grasp point (the pocket's centre) "
                        "exceeds this (mm; default the robot's 1 mm).")


def budget_deg_option():
    return typer.Option(None, "--budget-tol-deg", help="Refuse the measurement when its error "
                        "budget's 3-sigma rotation exceeds this (deg; default 0.3: 1 mm at the "
                        "pocket's ends, 200 mm from the origin; `experiment acceptance` shows "
                        "what another value accepts on a measured set).")


def budget_tolerance(position_mm: float | None, angle_deg: float | None):
    """The error budget's :class:`~cutterpose.budget.Tolerance` with the options given."""
    import math

    from ..budget import Tolerance
    from ..errors import InputError

    given = {}
    for key, name, v in (("position_mm", "--budget-tol-mm", position_mm),
                         ("angle_deg", "--budget-tol-deg", angle_deg)):
        if v is not None:
            if not (math.isfinite(v) and v > 0):
                raise InputError(f"{name} {v}: give a positive number")
            given[key] = float(v)
    return Tolerance(**given)


def edge_look_option():
    """``--edge-look``, the same in every command that measures with ``dm+b``."""
    return typer.Option(None, "--edge-look", help="Edge look file from `calibrate-edge-look` "
                        "(dm+b fits the calibrated look).")


def load_edge_look(path: str | None):
    """The calibrated look of ``--edge-look`` (None: the generic looks)."""
    if not path:
        return None
    from ..calibration.edge_look import load_edge_look

    return load_edge_look(path)


def convention_option(what: str):
    """``--convention`` of a pose file (``what``: which file)."""
    return typer.Option(None, help=f"Pose convention of {what} that does not state it: "
                        "protocol, quat-xyzw, quat-wxyz, abb, ur, rotvec, kuka, fanuc, matrix.")


def length_unit_option(what: str):
    return typer.Option(None, help=f"mm or m, for {what} that does not state it.")


def angle_unit_option(what: str):
    return typer.Option(None, help=f"deg or rad, for {what} that does not state it.")



def camera_from_option(spec: str | None):
    """``table1`` / ``synthetic`` (bundled cameras) or a camera file; default Table 1."""
    from ..geometry.camera import default_camera
    from ..geometry.camera_files import load_camera

    if spec is None or spec in ("table1", "synthetic"):
        return default_camera(spec or "table1")
    return load_camera(spec)



def image_paths(items) -> list:
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

