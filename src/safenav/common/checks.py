"""Checks of command-line values, done before any work starts, so that a mistake costs a second
and one line (``safenav: error: ...``), never a traceback or a lost training run.

- numbers: :func:`parse_count` (``1000000``, ``1e6``, ``1_000_000``, ``1M``), :func:`parse_finite`;
  :func:`registry` makes them tyro's parsers of every ``int`` and ``float`` option;
- ranges: :func:`at_least`, :func:`in_range`;
- paths: :func:`check_input_file`, :func:`check_output_file` (also :func:`check_output_dir`);
- devices, ports, memory: :func:`check_device`, :func:`parse_hostport`, :func:`check_memory`.

Exit codes (README, "Exit codes"): a wrong value or path is a :class:`SafenavError` (2); what the
machine cannot do now (no permission, no CUDA, too little memory) a :class:`SafenavRuntimeError` (1).
"""

from __future__ import annotations

import math
import os
import re
from pathlib import Path
from typing import Any

from safenav.errors import SafenavError, SafenavRuntimeError

_SUFFIX = {"k": 10**3, "m": 10**6, "g": 10**9, "b": 10**9}
_COUNT = re.compile(r"^([+-]?[0-9][0-9_]*(?:\.[0-9_]*)?(?:e[+-]?[0-9]+)?)([kmgb]?)$")


def parse_count(text: str) -> int:
    """A whole number written as ``1000000``, ``1_000_000``, ``1e6``, ``1M`` or ``300k``
    (k = 10^3, M = 10^6, G or B = 10^9; case-insensitive). ``ValueError`` for anything else,
    including fractions (``1.5``), NaN and infinity."""
    m = _COUNT.match(text.strip().lower())
    if m is None:
        raise ValueError(f"expected a whole number (1000000, 1e6, 1_000_000 or 1M), got {text!r}")
    number, suffix = m.group(1).replace("_", ""), m.group(2)
    if re.fullmatch(r"[+-]?[0-9]+", number):  # exact, also beyond float precision
        return int(number) * _SUFFIX.get(suffix, 1)
    value = float(number) * _SUFFIX.get(suffix, 1)
    if not math.isfinite(value) or value != int(value):
        raise ValueError(f"expected a whole number, got {text!r}")
    return int(value)


def parse_finite(text: str) -> float:
    """A finite float; ``ValueError`` for NaN and infinity (no option of safenav means them)."""
    value = float(text)
    if not math.isfinite(value):
        raise ValueError(f"expected a finite number, got {text!r}")
    return value


def registry() -> Any:
    """A tyro ``ConstructorRegistry`` that parses every ``int`` option with :func:`parse_count`
    and every ``float`` option with :func:`parse_finite`."""
    from tyro.constructors import ConstructorRegistry, PrimitiveConstructorSpec

    reg = ConstructorRegistry()

    @reg.primitive_rule
    def _numbers(type_info: Any) -> Any:
        if type_info.type is int:
            parse, metavar = parse_count, "INT"
        elif type_info.type is float:
            parse, metavar = parse_finite, "FLOAT"
        else:
            return None
        return PrimitiveConstructorSpec(
            nargs=1, metavar=metavar, instance_from_str=lambda args: parse(args[0]),
            is_instance=lambda x, t=type_info.type: type(x) is t or (t is float and type(x) is int),
            str_from_instance=lambda x: [str(x)],
        )  # fmt: skip

    return reg


# -- ranges ------------------------------------------------------------------------------------


def at_least(flag: str, value: float, low: float, what: str = "") -> None:
    """``SafenavError`` unless ``value >= low``."""
    if not value >= low:
        raise SafenavError(f"{flag} {value}: must be >= {low}{f' ({what})' if what else ''}")


def in_range(flag: str, value: float, low: float, high: float, what: str = "") -> None:
    """``SafenavError`` unless ``low <= value <= high``."""
    if not low <= value <= high:
        raise SafenavError(
            f"{flag} {value}: must lie in [{low}, {high}]{f' ({what})' if what else ''}"
        )


# -- paths -------------------------------------------------------------------------------------


def check_input_file(path: Path, flag: str, what: str = "file", allow_dir: bool = False) -> None:
    """``SafenavError`` unless ``path`` exists (and is a file, unless ``allow_dir``)."""
    path = Path(path)
    if not path.exists():
        raise SafenavError(f"{flag} {path}: no such {what}")
    if path.is_dir() and not allow_dir:
        raise SafenavError(f"{flag} {path} is a directory, not a {what}")


def _nearest_existing(path: Path) -> Path:
    parent = path.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    return parent


def _probe_writable(directory: Path, flag: str, path: Path) -> None:
    """Create and delete a file in ``directory`` (``os.access`` says yes to root on read-only
    mounts)."""
    probe = directory / f".safenav-write-test.{os.getpid()}"
    try:
        probe.touch(exist_ok=False)
        probe.unlink()
    except FileExistsError:
        pass  # a probe of ours from a crash: the directory is writable
    except OSError as err:
        raise SafenavRuntimeError(
            f"{flag} {path}: cannot write in {directory}: {err.strerror or err}"
        ) from None


