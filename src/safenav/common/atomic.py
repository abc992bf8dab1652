"""The one way safenav writes a file that must never be half-written: checkpoints, every JSON
file (``config.json``, ``final.json``, ``eval --json``, sidecars, results, benchmarks) and the
exported ONNX model.

:func:`atomic_write` writes into a temporary file ``.NAME.PID.tmp`` next to the target, flushes
it, ``fsync``-s it, moves it over the target with ``os.replace`` (atomic on POSIX) and then
``fsync``-s the directory, so that the rename itself survives a power cut: afterwards the target
holds either the old content or the new, whole, on disk. A writer that fails removes its
temporary file; the temporary files of writers that were killed (SIGKILL, a crash) are removed by
the next successful write of the same target.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any


def temp_path(path: Path) -> Path:
    """``.NAME.PID.tmp`` next to ``path``: hidden, and this process's own."""
    return path.with_name(f".{path.name}.{os.getpid()}.tmp")


@contextlib.contextmanager
def atomic_write(path: str | Path, mode: str = "wb", **open_kwargs: Any) -> Iterator[IO[Any]]:
    """``with atomic_write(path) as f: f.write(...)``: ``path`` is replaced by what was written
    when the block ends without an exception, and left as it was otherwise."""
    path = Path(path)
    tmp = temp_path(path)
    try:
        with tmp.open(mode, **open_kwargs) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
        fsync_dir(path.parent)
    finally:
        tmp.unlink(missing_ok=True)
    remove_stale_temps(path)


def write_text_atomic(path: str | Path, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` through :func:`atomic_write`."""
    with atomic_write(path, "w", encoding="utf-8") as f:
        f.write(text)


def replace_synced(tmp: str | Path, path: str | Path) -> None:
    """Move the finished file ``tmp`` (written by a library that takes a file name, such as an
    ONNX exporter) over ``path`` as :func:`atomic_write` would: ``fsync`` it, rename, ``fsync``
    the directory."""
    fd = os.open(tmp, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
    os.replace(tmp, path)
    fsync_dir(Path(path).parent)


def fsync_dir(directory: str | Path) -> None:
    """``fsync`` a directory (its entries: a rename into it) where the platform allows it; one
    system call (~0.1 ms on a local disk)."""
    try:
        fd = os.open(directory, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    except OSError:
        return  # e.g. Windows, where directories cannot be opened
    try:
        os.fsync(fd)
    except OSError:
        pass  # some file systems (and Windows) refuse fsync on a directory: nothing to do
    finally:
        os.close(fd)


def remove_stale_temps(path: Path) -> None:
    """Delete the ``.NAME.PID.tmp`` files of ``path``'s writers that no longer run (SIGKILLed
    mid-write: with ``--save-buffer`` a checkpoint's is as large as the replay buffer)."""
    for tmp in path.parent.glob(f".{path.name}.*.tmp"):
        try:
            os.kill(int(tmp.name.split(".")[-2]), 0)  # signal 0: does the process exist?
        except (ValueError, OverflowError):
            continue  # not one of ours
        except ProcessLookupError:
            tmp.unlink(missing_ok=True)
        except (PermissionError, OSError):
            pass  # another user's live process (or a PID this platform cannot probe)


__all__ = ["atomic_write", "fsync_dir", "remove_stale_temps", "replace_synced", "temp_path",
           "write_text_atomic"]  # fmt: skip
