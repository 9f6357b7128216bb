"""Reading the package's JSON files (camera, holder, plate) with typed, file-naming errors,
and the one-line reason of any parser's error (JSON, YAML, TOML) for the readers' messages."""

from __future__ import annotations

import json
import math
from pathlib import Path

from ..errors import ModelFileError


def read_json(path, error: type[ModelFileError] = ModelFileError, what: str = "file"):
    """Parse the JSON file at ``path``.

    Raises ``error`` (a :class:`ModelFileError`) naming the file when it is missing, unreadable
    or not valid JSON, instead of a bare ``OSError`` / ``JSONDecodeError``.
    """
    path = Path(path)
    if not path.is_file():
        raise error(f"{path}: {what} not found")
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise error(f"{path}: not valid JSON ({e})") from None
    except OSError as e:
        raise error(f"{path}: cannot be read ({e.strerror})") from None


def parse_error_text(e: Exception, limit: int = 240) -> str:
    """A parser's error as one short line: ``line L, column C: problem`` for PyYAML's marked
    errors (whose text spans several lines with a copy of the offending line), else the text
    with its whitespace runs joined."""
    mark, problem = getattr(e, "problem_mark", None), getattr(e, "problem", None)
    if mark is not None and problem:
        text = f"line {mark.line + 1}, column {mark.column + 1}: {problem}"
    else:
        text = str(e)
    text = " ".join(text.split())
    return text if len(text) <= limit else text[: limit - 3] + "..."


def is_finite_number(v) -> bool:
    """``v`` is an int or float (not a bool) that a float holds finitely: False for NaN, inf,
    ``10**400`` (where ``math.isfinite`` raises ``OverflowError``) and any other type."""
    if isinstance(v, bool) or not isinstance(v, int | float):
        return False
    try:
        return math.isfinite(v)
    except OverflowError:
        return False
