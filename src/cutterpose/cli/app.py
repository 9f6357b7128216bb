"""The Typer apps of the ``cutterpose`` command line and what its commands share:
failing with a one-line message, logging to stderr, the common options.
"""

from __future__ import annotations

from functools import wraps

import typer

from ..errors import CutterposeError

#: The help panels of ``measure`` and the commands that share its options.
IMAGE, CAMERA, VERDICT, ROBOT, OUTPUT = ("Image", "Camera and holder", "Method and verdict",
                                         "Robot", "Output")

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


def edge_break_option(panel: str | None = None):
    return typer.Option(None, "--edge-break-mm", metavar="MM", rich_help_panel=panel,
                        help="Largest edge break, for dm, dm+ and PnP (default 1.5; 0: "
                        "sharp).")


def holder_render_option():
    """``--holder`` of the renderers: the design to render (written into truth.json, so that
    the experiments measure with it)."""
    return typer.Option(None, "--holder", help="Holder JSON file to render (default: the "
                        "bundled holder); truth.json carries it, so experiments measure with it.")


def pixel_format_option(panel: str | None = None):
    """``--pixel-format`` of raw frames, the same in ``measure`` and ``track``."""
    return typer.Option(None, "--pixel-format", metavar="FORMAT", rich_help_panel=panel,
                        help="Raw frames: Mono8 (default), Mono10..Mono16 (LSB-aligned), "
                        "Mono12Packed, Mono12p.")


def budget_mm_option(panel: str | None = None):
    """``--verdict-tol-mm``: the measurement's own verdict (not the grasp's)."""
    return typer.Option(None, "--verdict-tol-mm", metavar="MM", rich_help_panel=panel,
                        help="Refuse a pose whose 3-sigma position error at the grasp point "
                        "exceeds this (default 1).")


def budget_deg_option(panel: str | None = None):
    """``--verdict-tol-deg``: the measurement's own verdict (the grasp's is ``--grasp-tol-deg``)."""
    return typer.Option(None, "--verdict-tol-deg", metavar="DEG", rich_help_panel=panel,
                        help="Refuse a pose whose 3-sigma rotation exceeds this (default "
                        "0.3).")


def old_name_option(name: str):
    """A former option name, hidden from the help, kept working so that scripts do not break."""
    return typer.Option(None, name, hidden=True)


def renamed(value, old, name: str, old_name: str):
    """The value of an option given under its name or under its former name (not both)."""
    if old is None:
        return value
    if value is not None:
        from ..errors import InputError

        raise InputError(f"{old_name} is the former name of {name}: give one of them")
    return old


def budget_tolerance(position_mm: float | None, angle_deg: float | None,
                     old_position_mm: float | None = None, old_angle_deg: float | None = None):
    """The error budget's :class:`~cutterpose.budget.Tolerance` with the options given
    (``old_*``: the same options under their former names ``--budget-tol-mm/-deg``)."""
    import math

    from ..budget import Tolerance
    from ..errors import InputError

    given = {}
    for key, name, v, old_name, old in (
            ("position_mm", "--verdict-tol-mm", position_mm, "--budget-tol-mm", old_position_mm),
            ("angle_deg", "--verdict-tol-deg", angle_deg, "--budget-tol-deg", old_angle_deg)):
        if old is not None:
            v, name = renamed(v, old, name, old_name), old_name
        if v is not None:
            if not (math.isfinite(v) and v > 0):
                raise InputError(f"{name} {v}: give a positive number")
            given[key] = float(v)
    return Tolerance(**given)


def edge_look_option(panel: str | None = None):
    """``--edge-look``, the same in every command that measures with ``dm+b``."""
    return typer.Option(None, "--edge-look", metavar="FILE", rich_help_panel=panel,
                        help="Edge look from `calibrate-edge-look` (dm+b).")


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

