"""Checkpoints: atomic writes, friendly errors on reading, and RNG state capture.

A checkpoint is one ``torch.save`` dict with ``format`` and ``format_version`` keys. It is written
to a temporary file in the same directory, flushed to disk, then moved over the old one with
``os.replace`` (atomic on POSIX): a crash leaves either the old or the new checkpoint, never half
of one. The temporary file of a writer that was killed mid-write is removed by the next write.
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

from safenav.errors import SafenavError, SafenavRuntimeError, one_line

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
    _remove_stale_temps(path)


def _remove_stale_temps(path: Path) -> None:
    """Delete ``.NAME.PID.tmp`` files of writers that no longer run (SIGKILLed mid-write: with
    ``--save-buffer`` each is as large as the replay buffer)."""
    for tmp in path.parent.glob(f".{path.name}.*.tmp"):
        try:
            os.kill(int(tmp.name.split(".")[-2]), 0)  # signal 0: does the process exist?
        except ValueError:
            continue  # not one of ours
        except ProcessLookupError:
            tmp.unlink(missing_ok=True)
        except PermissionError:
            pass  # another user's live process


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
    except RuntimeError as err:
        if "CUDA" not in str(err) or not str(map_location).startswith("cuda"):
            raise _unreadable(path, err) from None
        # a CUDA device asked for on a machine without one: not the file's fault
        raise SafenavRuntimeError(f"cannot load {path} onto {map_location}: CUDA is not "
                                  "available on this machine; use --device cpu") from None  # fmt: skip
    except (
        EOFError,
        pickle.UnpicklingError,
        zipfile.BadZipFile,
        ValueError,
        OSError,
    ) as err:
        raise _unreadable(path, err) from None
    if not isinstance(state, dict) or state.get("format") != FORMAT:
        raise SafenavError(f"{path} is not a safenav training checkpoint (no '{FORMAT}' tag)")
    version = state.get("format_version")
    if version != FORMAT_VERSION:
        newer = isinstance(version, int) and version > FORMAT_VERSION
        fix = ("it was written by a newer safenav: upgrade safenav to read it" if newer
               else "retrain, or use the safenav that wrote it")  # fmt: skip
        raise SafenavError(f"{path} has checkpoint format version {version}; this safenav reads "
                           f"version {FORMAT_VERSION}: {fix}")  # fmt: skip
    return state


def _unreadable(path: Path, err: BaseException) -> SafenavError:
    # torch's own text goes on for lines ("This is an internal miniz error..."): keep its start
    reason = one_line(str(err).split(". ")[0], 160)
    return SafenavError(f"checkpoint {path} is corrupt or truncated, or not a torch file "
                        f"({type(err).__name__}: {reason})")  # fmt: skip


# What ``--resume`` needs besides the agent's weights; a policy-only file has none of it.
TRAINING_KEYS = ("agent", "optimizers", "curriculum", "density", "rng", "global_step", "updates",
                 "elapsed_s")  # fmt: skip


def load_training_checkpoint(path: str | Path, algo: str,
                             map_location: str | torch.device = "cpu") -> dict[str, Any]:  # fmt: skip
    """:func:`load_checkpoint` for ``--resume``: also ``SafenavError`` for a policy-only file, a
    checkpoint of another algorithm, or one that lacks training state."""
    state = load_checkpoint(path, map_location)
    if state.get("policy_only"):
        raise SafenavError(f"{path} is a policy-only checkpoint: it can be evaluated and exported "
                           "but not resumed (it holds no optimiser or replay state)")  # fmt: skip
    if state.get("algo") != algo:
        raise SafenavError(f"{path} holds a {state.get('algo')!r} run, not {algo!r}: this checkpoint "
                           "was not written by this run directory's run")  # fmt: skip
    missing = [k for k in TRAINING_KEYS if k not in state]
    if missing:
        raise SafenavError(f"{path} lacks {missing}: it is not a resumable training checkpoint")
    return state


def restore_agent(agent: torch.nn.Module, state: dict[str, Any], path: str | Path) -> None:
    """Load the agent's weights and optimiser state from ``state``; ``SafenavError`` (one line) if
    they do not fit the agent built from the run's config (another observation layout, network
    size or algorithm variant)."""
    try:
        agent.load_state_dict(state["agent"])
        agent.load_optimizer_state(state["optimizers"])
    except (KeyError, RuntimeError, TypeError, ValueError) as err:
        raise SafenavError(f"{path} does not fit the networks of this run's config.json (another "
                           f"observation layout, network size or algorithm?): "
                           f"{one_line(err, 300)}") from None  # fmt: skip


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


POLICY_KEYS = ("algo", "global_step", "updates", "elapsed_s", "config", "policy")
"""What a policy-only checkpoint keeps of a training checkpoint (:func:`policy_state`)."""


def policy_state(algo: str, global_step: int, updates: int, elapsed_s: float, config: dict[str, Any],
                 meta: dict[str, Any], actor: torch.nn.Module) -> dict[str, Any]:
    """The part of a training checkpoint that a policy-only file keeps (``best.pt``, ``safenav
    export --policy-only``): counters, configs, and the deployable actor with its description."""
    return {"algo": algo, "global_step": global_step, "updates": updates, "elapsed_s": elapsed_s,
            "config": config, "policy": {"meta": meta, "state_dict": actor.state_dict()}}


__all__ = ["FORMAT", "FORMAT_VERSION", "POLICY_KEYS", "TRAINING_KEYS", "load_checkpoint", "load_training_checkpoint",
           "policy_state", "restore_agent", "rng_state", "save_checkpoint", "seed_everything",
           "set_rng_state"]  # fmt: skip
