"""Strict JSON for the files the CLI writes (``eval --json``, ``fly --json``): a metric without a
value (NaN, e.g. the mean time to goal of a policy that never arrives) is ``null``, since
Python's ``json`` would write a bare ``NaN`` that no other JSON reader accepts."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any


def jsonable(obj: Any) -> Any:
    """``obj`` with non-finite floats as None, NumPy/torch scalars as Python numbers, tuples as
    lists and paths as strings."""
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, Path):
        return str(obj)
    if hasattr(obj, "tolist") and not isinstance(obj, (str, bytes)):  # numpy / torch
        return jsonable(obj.tolist())
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def dumps(obj: Any) -> str:
    """Indented strict JSON (``allow_nan=False``: a non-finite number left is a bug, not output)."""
    return json.dumps(jsonable(obj), indent=2, allow_nan=False) + "\n"


def write_json(path: Path, obj: Any) -> None:
    """Write ``obj`` as strict JSON to ``path`` atomically (a temporary file, then a rename): an
    existing file is either kept or replaced whole."""
    path = Path(path)
    text = dumps(obj)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        tmp.write_text(text)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


__all__ = ["dumps", "jsonable", "write_json"]
