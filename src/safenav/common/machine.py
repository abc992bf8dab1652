"""One line that names the machine a result was measured on (for trial and result files)."""

from __future__ import annotations

import contextlib
import os
import platform
from pathlib import Path


def machine_description() -> str:
    """CPU model, core count, memory, OS, Python, torch (and GPU) of this machine, in one line."""
    cpu = platform.processor() or platform.machine()
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    mem = ""
    with contextlib.suppress(OSError, ValueError, IndexError):
        kib = int(Path("/proc/meminfo").read_text().split("\n")[0].split()[1])
        mem = f", {kib / 2**20:.0f} GiB RAM"
    parts = [f"{cpu}, {os.cpu_count()} CPUs{mem}", f"{platform.system()} {platform.release()}",
             f"Python {platform.python_version()}"]  # fmt: skip
    with contextlib.suppress(ImportError):
        import torch

        parts.append(f"torch {torch.__version__}")
        if torch.cuda.is_available():
            parts.append(torch.cuda.get_device_name(0))
    return "; ".join(parts)


__all__ = ["machine_description"]
