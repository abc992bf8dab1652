"""Load a trained policy from a checkpoint: ``load_policy(path) -> Policy``.

``Policy(obs)`` maps a batch of observations (a dict of tensors, or one tensor for ``Box``
observations) to deterministic actions in ``[-1, 1]`` as a ``(B, A)`` tensor (SAC's ``tanh(mean)``,
PPO's Beta mean or clipped Gaussian mean); a policy of a ``Discrete(n)`` task (PPO,
``meta["num_actions"]``) gives the most probable action's index ``0 .. n-1`` as a float ``(B, 1)``.
:func:`safenav.envs.vector.policy_action_to_env` turns either into what the env takes.
``Policy.sample(obs)`` draws a SAC-family policy's actions as training drew them instead.
``Policy.actor`` is the underlying :class:`~safenav.nn.networks.DeterministicActor`, an
``nn.Module`` taking the observation tensors positionally (``state, lidar, dynamic`` for SafeNav)
- what ``safenav export`` traces to ONNX. ``Policy.meta`` says what the policy is: algorithm, env
id, env configuration, observation shapes, network sizes, training step. A policy trained with
``--normalize-obs`` takes the env's own observations too: its actor is a
:class:`~safenav.common.normalize.NormalizedActor`, the observation statistics of its training
in front of the network (``meta["obs_normalization"]``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from safenav.common.checkpoint import load_checkpoint
from safenav.common.normalize import NormalizedActor, ObsNormalizer
from safenav.envs.config import observation_shapes
from safenav.errors import SafenavError, one_line
from safenav.nn.config import NetConfig
from safenav.nn.networks import (
    Actor,
    DeterministicActor,
    input_order,
    is_nav_layout,
    make_extractor,
    squashed_gaussian,
)

POLICY_FORMAT_VERSION = 1


class Policy:
    """A deterministic policy; see the module docstring."""

    def __init__(
        self, actor: DeterministicActor, meta: dict[str, Any], device: str | torch.device = "cpu"
    ) -> None:
        self.actor = actor.eval()
        self.meta = meta
        self.device = torch.device(device)
        self.obs_shapes = {k: tuple(v) for k, v in meta["obs_shapes"].items()}

    def env_config(self):
        """The :class:`~safenav.envs.config.EnvConfig` the policy was trained on (full density), or
        None for a non-SafeNav env."""
        from safenav.common.config import from_dict
        from safenav.envs.config import EnvConfig

        data = self.meta.get("env_config")
        return from_dict(EnvConfig, data) if data is not None else None

    def _prepare(self, obs) -> list[torch.Tensor]:
        if not isinstance(obs, dict):
            if set(self.obs_shapes) != {"obs"}:
                raise SafenavError(
                    f"this policy takes a dict observation with keys {sorted(self.obs_shapes)}"
                )
            obs = {"obs": obs}
        missing = sorted(set(self.obs_shapes) - set(obs))
        if missing:
            raise SafenavError(
                f"observation lacks {missing}: this policy reads {sorted(self.obs_shapes)}"
            )
        out, batched = [], None
        for k in self.actor.input_names:  # the actor's positional order
            shape = self.obs_shapes[k]
            x = obs[k]
            x = torch.as_tensor(
                np.asarray(x) if not isinstance(x, torch.Tensor) else x, dtype=torch.float32
            )
            if tuple(x.shape) == shape:
                x, this = x.unsqueeze(0), False
            elif tuple(x.shape[1:]) == shape:
                this = True
            else:
                raise SafenavError(f"observation {k!r} has shape {tuple(x.shape)}; this policy expects "
                                   f"(B, {', '.join(map(str, shape))})")  # fmt: skip
            if batched is not None and this != batched:
                raise SafenavError("observation entries disagree on the batch dimension")
            batched = this
            out.append(x.to(self.device))
        self._unbatched = not batched
        return out

    @torch.no_grad()
    def __call__(self, obs) -> torch.Tensor:
        """Deterministic actions in ``[-1, 1]``, ``(B, A)`` (``(A,)`` for one unbatched observation);
        for a discrete task the action's index, ``(B, 1)``."""
        action = self.actor(*self._prepare(obs))
        return action[0] if self._unbatched else action

    @torch.no_grad()
    def sample(self, obs, generator: torch.Generator | None = None) -> torch.Tensor:
        """Actions drawn as SAC-family training draws them, ``tanh(mean + std * eps)`` with
        ``eps ~ N(0, I)`` (:func:`~safenav.nn.networks.squashed_gaussian`), shaped as
        :meth:`__call__`'s: what the constraint of a CSAC run binds, where ``__call__`` gives the
        deterministic ``tanh(mean)`` that evaluation flies. PPO policies are refused."""
        if self.meta.get("policy_head") is not None:
            raise SafenavError(f"a {self.meta['policy_head']} PPO policy: sample() draws the "
                               "squashed Gaussian of SAC, SAC-Lag and CSAC policies only")  # fmt: skip
        mean, log_std = self.actor.gaussian(*self._prepare(obs))
        noise = torch.randn(mean.shape, generator=generator, device=mean.device)
        action, _ = squashed_gaussian(mean, log_std, noise)
        return action[0] if self._unbatched else action


