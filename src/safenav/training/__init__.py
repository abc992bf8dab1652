"""The training skeleton shared by every algorithm: one :class:`~safenav.training.trainer.Trainer`
runs a :class:`~safenav.training.trainer.Learner` (CSAC, SAC, SAC-Lag: ``algos.csac.CSACLearner``;
PPO, PPO-Lag: ``algos.ppo.PPOLearner``) from set-up to the last checkpoint.

- :mod:`safenav.training.trainer` - the loop: envs, curricula, resume, evaluation, progress rows,
  checkpoints; :func:`train` and :func:`write_config`, what ``safenav train`` calls.
- :mod:`safenav.training.evaluation` - periodic evaluation and ``best.pt``.
- :mod:`safenav.training.runs` - episode charts, the final summary, ``config.json``.

It sits above the algorithms: it imports them, they never import it (tests/test_layering.py).
"""

from safenav.training.trainer import LEARNERS, Learner, Trainer, algo_config, train, write_config

__all__ = ["LEARNERS", "Learner", "Trainer", "algo_config", "train", "write_config"]
