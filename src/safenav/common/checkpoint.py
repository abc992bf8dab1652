"""Checkpoints: atomic writes, friendly errors on reading, and RNG state capture.

A checkpoint is one ``torch.save`` dict with ``format`` and ``format_version`` keys. It is written
to a temporary file in the same directory, flushed to disk, then moved over the old one with
``os.replace`` (atomic on POSIX): a crash leaves either the old or the new checkpoint, never half
of one.
"""

from __future__ import annotations

import os
import pickle
import random
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import torch

from safenav.errors import SafenavError

FORMAT = "safenav-checkpoint"
FORMAT_VERSION = 1


def save_checkpoint(path: str | Path, state: dict[str, Any]) -> None:
    """Write ``state`` (plus format tags) to ``path`` atomically."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with tmp.open("wb") as f:
            torch.save({"format": FORMAT, "format_version": FORMAT_VERSION, **state}, f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def load_checkpoint(path: str | Path, map_location: str | torch.device = "cpu") -> dict[str, Any]:
    """Read a checkpoint; ``SafenavError`` naming the problem if it is missing, unreadable, not a
    safenav checkpoint, or of another format version."""
    path = Path(path)
    if path.is_dir():
        path = path / "checkpoint.pt"
    if not path.exists():
        raise SafenavError(f"checkpoint {path} not found")
    try:
        state = torch.load(path, map_location=map_location, weights_only=False)
    except (
        RuntimeError,
        EOFError,
        pickle.UnpicklingError,
        zipfile.BadZipFile,
        ValueError,
        OSError,
    ) as err:
        raise SafenavError(
            f"checkpoint {path} is corrupt or not a torch file ({type(err).__name__}: {err})"
        ) from None
    if not isinstance(state, dict) or state.get("format") != FORMAT:
        raise SafenavError(f"{path} is not a safenav training checkpoint (no '{FORMAT}' tag)")
    version = state.get("format_version")
    if version != FORMAT_VERSION:
        raise SafenavError(f"{path} has checkpoint format version {version}; this safenav reads "
                           f"version {FORMAT_VERSION}: retrain, or use the safenav that wrote it")  # fmt: skip
    return state


def rng_state() -> dict[str, Any]:
    """Python, NumPy, torch CPU (and CUDA) RNG states."""
    state = {
        "python": random.getstate(),
        "numpy": np.random.get_state(),  # noqa: NPY002 (the global RNG is what we restore)
        "torch": torch.get_rng_state(),
    }
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict[str, Any]) -> None:
    random.setstate(state["python"])
    np.random.set_state(state["numpy"])  # noqa: NPY002
    torch.set_rng_state(
        state["torch"].cpu() if isinstance(state["torch"], torch.Tensor) else state["torch"]
    )
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed % 2**32)  # noqa: NPY002
    torch.manual_seed(seed)


__all__ = ["FORMAT", "FORMAT_VERSION", "load_checkpoint", "rng_state", "save_checkpoint",
           "seed_everything", "set_rng_state"]  # fmt: skip
