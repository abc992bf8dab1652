"""Checkpoints: atomic writes, loading without pickle, friendly errors, and RNG state capture.

A checkpoint is one ``torch.save`` dict with ``format`` and ``format_version`` keys, written by
:func:`~safenav.common.atomic.atomic_write` (a temporary file, ``fsync``, ``os.replace``, ``fsync``
of the directory): a crash leaves either the old or the new checkpoint, never half of one.

Loading never unpickles: :func:`load_checkpoint` reads with ``torch.load(weights_only=True)`` and
torch's default allow-list alone (tensors, numbers, strings, ``None``, lists, tuples, dicts), so a
crafted file cannot run code. :func:`save_checkpoint` writes nothing else (:func:`safe_state`:
NumPy arrays become tensors, NumPy scalars Python numbers, anything else is refused before
writing). A file that needs more - a checkpoint of an older safenav, whose NumPy RNG state was an
array, or a malicious one - is refused with one line naming ``safenav convert``
(:func:`convert_checkpoint`), which rewrites an older safenav's checkpoint with NumPy arrays
allowed as well and still no code run (``--trust-pickle``: full pickle, for a file one trusts).
"""

from __future__ import annotations

import pickle
import random
import re
import shlex
import warnings
import zipfile
from collections import OrderedDict
from pathlib import Path
from typing import Any

import numpy as np
import torch

from safenav.common.atomic import atomic_write
from safenav.errors import SafenavError, SafenavRuntimeError, one_line

FORMAT = "safenav-checkpoint"
FORMAT_VERSION = 1


def save_checkpoint(path: str | Path, state: dict[str, Any]) -> None:
    """Write ``state`` (plus format tags) to ``path`` atomically, in a form that
    :func:`load_checkpoint` reads without pickle (``TypeError`` before writing for an object
    that has none: a bug)."""
    safe = safe_state({"format": FORMAT, "format_version": FORMAT_VERSION, **state})
    with atomic_write(path) as f:
        torch.save(safe, f)


_PLAIN = (type(None), bool, int, float, complex, str, bytes)
_TORCH = (torch.Tensor, torch.Size, torch.dtype, torch.device)


def safe_state(obj: Any, where: str = "state") -> Any:
    """``obj`` as ``torch.load(weights_only=True)`` reads it back with torch's default
    allow-list: dicts (and ``OrderedDict``), lists and tuples of tensors, ``torch.Size``/
    ``dtype``/``device`` and plain Python values, as they are; NumPy scalars become Python
    numbers and NumPy arrays tensors (``uint16``/``uint32`` as ``int64``, e.g. NumPy's RNG key).
    ``TypeError`` naming the entry (``where``) for anything else."""
    if type(obj) in _PLAIN or isinstance(obj, _TORCH):
        return obj
    if type(obj) in (dict, OrderedDict):
        return type(obj)((safe_state(k, f"{where} key"), safe_state(v, f"{where}[{k!r}]"))
                         for k, v in obj.items())  # fmt: skip
    if type(obj) in (list, tuple):
        return type(obj)(safe_state(v, f"{where}[{i}]") for i, v in enumerate(obj))
    if isinstance(obj, np.generic):
        return safe_state(obj.item(), where)
    if isinstance(obj, np.ndarray) and obj.dtype.kind in "biufc":
        if obj.dtype in (np.uint16, np.uint32):  # torch's own uint16/32 are barely supported
            obj = obj.astype(np.int64)
        return torch.from_numpy(np.array(obj, copy=True))
    raise TypeError(f"{where}: a {type(obj).__module__}.{type(obj).__qualname__} cannot go into "
                    "a checkpoint that loads without pickle (use tensors, numbers, strings, None, "
                    "lists, tuples and dicts)")  # fmt: skip


def _checkpoint_file(path: str | Path) -> Path:
    path = Path(path)
    if path.is_dir():
        path = path / "checkpoint.pt"
    if not path.exists():
        raise SafenavError(f"checkpoint {path} not found")
    return path


def load_checkpoint(path: str | Path, map_location: str | torch.device = "cpu") -> dict[str, Any]:
    """Read a checkpoint without unpickling; ``SafenavError`` naming the problem if it is missing,
    unreadable, needs pickle (:class:`UnsafeCheckpointError`), is not a safenav checkpoint, or is
    of another format version."""
    path = _checkpoint_file(path)
    state = _read(path, map_location)
    _check_tags(state, path)
    return state


