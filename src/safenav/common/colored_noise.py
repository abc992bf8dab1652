"""Colored-noise exploration for the SAC family (``--csac.action-noise-beta``; beyond the paper).

Eberhard et al., "Pink Noise Is All You Need: Colored Noise Exploration in Deep Reinforcement
Learning", ICLR 2023: in the rollouts, the standard-normal sample ``eps`` of the reparameterised
action ``a = tanh(mu + sigma * eps)`` is replaced by a Gaussian sequence with power spectrum
``1 / f^beta`` per env and per action dimension (``beta`` 0 = white = SAC as published, 1 =
pink, 2 = red / Brownian), one sequence as long as the episode horizon, started anew at each
episode's end. The updates (log-probabilities, actor loss) keep white noise: SAC is off-policy.

:class:`ColoredNoise` holds the sequences and an index per env. The sequences are generated
lazily, at the first :meth:`~ColoredNoise.sample` after an env's episode ended (or its sequence
ran out), by :func:`colorednoise.powerlaw_psd_gaussian` seeded from torch's global RNG: a run is
reproducible from its seed, and nothing is drawn during the warm-up.
"""

from __future__ import annotations

import math

import numpy as np
import torch


class ColoredNoise:
    """``num_envs`` independent colored-noise sequences of shape ``(action_dim, horizon)``, each
    Gaussian with power spectrum ``1 / f^beta``; see the module docstring. Unit variance as
    ``colorednoise`` (and the paper's code) normalise it, over the nonzero frequencies: the
    zero-frequency term adds about 7 % at beta 1 and 30 % at beta 2 (tests/test_colored_noise.py)."""

    def __init__(self, beta: float, num_envs: int, action_dim: int, horizon: int,
                 device: str | torch.device = "cpu") -> None:  # fmt: skip
        if not (math.isfinite(beta) and 0.0 <= beta <= 2.0):
            raise ValueError(f"beta={beta} must be a finite number in [0, 2]")
        if num_envs < 1 or action_dim < 1 or horizon < 2:
            raise ValueError("num_envs >= 1, action_dim >= 1 and horizon >= 2 are required")
        self.beta, self.horizon, self.device = float(beta), int(horizon), torch.device(device)
        # on the CPU; each step moves its (num_envs, action_dim) slice to the device
        self.noise = torch.zeros(num_envs, action_dim, self.horizon)
        self.index = np.full(num_envs, self.horizon, dtype=np.int64)  # horizon = to be generated

    def reset(self, mask: torch.Tensor | np.ndarray | None = None) -> None:
        """Start new sequences for the envs in ``mask`` (bool, ``(num_envs,)``; None = all): the
        episodes that ended. They are generated at the next :meth:`sample`."""
        if mask is None:
            self.index[:] = self.horizon
        else:
            if isinstance(mask, torch.Tensor):
                mask = mask.detach().cpu().numpy()
            self.index[np.asarray(mask, dtype=bool)] = self.horizon

    def sample(self) -> torch.Tensor:
        """The next noise of every env, ``(num_envs, action_dim)`` float32 on the device; envs
        whose sequence ended (or was reset) get a new one first."""
        stale = np.flatnonzero(self.index >= self.horizon)
        if len(stale):
            from colorednoise import powerlaw_psd_gaussian

            seed = int(torch.randint(0, 2**62, (1,)))  # torch's RNG: reproducible with the run seed
            shape = (len(stale), *self.noise.shape[1:])
            rng = np.random.default_rng(seed)
            fresh = powerlaw_psd_gaussian(self.beta, shape, random_state=rng)
            self.noise[torch.from_numpy(stale)] = torch.from_numpy(fresh).float()
            self.index[stale] = 0
        eps = self.noise[torch.arange(len(self.index)), :, torch.from_numpy(self.index)]
        self.index += 1
        return eps.to(self.device)


__all__ = ["ColoredNoise"]
