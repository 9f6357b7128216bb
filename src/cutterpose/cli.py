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
    """The main job on the bundled default data: measure the example image and print the pose
    (before the image pipeline exists: a short synthetic experiment)."""
    try:
        from .pipeline import demo as pipeline_demo
    except ImportError:
        pipeline_demo = None
    if pipeline_demo is not None:
        pipeline_demo(out)
        return
    from .experiments.synthetic import run_synthetic

    res = run_synthetic(["opencv-ippe-lm", "opencv-sqpnp"], [0.5, 1.0, 2.0], 100, out,
                        show_progress=True)
    typer.echo((res.out_dir / "summary.md").read_text())


# ---- section: measure, render, render-set, experiment images (issue 5) --------------------
def _render_camera(spec: str | None):
    """``table1`` / ``synthetic`` (bundled cameras) or a camera file; default Table 1."""
    from .camera import default_camera, load_camera

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
    from .holder import load_holder
    from .pose import Pose
    from .render import preset as get_preset
    from .render import render_holder, save_rendered

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
):
    """Render an image set with its truth.json (PROTOCOL.md, exchange formats)."""
    from rich.progress import Progress

    from .render import DEFAULT_MIX, render_set
    from .render import preset as get_preset

    mix = DEFAULT_MIX
    if preset is not None:
        get_preset(preset)
        mix = ((preset, 1.0),)
    cam = _render_camera(camera)
    with Progress(transient=True, console=None) as bar:
        task = bar.add_task("rendering", total=count)
        path = render_set(count, seed, out, cam, mix=mix,
                          progress=lambda i, n: bar.update(task, completed=i + 1))
    typer.echo(f"wrote {count} images and {path}")



# ---- section: calibrate, render-plate, camera convert (issue 6) ---------------------------


def main() -> None:  # pragma: no cover
    app(prog_name="cutterpose")


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