class UnsafeCheckpointError(SafenavError):
    """A checkpoint that needs pickle beyond torch's allow-list to load: refused unread (exit
    2); :attr:`needs` names the first global it asked for (``None``: another weights-only
    refusal)."""

    def __init__(self, path: Path, needs: str | None) -> None:
        self.path, self.needs = path, needs
        what = f"it asks for {needs}" if needs else "it is not plain tensors and values"
        super().__init__(
            f"checkpoint {path} needs pickle to load ({what}) and is refused unread, since "
            f"unpickling can run any code: a checkpoint of an older safenav (NumPy RNG state) is "
            f"converted once, without running code, by: safenav convert {shlex.quote(str(path))}"
        )


def _read(path: Path, map_location: str | torch.device = "cpu", *, unsafe: bool = False) -> Any:
    """``torch.load`` of ``path`` (weights only unless ``unsafe``) with its errors as one line."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # torch's notes on pickle protocols and weights_only
            return torch.load(path, map_location=map_location, weights_only=not unsafe)
    except RuntimeError as err:
        if "CUDA" not in str(err) or not str(map_location).startswith("cuda"):
            raise _unreadable(path, err) from None
        # a CUDA device asked for on a machine without one: not the file's fault
        raise SafenavRuntimeError(f"cannot load {path} onto {map_location}: CUDA is not "
                                  "available on this machine; use --device cpu") from None  # fmt: skip
    except pickle.UnpicklingError as err:
        text = str(err)
        if not unsafe and "Weights only load failed" in text:
            needs = re.search(r"GLOBAL ([\w.]+)|but got <class '([\w.]+)'>", text)
            if needs is not None:
                raise UnsafeCheckpointError(path, needs.group(1) or needs.group(2)) from None
            operand = re.search(r"Unsupported operand \d+", text)
            if operand is not None:  # not a pickle torch.save writes: garbage or a bare pickle
                raise _unreadable(path, pickle.UnpicklingError(operand.group(0))) from None
            raise UnsafeCheckpointError(path, None) from None
        raise _unreadable(path, err) from None
    except (EOFError, zipfile.BadZipFile, ValueError, OSError) as err:
        raise _unreadable(path, err) from None
    except Exception as err:  # noqa: BLE001 -- the unpickler on bytes no pickler wrote (IndexError...)
        raise _unreadable(path, err) from None


def _check_tags(state: Any, path: Path) -> None:
    if not isinstance(state, dict) or state.get("format") != FORMAT:
        raise SafenavError(f"{path} is not a safenav training checkpoint (no '{FORMAT}' tag)")
    version = state.get("format_version")
    if version != FORMAT_VERSION:
        newer = isinstance(version, int) and version > FORMAT_VERSION
        fix = ("it was written by a newer safenav: upgrade safenav to read it" if newer
               else "retrain, or use the safenav that wrote it")  # fmt: skip
        raise SafenavError(f"{path} has checkpoint format version {version}; this safenav reads "
                           f"version {FORMAT_VERSION}: {fix}")  # fmt: skip


def _unreadable(path: Path, err: BaseException) -> SafenavError:
    # torch's own text goes on for lines ("This is an internal miniz error..."): keep its start
    reason = one_line(str(err).split(". ")[0], 160)
    return SafenavError(f"checkpoint {path} is corrupt or truncated, or not a torch file "
                        f"({type(err).__name__}: {reason})")  # fmt: skip


def _numpy_globals() -> list[Any]:
    """What a NumPy array or scalar of numbers in a pickle asks for, under NumPy 1's and 2's
    module names: ``ndarray``, ``dtype`` and its numeric subclasses, and the two constructors,
    which build arrays and scalars from bytes and run no code of the file's choosing."""
    reconstruct = np.ndarray.__reduce__(np.zeros(1))[0]
    scalar = np.float64(0).__reduce__()[0]
    named = [(f, f"numpy.{core}.multiarray.{f.__name__}") for f in (reconstruct, scalar)
             for core in ("core", "_core")]  # fmt: skip
    dtypes = {type(np.dtype(code)) for code in "?bBhHiIlLqQefdgFDG"}  # bool, ints, floats, complex
    return [np.ndarray, np.dtype, *dtypes, *named]