def build_actor(meta: dict[str, Any]) -> DeterministicActor:
    """An untrained :class:`DeterministicActor` with the architecture ``meta`` describes (for PPO
    checkpoints, ``policy_head: "beta"``, the Beta-mean actor of :mod:`safenav.nn.beta`, or
    ``"gaussian"``, the clipped Gaussian mean of :mod:`safenav.nn.gaussian`, or ``"categorical"``,
    the most probable action of :mod:`safenav.nn.categorical`), behind an
    observation normaliser if ``meta`` has ``obs_normalization`` (``--normalize-obs``)."""
    actor = _build_network(meta)
    norm = meta.get("obs_normalization")
    if norm is None:
        return actor
    shapes = {k: tuple(v) for k, v in meta["obs_shapes"].items()}
    return NormalizedActor(
        ObsNormalizer(shapes, float(norm["clip"]), float(norm["epsilon"])), actor
    )


def _build_network(meta: dict[str, Any]) -> DeterministicActor:
    if meta.get("policy_head") == "beta":
        from safenav.nn.beta import build_beta_actor

        return build_beta_actor(meta)
    if meta.get("policy_head") == "gaussian":
        from safenav.nn.gaussian import build_gaussian_actor

        return build_gaussian_actor(meta)
    if meta.get("policy_head") == "categorical":
        from safenav.nn.categorical import build_categorical_actor

        return build_categorical_actor(meta)
    from safenav.common.config import from_dict

    net: NetConfig = from_dict(NetConfig, meta["net"])
    shapes = {k: tuple(v) for k, v in meta["obs_shapes"].items()}
    encoder = make_extractor(shapes, net) if net.shared_extractor else None
    actor_ex = None if net.shared_extractor else make_extractor(shapes, net)
    feat = (encoder or actor_ex).out_features
    return DeterministicActor(
        encoder, Actor(actor_ex, feat, int(meta["action_dim"]), net.hidden), input_order(shapes)
    )


def check_fits_safenav(policy: Policy, env_cfg: Any, where: str | Path) -> None:
    """``SafenavError`` unless ``policy`` was trained on SafeNav and reads the observations the
    env configuration ``env_cfg`` (an EnvConfig) produces: say so before flying, not mid-episode."""
    env_id = str(policy.meta.get("env_id", ""))
    if not env_id.split(":")[-1].startswith("SafeNav-"):
        raise SafenavError(f"{where} is a policy for {env_id or 'an unknown env'}, not SafeNav: "
                           "its observations do not fit the SafeNav test scenario")  # fmt: skip
    want = observation_shapes(env_cfg)
    if policy.obs_shapes != want:
        raise SafenavError(f"{where} reads observations {policy.obs_shapes}, but this SafeNav "
                           f"configuration gives {want}: evaluate it with the preset it was "
                           "trained on (drop --preset)")  # fmt: skip


def _check_layout(meta: dict[str, Any], path: Path) -> None:
    shapes = {k: tuple(v) for k, v in meta.get("obs_shapes", {}).items()}
    if not shapes:
        raise SafenavError(f"{path}: the policy metadata names no observation layout")
    env_cfg = meta.get("env_config")
    if env_cfg is not None:
        want = observation_shapes(env_cfg)
        if not is_nav_layout(shapes) or shapes != want:
            raise SafenavError(f"{path}: observation layout {shapes} does not match its SafeNav env "
                               f"configuration {want}: the checkpoint is inconsistent")  # fmt: skip


def load_policy(path: str | Path, device: str | torch.device = "cpu") -> Policy:
    """The deterministic policy of a training checkpoint (a ``checkpoint.pt`` or its run dir)."""
    path = Path(path)
    return policy_from_state(load_checkpoint(path, map_location=device), path, device)


def policy_from_state(
    state: dict[str, Any], where: str | Path = "policy", device: str | torch.device = "cpu"
) -> Policy:
    """The deterministic policy of a checkpoint dict already in memory (e.g. a weight average);
    ``where`` names it in errors."""
    path = where
    policy = state.get("policy")
    if not isinstance(policy, dict) or "meta" not in policy or "state_dict" not in policy:
        raise SafenavError(f"{path}: the checkpoint holds no policy (algorithm {state.get('algo')!r} "
                           "does not export one)")  # fmt: skip
    meta = dict(policy["meta"])
    if meta.get("format_version") != POLICY_FORMAT_VERSION:
        raise SafenavError(f"{path}: policy format version {meta.get('format_version')}; this safenav "
                           f"reads version {POLICY_FORMAT_VERSION}")  # fmt: skip
    _check_layout(meta, path)
    try:
        actor = build_actor(meta)
        actor.load_state_dict(policy["state_dict"])
    except (KeyError, RuntimeError, TypeError, ValueError) as err:
        raise SafenavError(
            f"{path}: the policy weights do not fit its described architecture ({one_line(err, 300)})"
        ) from None
    return Policy(actor.to(device), meta, device)


def save_policy_only(src: str | Path, dst: str | Path) -> Path:
    """Write the policy of checkpoint ``src`` without optimisers, critics or RNG state (a small
    file that :func:`load_policy` and ``safenav eval`` read, but ``--resume`` cannot continue)."""
    from safenav.common.checkpoint import POLICY_KEYS, save_checkpoint

    state = load_checkpoint(Path(src), map_location="cpu")
    if not isinstance(state.get("policy"), dict):
        raise SafenavError(f"{src}: the checkpoint holds no policy")
    dst = Path(dst)
    dst.parent.mkdir(parents=True, exist_ok=True)
    save_checkpoint(dst, {k: state[k] for k in POLICY_KEYS if k in state} | {"policy_only": True})
    return dst


__all__ = ["POLICY_FORMAT_VERSION", "Policy", "build_actor", "check_fits_safenav", "load_policy",
           "policy_from_state", "save_policy_only"]  # fmt: skip
