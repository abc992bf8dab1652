"""safenav: safe UAV navigation with constrained reinforcement learning.

The parts, as the folders show them:

* :mod:`safenav.envs` - ``SafeNav-v1``, a batched CMDP simulator (world, sensors, dynamics).
* :mod:`safenav.nn` - the shared feature extractor and the actor/critic heads.
* :mod:`safenav.algos` - CSAC (the paper's method), SAC, PPO and the Lagrangian family.
* :mod:`safenav.common` - replay buffer, Lagrange multiplier, curricula, logging, checkpoints.
* :mod:`safenav.experiments` - the evaluation protocol, multi-seed sweeps on Ray, plots.
* :mod:`safenav.deploy` - ONNX export, the onboard runtime, PX4 over MAVLink, the safety shield.

Importing :mod:`safenav` registers ``SafeNav-v1`` for ``gymnasium.make`` and
``gymnasium.make_vec`` (or use the id ``"safenav:SafeNav-v1"`` without importing), and the
velocity-constrained ``SafetyHopperVelocity-v5`` and ``SafetyHalfCheetahVelocity-v5``
(:mod:`safenav.common.costs`).
"""

import gymnasium

from safenav.errors import SafenavError

__version__ = "0.1.0"

ENV_ID = "SafeNav-v1"
"""The simulator's Gymnasium id. (SafeNav-v0, the open arena, was removed: see the env's Version
History; gymnasium.make("SafeNav-v0") names v1 in its error.)"""

if ENV_ID not in gymnasium.registry:
    gymnasium.register(
        id=ENV_ID,
        entry_point="safenav.envs.nav:SafeNavEnv",
        vector_entry_point="safenav.envs.nav:SafeNavVectorEnv",
        # The env truncates at its own time limit (EnvConfig.max_episode_seconds).
        max_episode_steps=None,
    )

# Safety-Gymnasium's velocity tasks on Gymnasium's MuJoCo v5 models (safenav.common.costs).
from safenav.common.costs import register_velocity_tasks  # noqa: E402

register_velocity_tasks()

__all__ = ["ENV_ID", "SafenavError", "__version__"]
