"""Run-directory logging shared by the trainers: ``progress.csv``, TensorBoard, ``events.jsonl``.

- ``progress.csv``: one row per log interval, a fixed header (``global_step`` first); a metric
  without a value in that interval is an empty cell. Flushed at every row, so plots and sweeps can
  read a live run. On resume, rows logged after the checkpoint's step are dropped (they will be
  logged again) and a header that gained columns is rewritten in place.
- ``tb/``: the same scalars as TensorBoard events (``purge_step`` on resume).
- ``events.jsonl``: discrete events (curriculum changes, evaluations, resumes), one JSON a line.
"""

from __future__ import annotations

import contextlib
import csv
import errno
import json
import math
import os
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

from safenav.errors import SafenavError, SafenavRuntimeError

RUN_FILES = ("config.json", "progress.csv", "checkpoint.pt", "events.jsonl")


def prepare_run_dir(run_dir: Path, resume: bool, overwrite: bool) -> None:
    """Create ``run_dir``; refuse one that already holds a run unless resuming or overwriting
    (``overwrite`` deletes the previous run's files, nothing else), and one that cannot be
    written (``SafenavError`` before any training, not an ``OSError`` at the first log row)."""
    run_dir = Path(run_dir)
    held = [f for f in RUN_FILES if (run_dir / f).exists()] + (
        ["tb/"] if (run_dir / "tb").is_dir() else []
    )
    if resume:
        if not (run_dir / "checkpoint.pt").exists():
            raise SafenavError(f"--resume {run_dir}: no checkpoint.pt there to resume from (the run "
                               "stopped before its first checkpoint): start it again with "
                               "--overwrite")  # fmt: skip
        _check_writable(run_dir)
        return
    if held and not overwrite and has_trained(run_dir):
        fix = ("pass --resume to continue it or --overwrite to replace it"
               if (run_dir / "checkpoint.pt").exists() else
               "it stopped before its first checkpoint: pass --overwrite to replace it")  # fmt: skip
        raise SafenavError(f"--run-dir {run_dir} already holds a run ({', '.join(held)}): {fix}")
    # A run that never trained (it failed before its first progress row, e.g. on a bad env) left
    # only its config: replace it, so that the retry with the same --run-dir is not refused.
    if held:
        import shutil

        for f in RUN_FILES:
            (run_dir / f).unlink(missing_ok=True)
        shutil.rmtree(run_dir / "tb", ignore_errors=True)
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
    except OSError as err:  # a file in the way (usage), a read-only file system, no permission
        kind = (
            SafenavRuntimeError
            if err.errno in (errno.EACCES, errno.EPERM, errno.EROFS)
            else SafenavError
        )
        raise kind(
            f"--run-dir {run_dir}: cannot create run directory: {err.strerror or err}"
        ) from None
    _check_writable(run_dir)


LOCK_FILE = ".safenav.lock"


def _open_lock(run_dir: Path) -> int | None:
    """The lock file's descriptor (created with the directory where missing), or None where no
    lock can be had: no ``fcntl`` (Windows), or a directory that cannot be made (then
    :func:`prepare_run_dir` says why). Read-only where the file is another user's."""
    try:
        import fcntl  # noqa: F401
    except ImportError:
        return None
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
        return os.open(run_dir / LOCK_FILE, os.O_RDWR | os.O_CREAT, 0o644)
    except PermissionError:
        with contextlib.suppress(OSError):
            return os.open(run_dir / LOCK_FILE, os.O_RDONLY)  # flock works on it too
    except OSError:
        pass
    return None


def _try_flock(fd: int) -> bool | None:
    """True: locked; False: another process holds it; None: this file system has no flock."""
    import fcntl

    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        return True
    except OSError as err:
        if err.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
            return False
        return None  # ENOLCK, EOPNOTSUPP, ENOSYS: NFS without lockd, some FUSE/Lustre mounts


class RunDirLock:
    """What :func:`run_dir_lock` yields: set ``accepted`` once the command passed its refusals,
    so that a failure after it (a diverged run) keeps the lock file."""

    accepted = False


@contextlib.contextmanager
def run_dir_lock(run_dir: Path) -> Iterator[RunDirLock]:
    """Hold ``run_dir`` for this process: a second ``safenav train`` on the same directory (a
    rerun while the first still trains, e.g. an orphan of a stopped ``safenav bench``) is refused
    with one line instead of both writing the same checkpoint and logs.

    An advisory ``flock`` on ``RUN_DIR/.safenav.lock``, which holds the owner's ``pid@host``; the
    OS releases it when the process ends, however it ends, so a killed run never leaves a stale
    lock. Runs without a lock where none can be had (:func:`_open_lock`, a file system without
    flock). A command refused before ``accepted`` leaves no lock file (nor a directory it made)
    behind."""
    import socket

    run_dir = Path(run_dir)
    lock = run_dir / LOCK_FILE
    made_dir, made_lock = not run_dir.exists(), not lock.exists()
    fd = _open_lock(run_dir)
    locked = _try_flock(fd) if fd is not None else None
    try:
        if locked is False:
            owner = os.pread(fd, 256, 0).decode(errors="replace").strip()
            pid, _, host = owner.partition("@")
            here = host == socket.gethostname() and pid.isdigit()
            where = f"pid {pid} on {host}" if owner else "its pid not yet written"
            stop = f"stop it (kill -TERM {pid} checkpoints it)" if here else "stop it"
            raise SafenavError(f"--run-dir {run_dir} is in use by another safenav process "
                               f"({where}): wait for it to finish, or {stop} and then --resume")  # fmt: skip
        if locked:
            with contextlib.suppress(OSError):  # read-only: the lock holds, the name is unknown
                os.ftruncate(fd, 0)
                os.pwrite(fd, f"{os.getpid()}@{socket.gethostname()}\n".encode(), 0)
        state, failed = RunDirLock(), True
        try:
            yield state
            failed = False
        finally:
            # Refused before anything was written: leave the directory as it was found.
            if failed and locked and not state.accepted:
                if made_lock:
                    lock.unlink(missing_ok=True)
                if made_dir:
                    with contextlib.suppress(OSError):
                        run_dir.rmdir()  # only if empty
    finally:
        if fd is not None:
            os.close(fd)  # releases the lock


