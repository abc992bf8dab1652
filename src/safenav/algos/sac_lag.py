"""SAC-Lag as OmniSafe does it: CSAC's code path with OmniSafe's Lagrangian mechanics.

No copy of the algorithm: ``safenav.training.train("sac_lag", ...)`` trains CSAC's code with
:func:`sac_lag_config`, which switches three things relative to CSAC (everything else - reward
critics, entropy tuning, warm-up, replay, target networks, the constraint curriculum on ``d`` -
is shared, so ``csac`` vs ``sac_lag`` isolates the Lagrangian design):

- **one** cost critic ``Q_C`` (``num_cost_critics=1``): no min/mean choice to make;
- lambda driven by the **mean episode cost** ``J_c`` of the episodes that ended in the last
  ``lambda_every`` env steps (or, with ``lambda_window`` N, of the last N episodes, as OmniSafe's
  logger window does), against the episode budget ``d`` (``lambda_from="episode_cost"``):
  ``lambda <- max(0, lambda + Adam step on (J_c - d))`` at ``episode_lambda_lr``, instead of Eq. 11
  on ``E[Q_C]`` at every gradient update;
- the actor loss divided by ``1 + lambda`` (``scale_actor_loss``):
  ``L(phi) = E[alpha log pi - min_j Q_R_j + lambda Q_C] / (1 + lambda)``.

OmniSafe's ``SACLag._update`` reads ``J_c`` back from its logger; here the learner passes it to the
:class:`~safenav.common.lagrange.Lagrange` object directly
(:meth:`safenav.algos.csac.CSACLearner.update`).
"""

from __future__ import annotations

import dataclasses

from safenav.algos.config import CSACConfig


def sac_lag_config(cfg: CSACConfig) -> CSACConfig:
    """``cfg`` with OmniSafe's SAC-Lag switches (see module docstring)."""
    return dataclasses.replace(cfg, constrained=True, num_cost_critics=1, lambda_from="episode_cost",
                               scale_actor_loss=True)  # fmt: skip


__all__ = ["sac_lag_config"]
