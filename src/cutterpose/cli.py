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


# ---- section: demo ------------------------------------------------------------------------


# ---- section: measure, render, render-set, experiment images (issue 5) --------------------


# ---- section: calibrate, render-plate, camera convert (issue 6) ---------------------------


def main() -> None:  # pragma: no cover
    app(prog_name="cutterpose")


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
