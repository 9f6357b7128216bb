"""The command line's help reads on an 80-column terminal: `measure --help` fits a screen, no
help text is cut, and the renamed options still work under their former names."""

from __future__ import annotations

import pytest
import typer
from typer.testing import CliRunner

from cutterpose.cli import app

runner = CliRunner()
NARROW = {"COLUMNS": "80", "TERMINAL_WIDTH": "80"}


def _command_paths(group, prefix=()):
    for name, cmd in sorted(group.commands.items()):
        if hasattr(cmd, "commands"):  # a group (typer ships its own click)
            yield from _command_paths(cmd, prefix + (name,))
        else:
            yield prefix + (name,)


COMMANDS = list(_command_paths(typer.main.get_command(app)))


def _help(path) -> str:
    res = runner.invoke(app, [*path, "--help"], env=NARROW)
    assert res.exit_code == 0, res.output
    return res.output


def test_measure_help_fits_a_screen_grouped():
    out = _help(("measure",))
    lines = out.rstrip("\n").splitlines()
    assert len(lines) <= 50, f"{len(lines)} lines:\n{out}"
    assert max(len(x) for x in lines) <= 80
    for panel in ("Image", "Camera and holder", "Method and verdict", "Robot", "Output"):
        assert f"─ {panel} ─" in out, panel
    # one name per tolerance, saying whose it is; the former names are not shown
    for shown in ("--verdict-tol-deg", "--verdict-tol-mm", "--grasp-tol-deg", "--grasp-tol-mm"):
        assert shown in out
    for former in ("--budget-tol-deg", "--budget-tol-mm", "--angle-tol-deg", "--position-tol-mm"):
        assert former not in out


@pytest.mark.parametrize("path", COMMANDS, ids=" ".join)
def test_no_help_text_is_cut_at_80_columns(path):
    out = _help(path)
    assert "…" not in out, out
    assert max(len(x) for x in out.splitlines()) <= 80


def test_former_tolerance_names_still_work(tmp_path):
    missing = str(tmp_path / "none.png")
    for opt in ("--budget-tol-deg", "--budget-tol-mm", "--angle-tol-deg", "--position-tol-mm"):
        res = runner.invoke(app, ["measure", missing, opt, "0.5"])
        assert "No such option" not in res.output, opt
        assert res.exit_code == 2 and "none.png" in res.output, (opt, res.output)
    # both names at once: refused before any work
    both = runner.invoke(app, ["experiment", "images", str(tmp_path), "--verdict-tol-deg",
                               "0.4", "--budget-tol-deg", "0.5"])
    assert both.exit_code == 2 and "former name of --verdict-tol-deg" in both.output
