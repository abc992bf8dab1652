"""SAC baseline (Haarnoja et al. 2018): CSAC with the cost side switched off.

No copy of the algorithm: :func:`train` runs :func:`safenav.algos.csac.train` with
``constrained=False``, which drops the cost critics, their targets, the Lagrange multiplier and
the constraint curriculum. Collisions then only end the episode (SPEC §2); everything else -
networks, learning rates, warm-up, replay, target networks, entropy tuning - is shared.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from safenav.algos import csac
from safenav.algos.csac import CSACConfig
from safenav.common.config import RunConfig


def sac_config(cfg: CSACConfig) -> CSACConfig:
    """``cfg`` without the constraint (``constrained=False``)."""
    return dataclasses.replace(cfg, constrained=False)


def train(run: RunConfig, cfg: CSACConfig, run_dir: Path, resume: bool = False,
          progress: bool = True) -> dict[str, float]:  # fmt: skip
    """Train SAC into ``run_dir``; see :func:`safenav.algos.csac.train`."""
    return csac.train("sac", run, sac_config(cfg), run_dir, resume=resume, progress=progress)


__all__ = ["sac_config", "train"]