def check_output_file(path: Path, flag: str, example: str) -> None:
    """Before any work: ``path`` can be written as a file. A directory given as ``path``, a
    parent directory that does not exist or a file where a directory should be is a
    :class:`SafenavError` (fix the path; ``example`` is a file name to suggest), a directory that
    cannot be written a :class:`SafenavRuntimeError`. Nothing is created or changed."""
    path = Path(path)
    if path.is_dir():
        raise SafenavError(f"{flag} {path} is a directory: name a file in it, e.g. "
                           f"{flag} {path / example}")  # fmt: skip
    parent = path.parent
    if not parent.exists():
        blocker = _nearest_existing(path)
        if not blocker.is_dir():
            raise SafenavError(f"{flag} {path}: {blocker} is a file, not a directory")
        raise SafenavError(
            f"{flag} {path}: directory {parent} does not exist (create it: mkdir -p {parent})"
        )
    if not parent.is_dir():
        raise SafenavError(f"{flag} {path}: {parent} is a file, not a directory")
    if path.is_symlink():  # the rename would replace the link, not write where it points
        raise SafenavError(f"{flag} {path} is a symbolic link (to {os.path.realpath(path)}): "
                           "name the file itself, or another path")  # fmt: skip
    if path.exists() and not path.is_file():
        # Outputs are written beside and renamed over the target (common/atomic.py): over
        # /dev/null or a FIFO that would replace the device itself (as root), not write into it.
        raise SafenavError(f"{flag} {path} is not a regular file (a device, FIFO or socket): "
                           f"name a file, e.g. {flag} {example}")  # fmt: skip
    if path.exists() and not os.access(path, os.W_OK):
        raise SafenavRuntimeError(f"{flag} {path}: the file exists and is not writable")
    _probe_writable(parent, flag, path)


def check_output_dir(path: Path, flag: str) -> None:
    """Before any work: directory ``path`` exists and can be written, or can be created (its
    missing parents too). A file in the way is a :class:`SafenavError`, no permission a
    :class:`SafenavRuntimeError`. Nothing is created."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise SafenavError(f"{flag} {path} is a file, not a directory")
    existing = path if path.is_dir() else _nearest_existing(path)
    if not existing.is_dir():
        raise SafenavError(f"{flag} {path}: {existing} is a file, not a directory")
    _probe_writable(existing, flag, path)


# -- devices, ports, memory --------------------------------------------------------------------


def check_device(device: str, flag: str = "--device") -> None:
    """``cpu``, ``cuda``, ``cuda:N`` (or ``mps``) that torch knows and this machine has: an
    unknown name is a :class:`SafenavError`, a device this machine lacks a
    :class:`SafenavRuntimeError`."""
    import torch

    try:
        dev = torch.device(device)
    except (RuntimeError, ValueError, TypeError):
        raise SafenavError(f"{flag} {device!r}: unknown device; use cpu or cuda (cuda:N)") from None
    if dev.type == "cpu":
        return
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise SafenavRuntimeError(f"{flag} {device}: CUDA is not available on this machine "
                                      f"(torch {torch.__version__}): use --device cpu")  # fmt: skip
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise SafenavRuntimeError(f"{flag} {device}: this machine has "
                                      f"{torch.cuda.device_count()} CUDA device(s)")  # fmt: skip
        return
    if dev.type == "mps" and torch.backends.mps.is_available():
        return
    raise SafenavError(f"{flag} {device!r}: safenav runs on cpu or cuda")


def parse_port(flag: str, port: int, allow: tuple[int, ...] = ()) -> int:
    """``SafenavError`` unless ``port`` is a TCP/UDP port number (0-65535) or in ``allow``."""
    if port in allow or 0 <= port <= 65535:
        return port
    raise SafenavError(f"{flag} {port}: a port number lies in 0-65535")


def parse_hostport(text: str, flag: str, default_host: str = "127.0.0.1") -> tuple[str, int]:
    """``"host:port"``, ``":port"``, ``"port"`` or ``"scheme://host:port"`` -> ``(host, port)``;
    ``SafenavError`` naming ``flag`` for anything else."""
    rest = text.split("://", 1)[-1]
    host, _, port = rest.rpartition(":")
    try:
        number = int(port)
    except ValueError:
        raise SafenavError(f"{flag} {text!r}: expected HOST:PORT, e.g. 127.0.0.1:14540") from None
    if not 0 <= number <= 65535:
        raise SafenavError(f"{flag} {text}: port {number} is outside 0-65535")
    return host or default_host, number


def available_memory() -> int | None:
    """Bytes of memory available to a new allocation (Linux MemAvailable), or None if unknown."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def fmt_bytes(n: float) -> str:
    for unit in ("B", "KB", "MB", "GB", "TB", "PB"):
        if abs(n) < 1000 or unit == "PB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1000
    return f"{n:.1f} PB"  # pragma: no cover


def check_memory(need: float, what: str, fix: str, available: int | None = None) -> None:
    """``SafenavRuntimeError`` if ``need`` bytes exceed the memory this machine has available."""
    have = available_memory() if available is None else available
    if have is not None and need > have:
        raise SafenavRuntimeError(f"{what} needs about {fmt_bytes(need)} of memory; this machine "
                                  f"has {fmt_bytes(have)} available: {fix}")  # fmt: skip


__all__ = ["at_least", "available_memory", "check_device", "check_input_file", "check_memory",
           "check_output_dir", "check_output_file", "fmt_bytes", "in_range", "parse_count",
           "parse_finite", "parse_hostport", "parse_port", "registry"]  # fmt: skip