def wait_for_run_dir(run_dir: Path, timeout_s: float = 300.0) -> bool:
    """Wait until no process holds ``run_dir``'s lock (a trainer that is still writing its
    checkpoint after a SIGTERM); True when free (or never locked), False after ``timeout_s``."""
    lock = Path(run_dir) / LOCK_FILE
    if not lock.exists():
        return True
    try:
        fd = os.open(lock, os.O_RDONLY)
    except OSError:
        return True
    try:
        deadline = time.monotonic() + timeout_s
        while _try_flock(fd) is False:
            if time.monotonic() > deadline:
                return False
            time.sleep(0.5)
        return True
    finally:
        os.close(fd)


def has_trained(run_dir: Path) -> bool:
    """True if ``run_dir`` holds a checkpoint or a ``progress.csv`` with at least one row."""
    run_dir = Path(run_dir)
    if (run_dir / "checkpoint.pt").exists():
        return True
    try:
        with (run_dir / "progress.csv").open() as f:
            return len(f.readlines(1 << 16)) > 1  # a header and a row
    except OSError:
        return False


def _check_writable(run_dir: Path) -> None:
    """Create and delete a file in ``run_dir`` (``os.access`` says yes to root on read-only
    mounts and no to some ACL'd directories that do accept writes)."""
    probe = run_dir / f".write-test.{os.getpid()}"
    try:
        probe.touch()
        probe.unlink()
    except OSError as err:
        raise SafenavRuntimeError(
            f"--run-dir {run_dir}: the run directory is not writable: {err.strerror or err}"
        ) from None


def write_json_atomic(path: Path, obj: Any) -> None:
    """``config.json`` and the like: :func:`safenav.common.jsonout.write_json` (atomic, fsynced,
    strict JSON), anything JSON has no type for written as its ``str``."""
    from safenav.common.jsonout import write_json

    write_json(path, obj, default=str)


class RunLogger:
    """Writes metrics rows to CSV and TensorBoard (see module docstring)."""

    def __init__(self, run_dir: Path, columns: Sequence[str], tensorboard: bool = True,
                 resume_step: int | None = None) -> None:  # fmt: skip
        self.run_dir = Path(run_dir)
        self.columns = ["global_step", *[c for c in columns if c != "global_step"]]
        self.csv_path = self.run_dir / "progress.csv"
        rows: list[dict[str, str]] = []
        if resume_step is not None and self.csv_path.exists():
            with self.csv_path.open(newline="") as f:
                reader = csv.DictReader(f)
                old = reader.fieldnames or []
                rows = [
                    r
                    for r in reader
                    if r.get("global_step") and float(r["global_step"]) <= resume_step
                ]
            self.columns += [c for c in old if c not in self.columns]
        self._file = self.csv_path.open("w", newline="")
        self._writer = csv.DictWriter(self._file, fieldnames=self.columns, extrasaction="ignore")
        self._writer.writeheader()
        for r in rows:
            self._writer.writerow(r)
        self._file.flush()
        self._events = (self.run_dir / "events.jsonl").open("a")
        self.tb = None
        if tensorboard:
            from torch.utils.tensorboard import SummaryWriter

            self.tb = SummaryWriter(str(self.run_dir / "tb"), purge_step=resume_step)

    def log(self, step: int, metrics: dict[str, float]) -> None:
        row = {"global_step": int(step)}
        for k, v in metrics.items():
            if k not in self.columns:
                raise KeyError(f"metric {k!r} is not a declared progress.csv column")
            if v is None or (isinstance(v, float) and math.isnan(v)):
                continue
            row[k] = float(v)
            if self.tb is not None:
                self.tb.add_scalar(k, float(v), int(step))
        self._writer.writerow(
            {k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in row.items()}
        )
        self._file.flush()

    def event(self, step: int, kind: str, **data: Any) -> None:
        rec = {"global_step": int(step), "event": kind, "time": time.time(), **data}
        self._events.write(json.dumps(rec, default=str) + "\n")
        self._events.flush()

    def close(self) -> None:
        self._file.close()
        self._events.close()
        if self.tb is not None:
            self.tb.close()


__all__ = ["RUN_FILES", "RunLogger", "prepare_run_dir", "write_json_atomic"]
