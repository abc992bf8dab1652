"""SAC baseline (Haarnoja et al. 2018): CSAC with the cost side switched off.

No copy of the algorithm: ``safenav.training.train("sac", ...)`` trains CSAC's code
(:class:`~safenav.algos.csac.CSAC`, :class:`~safenav.algos.csac.CSACLearner`) with
:func:`sac_config`, ``constrained=False``, which drops the cost critics, their targets, the
Lagrange multiplier and the constraint curriculum. Collisions then only end the episode (SPEC §2);
everything else - networks, learning rates, warm-up, replay, target networks, entropy tuning - is
shared.
"""

from __future__ import annotations

import dataclasses

from safenav.algos.config import CSACConfig


def sac_config(cfg: CSACConfig) -> CSACConfig:
    """``cfg`` without the constraint (``constrained=False``)."""
    return dataclasses.replace(cfg, constrained=False)


__all__ = ["sac_config"]