def convert_checkpoint(src: str | Path, dst: str | Path | None = None, *,
                       trust_pickle: bool = False) -> tuple[Path, Path, str]:  # fmt: skip
    """Rewrite checkpoint ``src`` (a file, or a run directory's ``checkpoint.pt``) as
    :func:`save_checkpoint` writes today, into ``dst`` (default: ``src`` itself, replaced
    atomically). ``src`` is read with NumPy arrays and scalars allowed besides tensors - all an
    older safenav stored - and still no code run; a file that needs more is refused
    (:class:`UnsafeCheckpointError`) unless ``trust_pickle``, which unpickles it in full (only
    for a file one trusts: it runs whatever code the file holds). Returns ``(src, dst, how)``:
    ``how`` is ``"safe"`` (it loaded without pickle already), ``"numpy"`` or ``"pickle"``."""
    path = _checkpoint_file(src)
    out = path if dst is None else Path(dst)
    try:
        state, how = _read(path), "safe"
    except UnsafeCheckpointError:
        try:
            with torch.serialization.safe_globals(_numpy_globals()):
                state, how = _read(path), "numpy"
        except UnsafeCheckpointError as err:
            if not trust_pickle:
                raise SafenavError(
                    f"checkpoint {path} asks for {err.needs or 'objects'} besides tensors and NumPy "
                    "arrays, which no safenav wrote: not converted. Only for a file you trust "
                    "(unpickling runs any code it holds): safenav convert "
                    f"{shlex.quote(str(path))} --trust-pickle"
                ) from None
            state, how = _read(path, unsafe=True), "pickle"
    _check_tags(state, path)
    try:
        safe = safe_state(state)
    except TypeError as err:
        raise SafenavError(f"checkpoint {path} holds what safenav cannot store without pickle "
                           f"({err}): not converted") from None  # fmt: skip
    if how == "safe" and out.resolve() == path.resolve():
        return path, out, how  # nothing to rewrite
    save_checkpoint(out, safe)
    return path, out, how


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
    """Python, NumPy, torch CPU (and CUDA) RNG states, as plain values and tensors (NumPy's key,
    624 ``uint32``, as an ``int64`` tensor)."""
    name, key, pos, has_gauss, cached = np.random.get_state()  # noqa: NPY002 (the global RNG)
    numpy = (str(name), torch.from_numpy(key.astype(np.int64)), int(pos), int(has_gauss), cached)
    state = {
        "python": random.getstate(),
        "numpy": numpy,
        "torch": torch.get_rng_state(),
    }
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict[str, Any]) -> None:
    """Restore what :func:`rng_state` captured (also its older form: NumPy's key as an array)."""
    python = state["python"]
    random.setstate((python[0], tuple(python[1]), python[2]))
    name, key, *rest = state["numpy"]
    key = key.cpu().numpy() if isinstance(key, torch.Tensor) else np.asarray(key)
    np.random.set_state((name, key.astype(np.uint32), *rest))  # noqa: NPY002
    torch.set_rng_state(
        state["torch"].cpu() if isinstance(state["torch"], torch.Tensor) else state["torch"]
    )
    if "cuda" in state and torch.cuda.is_available():
        # a checkpoint loaded onto the GPU (map_location) brings the states there; torch takes
        # them as CPU byte tensors only
        torch.cuda.set_rng_state_all([s.cpu() for s in state["cuda"]])


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed % 2**32)  # noqa: NPY002
    torch.manual_seed(seed)


POLICY_KEYS = ("algo", "global_step", "updates", "elapsed_s", "config", "policy")
"""What a policy-only checkpoint keeps of a training checkpoint (:func:`policy_state`)."""


def policy_state(
    algo: str,
    global_step: int,
    updates: int,
    elapsed_s: float,
    config: dict[str, Any],
    meta: dict[str, Any],
    actor: torch.nn.Module,
) -> dict[str, Any]:
    """The part of a training checkpoint that a policy-only file keeps (``best.pt``, ``safenav
    export --policy-only``): counters, configs, and the deployable actor with its description."""
    return {
        "algo": algo,
        "global_step": global_step,
        "updates": updates,
        "elapsed_s": elapsed_s,
        "config": config,
        "policy": {"meta": meta, "state_dict": actor.state_dict()},
    }


__all__ = ["FORMAT", "FORMAT_VERSION", "POLICY_KEYS", "TRAINING_KEYS", "UnsafeCheckpointError",
           "convert_checkpoint", "load_checkpoint", "load_training_checkpoint", "policy_state",
           "restore_agent", "rng_state", "safe_state", "save_checkpoint", "seed_everything",
           "set_rng_state"]  # fmt: skip
