"""The ``cutterpose`` command line.

Results go to stdout (tables, or one JSON object with ``--json``); logs and progress bars go to
stderr. Every expected failure exits non-zero with a one-line message, never a traceback.
One module per command group; importing them registers their commands on :data:`app`.
"""

from __future__ import annotations

# isort: off
# the import order is the order of the commands in --help: the daily ones first
from . import measure, render, track, experiment  # noqa: F401  (registers the commands)
from . import calibrate, edge_look, handeye, camera, serve  # noqa: F401
# isort: on
from .app import app

__all__ = ["app", "main"]


def main() -> None:  # pragma: no cover
    app(prog_name="cutterpose")
