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


# ---- section: measure, render, render-set, experiment images (issue 5) --------------------


# ---- section: calibrate, render-plate, camera convert (issue 6) ---------------------------


def main() -> None:  # pragma: no cover
    app(prog_name="cutterpose")


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
