"""Reading JSON inputs with errors that name the file."""

from __future__ import annotations

import json
import os
from pathlib import Path

__all__ = ["read_json"]


def read_json(path: str | os.PathLike) -> object:
    """Parse a JSON file.

    Raises
    ------
    ValueError
        ``"<path>: file not found"`` or ``"<path>: not valid JSON (...)"``.
    """
    path = Path(path)
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise ValueError(f"{path}: file not found") from None
    except json.JSONDecodeError as err:
        raise ValueError(f"{path}: not valid JSON ({err})") from None
