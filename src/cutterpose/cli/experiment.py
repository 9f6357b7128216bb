"""The paper's experiments and the field tables: ``experiment synthetic``, ``images``,
``field-table``, ``acceptance``."""

from __future__ import annotations

import typer

from .app import (
    budget_deg_option,
    budget_mm_option,
    budget_tolerance,
    edge_break_option,
    edge_look_option,
    experiment_app,
    fail,
    friendly,
    load_edge_look,
    log,
    old_name_option,
)


@experiment_app.command("synthetic")
@friendly
def experiment_synthetic(
    methods: str = typer.Option("opencv-ippe-lm,opencv-sqpnp", show_default=False,
                                help="Comma-separated method names (see `cutterpose methods`; "
                                "default: opencv-ippe-lm, opencv-sqpnp)."),
    trials: int = typer.Option(1000, min=1, help="Trials per noise level."),
    sigmas: str = typer.Option("0:5:0.5", help="Noise levels in px: start:stop:step or a,b,c."),
    out: str = typer.Option("results/synthetic", help="Output folder."),
    trials_file: str = typer.Option(None, "--trials-file", help="Run a PROTOCOL trial file "
                                    "(.npz) instead of drawing trials."),
    workers: int = typer.Option(1, min=1, help="Worker processes (results are identical)."),
    scheduler: str = typer.Option(None, "--scheduler", help="Run on the Dask distributed "
                                  "cluster at this address (tcp://host:8786) instead of local "
                                  "processes; needs cutterpose\\[cluster]."),
    seed: int = typer.Option(0, help="Base seed of the trial generator."),
    progress: bool = typer.Option(True, help="Show a progress bar on stderr."),
):
    """The paper's synthetic noise sweep (Fig. 5): writes trials.csv, summary.md, fig5.png."""
    from ..experiments.synthetic import parse_sigmas, run_synthetic
    from ..methods import parse_methods

    meths = parse_methods(methods)
    res = run_synthetic(meths, parse_sigmas(sigmas), trials, out, seed=seed, workers=workers,
                        trials_file=trials_file, show_progress=progress, scheduler=scheduler)
    typer.echo((res.out_dir / "summary.md").read_text())
    log(f"wrote {res.out_dir}/trials.csv, summary.md, summary.json, fig5.png")




@experiment_app.command("images")
@friendly
def experiment_images_cmd(
    folder: str = typer.Argument(..., help="Image set: a folder with truth.json."),
    methods: str = typer.Option("dm,dm+,dlt,epnp,rpnp,aspnp,opnp", show_default=False,
                                help="Comma-separated methods (default: dm, dm+, dlt, epnp, "
                                "rpnp, aspnp, opnp)."),
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
    edge_break_mm: float = edge_break_option(),
    edge_look: str = edge_look_option(),
    budget_tol_mm: float = budget_mm_option(),
    budget_tol_deg: float = budget_deg_option(),
    old_budget_tol_mm: float = old_name_option("--budget-tol-mm"),
    old_budget_tol_deg: float = old_name_option("--budget-tol-deg"),
):
    """Table 2 figures of every method on an image set (trials.csv, summary.md)."""
    from rich.progress import Progress

    from ..experiments.images import run_images
    from ..image import FeatureParams
    from ..methods import parse_methods

    names = [m.name for m in parse_methods(methods)]
    chains = {"field": lambda: FeatureParams(refine=not no_refine),
              "paper": lambda: FeatureParams.paper(refine=not no_refine),
              "as-written": lambda: FeatureParams.paper(refine=False, threshold_fallback="none",
                                                        model_fallback="none")}
    if chain not in chains:
        fail(f"--chain must be one of {', '.join(chains)}, got {chain!r}")
    tol = budget_tolerance(budget_tol_mm, budget_tol_deg, old_budget_tol_mm, old_budget_tol_deg)
    with Progress(transient=True) as bar:
        task = bar.add_task("images", total=None)
        from ..pipeline import QualityLimits

        look = load_edge_look(edge_look)
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

    from ..errors import InputError

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

    from ..experiments.field import write_field

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

    from ..errors import InputError
    from ..experiments.acceptance import DEFAULT_TOLERANCES_DEG, write_acceptance

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
                     budget_tolerance(position_tol_mm, None).position_mm)
    typer.echo((Path(out) / "acceptance.md").read_text())
