"""Reading the package's JSON files (camera, holder, plate) with typed, file-naming errors."""

from __future__ import annotations

import json
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
