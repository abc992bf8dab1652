"""The algorithms, one file each, read top to bottom: CSAC, the paper's method, with its variants
SAC and SAC-Lag (:mod:`safenav.algos.csac`; the switches of :mod:`safenav.algos.sac` and
:mod:`safenav.algos.sac_lag`), PPO and PPO-Lag (:mod:`safenav.algos.ppo`); their pure losses
(:mod:`safenav.algos.losses`, :mod:`safenav.algos.ppo_losses`); the loader of trained policies
(:mod:`safenav.algos.policy`) and weight averaging (:mod:`safenav.algos.averaging`).

An algorithm file holds the networks and the update rule (``CSAC``, ``PPO``) and the learner
(``CSACLearner``: replay; ``PPOLearner``: rollouts) that the one training loop,
:mod:`safenav.training`, calls. Nothing here imports :mod:`safenav.training`."""
