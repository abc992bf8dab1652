"""Strict JSON for every JSON file safenav writes (``config.json``, ``final.json``, ``eval
--json``, ``fly --json``, ONNX sidecars, results, benchmarks): a metric without a value (NaN,
e.g. the mean time to goal of a policy that never arrives) is ``null``, since Python's ``json``
would write a bare ``NaN`` that no other JSON reader accepts. :func:`write_json` is the one
writer: atomic and ``fsync``-ed (:func:`~safenav.common.atomic.atomic_write`)."""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

from safenav.common.atomic import write_text_atomic


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


def dumps(obj: Any, default: Callable[[Any], Any] | None = None) -> str:
    """Indented strict JSON (``allow_nan=False``: a non-finite number left is a bug, not output);
    ``default`` turns what JSON has no type for into something it has (``str``, say)."""
    return json.dumps(jsonable(obj), indent=2, allow_nan=False, default=default) + "\n"


def write_json(path: str | Path, obj: Any, default: Callable[[Any], Any] | None = None) -> None:
    """Write ``obj`` as strict JSON (:func:`dumps`) to ``path`` atomically and durably: a
    temporary file, ``fsync``, a rename, ``fsync`` of the directory. An existing file is either
    kept or replaced whole, also across a crash or power cut. Missing parent folders are made
    (``--json results/new/x.json``)."""
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(path, dumps(obj, default))


__all__ = ["dumps", "jsonable", "write_json"]
