"""Typed errors of cutterpose.

Every error the package raises on purpose derives from :class:`CutterposeError`, so a caller (the
CLI, a robot controller) can catch all expected failures with one ``except`` and let real bugs
surface as tracebacks.
"""

from __future__ import annotations

#: the longest message an error carries (a value quoted from a file is cut in its middle)
MAX_MESSAGE_CHARS = 600


def one_line(text: str, limit: int = MAX_MESSAGE_CHARS) -> str:
    """``text`` on one line (whitespace runs joined) and at most ``limit`` characters (the
    middle cut out: a message that quotes a 10 000-character value from a hostile file keeps
    its start, which names the file and field, and its end)."""
    text = " ".join(str(text).split())
    if len(text) <= limit:
        return text
    head = (2 * limit) // 3
    return f"{text[:head]} [...] {text[-(limit - head - 7):]}"


class CutterposeError(Exception):
    """Base class of every expected failure in cutterpose.

    Its message is one line of at most :data:`MAX_MESSAGE_CHARS` characters (:func:`one_line`),
    whatever the input it quotes: the CLI prints it as ``error: <message>``, the service as
    the ``message`` of its answer.
    """

    def __init__(self, *args):
        if args and isinstance(args[0], str):
            args = (one_line(args[0]), *args[1:])
        super().__init__(*args)


class InputError(CutterposeError, ValueError):
    """An argument has the wrong shape, type or value (NaN, inf, mismatched arrays...)."""


class DegenerateInputError(InputError):
    """The input is well formed but geometrically degenerate (too few points, collinear points,
    points behind the camera, a pose outside the motion range...)."""


class ModelFileError(CutterposeError, ValueError):
    """A camera or holder file is missing, unreadable or malformed.

    The message names the file and the offending field.
    """


class CameraFileError(ModelFileError):
    """A camera file is malformed."""


class HolderModelError(ModelFileError):
    """A holder model is malformed (not closed, not simple, not planar, edges not in two
    directions...)."""


class CellFileError(ModelFileError):
    """A cell file (``cutterpose serve --config``) is malformed; the message names the field."""


class ImageError(CutterposeError):
    """An image cannot be used: missing, unreadable, wrong size, black, saturated..."""


class FeatureError(CutterposeError):
    """The image processing could not extract the holder's 20 characteristic segments."""


class NoSolutionError(CutterposeError):
    """A solver found no admissible pose."""


class DependencyError(CutterposeError):
    """An optional dependency is missing; the message says which extra installs it."""


class ClusterError(CutterposeError):
    """A Dask cluster cannot be reached, or its workers cannot run the jobs."""


class EdgeLookFileError(ModelFileError):
    """An edge look file (``cutterpose calibrate-edge-look --out``) is missing or malformed."""


class HandEyeFileError(ModelFileError):
    """A hand-eye file (``handeye.json``) is missing or malformed."""


class StoreError(CutterposeError):
    """The service's record (the data directory's database and images) cannot be opened or
    written: locked, corrupt, full or read-only; the message says which."""

    def __init__(self, message: str, transient: bool = False):
        super().__init__(message)
        #: the next try may work once the cause is gone (space freed, lock released)
        self.transient = transient
