"""Any Gymnasium env as a batch of torch tensors, with costs, true final observations and episodes.

:func:`make_vec_env` builds a vector env for any registered id: ``SafeNav-v1`` natively batched
(torch tensors on the training device), anything else as a ``SyncVectorEnv`` created with
``SAME_STEP`` autoreset. :class:`TorchVecEnv` then gives every algorithm the same view of it:

- observations as a dict of float32 tensors on ``device`` (a ``Box`` observation is ``{"obs": x}``;
  a ``Discrete`` or ``Tuple`` one, flattened by :func:`flat_observations`, its one-hot vector),
- actions in ``[-1, 1]^A``, mapped affinely onto the env's action box; for a ``Discrete(n)``
  action space (PPO only) the action is its index ``0 .. n-1`` as a float ``(N, 1)``, handed to
  the env as ``index + start`` (:func:`to_discrete_action`),
- ``cost`` from ``info["cost"]`` when the env reports one (for a finished env of a ``SyncVectorEnv``
  the step's info is ``info["final_info"]``), else 0; inside :func:`cost_function` every env
  :func:`make_vec_env` builds is wrapped in :class:`~safenav.common.costs.CostFn` (``--cost-fn``),
- ``real_next_obs``: the true ``s'`` of every transition (``final_obs`` for finished envs),
- ``valid``: False for the reset steps a ``NEXT_STEP`` autoreset env interleaves (no transition),
- ``episodes``: return, cost, length, success, collision, timeout of the episodes that ended
  (success is NaN for envs that report none; collision is "episode cost > 0" unless reported),
- with ``normalization`` (:class:`~safenav.common.normalize.EnvNormalization`, ``--normalize-obs``
  / ``--normalize-reward``): observations (``next_obs``, ``real_next_obs``, those of ``reset``)
  and ``reward`` normalised, its statistics updated with every step; the episode statistics and
  ``cost`` stay in the env's own units.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from contextvars import ContextVar
from typing import Any, NamedTuple

import gymnasium as gym
import numpy as np
import torch
from gymnasium.vector import AutoresetMode

from safenav.errors import SafenavError, SafenavRuntimeError

_COST_FN: ContextVar[str | None] = ContextVar("safenav_cost_fn", default=None)


@contextlib.contextmanager
def cost_function(spec: str | None) -> Iterator[None]:
    """Within the block, :func:`make_vec_env` wraps every non-SafeNav env in
    :class:`~safenav.common.costs.CostFn` with ``spec`` (``module:function``; None: no wrapper).
    ``safenav train`` runs the trainer inside it with ``RunConfig.cost_fn``."""
    token = _COST_FN.set(spec)
    try:
        yield
    finally:
        _COST_FN.reset(token)


def reports_cost(env_id: str, cost_fn: str | None = None, steps: int = 5) -> bool:
    """Whether ``env_id`` (wrapped in ``cost_fn`` when given) puts ``cost`` in its step info:
    a probe of ``steps`` random steps of one env."""
    from safenav.common.costs import CostFn

    env = _make(env_id)
    if cost_fn is not None:
        env = CostFn(env, cost_fn)
    try:
        env.reset(seed=0)
        env.action_space.seed(0)
        for _ in range(steps):
            _, _, terminated, truncated, info = env.step(env.action_space.sample())
            if "cost" in info:
                return True
            if terminated or truncated:
                env.reset()
        return False
    finally:
        env.close()


def quiet_mujoco() -> None:
    """MuJoCo's warnings (MuJoCo 4 warns about an attribute of HalfCheetah's model) as Python
    warnings instead of lines on stderr and a MUJOCO_LOG.TXT in the working directory."""
    import importlib.util

    if importlib.util.find_spec("mujoco") is None:
        return
    import warnings

    import mujoco

    mujoco.set_mju_user_warning(lambda msg: warnings.warn(f"MuJoCo: {msg}", stacklevel=1))


def _make(env_id: str, **kwargs: Any) -> gym.Env:
    """``gym.make``, MuJoCo's warnings routed first for a MuJoCo task."""
    from safenav.common.families import task_family

    if task_family(env_id)[0] == "mujoco":
        quiet_mujoco()
    return gym.make(env_id, **kwargs)


def _box_layout(space: gym.Space) -> bool:
    """A ``Box`` or a ``Dict`` of ``Box``es: what the networks read as it is."""
    return isinstance(space, gym.spaces.Box) or (
        isinstance(space, gym.spaces.Dict)
        and all(isinstance(s, gym.spaces.Box) for s in space.spaces.values())
    )


def flat_observations(env: gym.Env) -> gym.Env:
    """``env`` itself where its observation is a ``Box`` or a ``Dict`` of ``Box``es, else wrapped
    in Gymnasium's ``FlattenObservation``: a ``Discrete(n)`` observation (FrozenLake, Taxi) becomes
    its one-hot vector, a ``Tuple`` (Blackjack) the concatenation of its parts', as SB3 feeds them
    to its networks. A space Gymnasium cannot flatten is left to :func:`obs_layout` to refuse."""
    if _box_layout(env.observation_space):
        return env
    try:
        return gym.wrappers.FlattenObservation(env)
    except (NotImplementedError, TypeError, ValueError):  # flatten_space refused the space
        return env


def obs_layout(space: gym.Space) -> dict[str, tuple[int, ...]]:
    """Observation space -> ``{key: shape}`` of the observation dict the networks read
    (``{"obs": shape}`` for a ``Box``); ``SafenavError`` for anything else."""
    if isinstance(space, gym.spaces.Box):
        return {"obs": tuple(int(s) for s in space.shape)}
    if _box_layout(space):  # a Dict of Boxes
        return {k: tuple(int(d) for d in s.shape) for k, s in space.spaces.items()}
    raise SafenavError(
        f"observation space {space} is not supported: use a Box, a Dict of Boxes "
        "or a space Gymnasium flattens (Discrete, Tuple, MultiDiscrete, ...)"
    )


def is_safenav(env_id: str) -> bool:
    return env_id.split(":")[-1].startswith("SafeNav-")


def check_env(env_id: str, preset: str | None = None) -> None:
    """``SafenavError`` unless ``env_id`` is a registered Gymnasium id and ``preset`` a SafeNav
    preset given for SafeNav (what ``safenav train`` checks before creating its run directory)."""
    try:
        gym.spec(env_id)
    except gym.error.Error as err:
        raise SafenavError(f"unknown env id {env_id!r}: {err}") from None
    if preset is None:
        return
    if not is_safenav(env_id):
        raise SafenavError(f"--preset applies to SafeNav-v1 only, not {env_id!r}")
    from safenav.envs.config import PRESETS

    if preset not in PRESETS:
        raise SafenavError(f"unknown preset {preset!r}: choose one of {sorted(PRESETS)}")


def env_spaces(
    env_id: str,
    preset: str | None = None,
    env_kwargs: dict[str, Any] | None = None,
    discrete_ok: bool = False,
) -> tuple[dict[str, tuple[int, ...]], int, Any, int | None]:
    """``(observation shapes, action dimension, SafeNav EnvConfig or None, n of a Discrete(n)
    action space or None)`` of ``env_id``, checked before a run directory exists:
    ``SafenavError`` for an env that cannot be made (missing dependency) or whose spaces the
    algorithm does not support (:func:`check_action_space`; a ``Discrete`` action space,
    ``discrete_ok`` for PPO, has dimension 1: the index)."""
    check_env(env_id, preset)
    if is_safenav(env_id):
        from safenav.envs.config import make_config, observation_shapes

        try:
            cfg = make_config(preset or "paper", **(env_kwargs or {}))
        except (TypeError, ValueError) as err:
            raise SafenavError(f"--env-kwargs: {err}") from None
        return observation_shapes(cfg), 3, cfg, None
    try:
        env = flat_observations(_make(env_id, **(env_kwargs or {})))
    except Exception as err:  # noqa: BLE001 -- a missing extra (box2d, mujoco), a bad kwarg, ...
        missing = isinstance(err, ImportError) or type(err).__name__ == "DependencyNotInstalled"
        kind = SafenavRuntimeError if missing else SafenavError  # install it vs. fix the command
        raise kind(f"cannot make env {env_id!r}: {type(err).__name__}: {err}") from None
    try:
        check_action_space(env.action_space, discrete_ok)
        n = discrete_actions(env.action_space)
        dim = 1 if n is not None else int(env.action_space.shape[0])
        return obs_layout(env.observation_space), dim, None, n
    finally:
        env.close()


def discrete_actions(act: gym.Space) -> int | None:
    """``n`` of a ``Discrete(n)`` action space; None for any other (continuous: a ``Box``)."""
    return int(act.n) if isinstance(act, gym.spaces.Discrete) else None


def check_action_space(act: gym.Space, discrete_ok: bool = False) -> None:
    """``SafenavError`` unless ``act`` is a bounded 1-D ``Box`` (continuous actions, every
    algorithm) or, with ``discrete_ok`` (PPO and PPO-Lag), a ``Discrete`` space."""
    if isinstance(act, gym.spaces.Discrete):
        if discrete_ok:
            return
        raise SafenavError(f"action space {act} is discrete: CSAC, SAC and SAC-Lag need "
                           "continuous actions (a 1-D Box); PPO and PPO-Lag take discrete ones "
                           "(--algo ppo or ppo_lag)")  # fmt: skip
    if not isinstance(act, gym.spaces.Box) or len(act.shape) != 1:
        raise SafenavError(f"action space {act} is not supported: safenav's algorithms need "
                           "continuous actions (a 1-D Box) or, PPO and PPO-Lag, a Discrete "
                           "space")  # fmt: skip
    if not (np.all(np.isfinite(act.low)) and np.all(np.isfinite(act.high))):
        raise SafenavError(f"action space {act} is unbounded: the policies squash their actions "
                           "into finite bounds")  # fmt: skip


def make_vec_env(env_id: str, num_envs: int, device: str = "cpu", preset: str | None = None,
                 **env_kwargs: Any) -> gym.vector.VectorEnv:  # fmt: skip
    """A vector env of ``num_envs`` copies of ``env_id`` (see module docstring)."""
    if num_envs < 1:
        raise SafenavError(f"--num-envs {num_envs}: need at least one env")
    check_env(env_id, preset)
    if is_safenav(env_id):
        kwargs = dict(
            device=device, output="torch", autoreset_mode=AutoresetMode.SAME_STEP, **env_kwargs
        )
        if preset is not None:
            kwargs["preset"] = preset
        return gym.make_vec(
            env_id, num_envs=num_envs, vectorization_mode="vector_entry_point", **kwargs
        )
    cost_fn = _COST_FN.get()
    from safenav.common.families import task_family

    if task_family(env_id)[0] == "mujoco":
        quiet_mujoco()
    wrappers: list = [flat_observations]  # the cost function reads the env's own observations
    if cost_fn is not None:
        from safenav.common.costs import CostFn, load_cost_fn

        fn = load_cost_fn(cost_fn)
        wrappers.insert(0, lambda env: CostFn(env, fn))
    return gym.make_vec(env_id, num_envs=num_envs, vectorization_mode="sync", wrappers=wrappers,
                        vector_kwargs={"autoreset_mode": AutoresetMode.SAME_STEP}, **env_kwargs)  # fmt: skip


class Step(NamedTuple):
    next_obs: dict[str, torch.Tensor]
    reward: torch.Tensor
    cost: torch.Tensor
    terminated: torch.Tensor
    truncated: torch.Tensor
    real_next_obs: dict[str, torch.Tensor]
    valid: torch.Tensor
    episodes: dict[str, torch.Tensor] | None


def _pick(info: dict, key: str, i: int):
    """``info[key][i]`` if the vector env reported it for env ``i`` (``_key`` mask), else None."""
    if key not in info:
        return None
    mask = info.get("_" + key)
    if mask is not None and not bool(np.asarray(mask)[i]):
        return None
    return info[key][i]


def _info_costs(info: dict, done, same_step: bool, n: int) -> np.ndarray:
    """``info["cost"]`` of each env as float32, 0 where none; a ``SyncVectorEnv`` keeps a
    finished env's step info in ``final_info`` (SAME_STEP)."""
    cost = np.zeros(n, dtype=np.float32)
    final_info = info.get("final_info", {})
    for i in range(n):
        c = _pick(final_info, "cost", i) if bool(done[i]) and same_step else None
        c = _pick(info, "cost", i) if c is None else c
        if c is not None:
            cost[i] = float(c)
    return cost


def _info_success(info: dict, ids: list[int]) -> np.ndarray:
    """``success`` (or ``is_success``) of the envs ``ids`` as float32, NaN where none."""
    success = np.full(len(ids), np.nan, dtype=np.float32)
    for j, i in enumerate(ids):
        s = _pick(info, "success", i)
        s = _pick(info, "is_success", i) if s is None else s
        if s is not None:
            success[j] = float(s)
    return success


def to_action_box(action: torch.Tensor, low: torch.Tensor, high: torch.Tensor) -> torch.Tensor:
    """A policy's ``[-1, 1]^A`` action (clamped) -> the box ``[low, high]``. Written as a blend
    of the two bounds: ``high - low`` overflows for bounds near the float32 limit, which some
    tasks use for "unbounded"."""
    t = (action.clamp(-1, 1) + 1.0) * 0.5
    return low * (1.0 - t) + high * t


def to_discrete_action(action: torch.Tensor, start: int, num_actions: int) -> np.ndarray:
    """A discrete policy's action index ``(..., 1)`` (float) as a ``Discrete(num_actions,
    start)`` env takes it: rounded into ``0 .. n-1``, plus ``start``, as int64 ``(...)``."""
    index = action[..., 0].round().clamp(0, num_actions - 1).long()
    return (index + start).cpu().numpy()


def policy_action_to_env(action: torch.Tensor, meta: dict[str, Any]) -> np.ndarray | int:
    """A deterministic policy's output (:class:`safenav.algos.policy.Policy`, its ``meta``) as
    the env of its training takes it: the index plus ``start`` for discrete actions
    (``meta["num_actions"]``; a Python int for one observation, which toy-text envs use as a
    key), else the ``[-1, 1]`` action mapped onto the action box."""
    low = torch.as_tensor(meta["action_low"], dtype=torch.float32)
    if meta.get("num_actions") is not None:
        index = to_discrete_action(action, int(low[0]), int(meta["num_actions"]))
        return int(index) if index.ndim == 0 else index
    high = torch.as_tensor(meta["action_high"], dtype=torch.float32)
    return to_action_box(action.cpu(), low, high).numpy().astype(np.float64)


class TorchVecEnv:
    """The tensor view of a vector env described in the module docstring."""

    def __init__(self, envs: gym.vector.VectorEnv, device: str | torch.device = "cpu",
                 normalization: Any = None) -> None:  # fmt: skip
        self.envs, self.device, self.num_envs = envs, torch.device(device), envs.num_envs
        self.normalization = normalization
        """An :class:`~safenav.common.normalize.EnvNormalization` (on ``device``) or None."""
        space = envs.single_observation_space
        self.obs_shapes = obs_layout(space)
        self._box_obs = isinstance(space, gym.spaces.Box)
        act = envs.single_action_space
        check_action_space(act, discrete_ok=True)  # the SAC family refuses it (csac.py)
        self.num_actions = discrete_actions(act)
        """``n`` of a ``Discrete(n)`` action space, else None (continuous)."""
        if self.num_actions is not None:  # the action is the index: lowest and highest action
            self._start = int(act.start)
            self.action_dim = 1
            self._low = torch.tensor([float(self._start)], device=self.device)
            self._high = torch.tensor(
                [float(self._start + self.num_actions - 1)], device=self.device
            )
        else:
            self.action_dim = int(act.shape[0])
            self._low = torch.as_tensor(act.low, dtype=torch.float32, device=self.device)
            self._high = torch.as_tensor(act.high, dtype=torch.float32, device=self.device)
        self._torch_actions = is_safenav_vector(envs)
        self._unit = bool(torch.all(self._low == -1) and torch.all(self._high == 1))
        self.numpy_step = self.device.type == "cpu" and not self._torch_actions
        """Step through :meth:`_step_numpy` (a NumPy vector env on the CPU); same results."""
        self.autoreset_mode = AutoresetMode(
            envs.metadata.get("autoreset_mode", AutoresetMode.NEXT_STEP)
        )
        if self.autoreset_mode == AutoresetMode.DISABLED:
            raise SafenavError("the vector env has autoreset disabled: create it with SAME_STEP")
        n = self.num_envs
        self._ret = torch.zeros(n, device=self.device)
        self._cost = torch.zeros(n, device=self.device)
        self._len = torch.zeros(n, device=self.device)
        self._prev_done = torch.zeros(n, dtype=torch.bool, device=self.device)

    # -- conversions -------------------------------------------------------------------------
    def _t(self, x, dtype=torch.float32) -> torch.Tensor:
        return torch.as_tensor(
            np.asarray(x) if not isinstance(x, torch.Tensor) else x, dtype=dtype
        ).to(self.device)

    def _obs(self, obs) -> dict[str, torch.Tensor]:
        if self._box_obs:
            return {"obs": self._t(obs)}
        return {k: self._t(obs[k]) for k in self.obs_shapes}

    def scale_action(self, action: torch.Tensor) -> torch.Tensor:
        """``[-1, 1]^A`` -> the env's action box."""
        if self._unit:
            return action
        return to_action_box(action, self._low, self._high)

    def _to_env(self, action: torch.Tensor):
        if self.num_actions is not None:
            return to_discrete_action(action.detach(), self._start, self.num_actions)
        a = self.scale_action(action)
        return a if self._torch_actions else a.detach().cpu().numpy()

    # -- API ---------------------------------------------------------------------------------
    def reset(self, seed: int | None = None) -> dict[str, torch.Tensor]:
        obs, _ = self.envs.reset(seed=seed)
        self._ret.zero_(), self._cost.zero_(), self._len.zero_(), self._prev_done.zero_()
        if self.normalization is not None:
            return self.normalization.reset(self._obs(obs))
        return self._obs(obs)

    def set_density(self, density: float) -> bool:
        """Forward to the env's ``set_density`` (SafeNav); False if it has none."""
        fn = getattr(self.envs.unwrapped, "set_density", None)
        if fn is None:
            return False
        fn(density)
        return True

    def redraw_maps(self, seed: int) -> None:
        """Forward to SafeNav's ``redraw_maps`` (new maps, each env moving at its next episode)."""
        self.envs.unwrapped.redraw_maps(seed)

    def can_redraw_maps(self) -> bool:
        return self.envs.unwrapped.can_redraw_maps()

    def step(self, action: torch.Tensor) -> Step:
        if self.numpy_step:
            return self._step_numpy(action)
        obs, reward, terminated, truncated, info = self.envs.step(self._to_env(action))
        n, dev = self.num_envs, self.device
        next_obs = self._obs(obs)
        reward, terminated, truncated = (
            self._t(reward),
            self._t(terminated, torch.bool),
            self._t(truncated, torch.bool),
        )
        done = terminated | truncated
        same_step = self.autoreset_mode == AutoresetMode.SAME_STEP
        valid = torch.ones(n, dtype=torch.bool, device=dev) if same_step else ~self._prev_done

        # cost: info["cost"]; a SyncVectorEnv keeps a finished env's step info in final_info
        cost = torch.zeros(n, device=dev)
        if isinstance(info.get("cost"), torch.Tensor):  # native torch vector env (SafeNav)
            cost = info["cost"].to(dev, torch.float32)
        elif "cost" in info or "final_info" in info:
            cost = torch.from_numpy(_info_costs(info, done, same_step, n)).to(dev)

        # the true s' of every transition
        real_next = {k: v.clone() for k, v in next_obs.items()}
        if same_step and bool(done.any()) and info.get("final_obs") is not None:
            final, mask = info["final_obs"], info.get("_final_obs", done)
            if isinstance(mask, torch.Tensor):  # native torch vector env: one masked copy per key
                mask = mask.to(dev)
                for k in real_next:
                    real_next[k][mask] = final[k].to(dev, torch.float32)[mask]
            else:  # SyncVectorEnv: an object array of per-env observations (or a dict of them)
                for i in np.nonzero(np.asarray(mask))[0].tolist():
                    one = {k: final[k][i] for k in final} if isinstance(final, dict) else final[i]
                    for k in real_next:
                        real_next[k][i] = self._t(one[k] if isinstance(one, dict) else one)

        # episode bookkeeping
        v = valid.float()
        self._ret += reward * v
        self._cost += cost * v
        self._len += v
        ended = done & valid
        episodes = None
        if bool(ended.any()):
            ids = ended.nonzero().squeeze(-1)
            ep = info.get("episode") if isinstance(info.get("episode"), dict) else None
            collision = (self._cost[ids] > 0).float()
            if ep is not None and "success" in ep:  # SafeNav reports its own episode statistics
                success = self._t(ep["success"])[ids].float()
                collision = self._t(ep["collision"])[ids].float()
            else:
                final_info = info.get("final_info", {}) if same_step else info
                success = torch.from_numpy(_info_success(final_info, ids.tolist())).to(dev)
            episodes = {"return": self._ret[ids].clone(), "cost": self._cost[ids].clone(),
                        "length": self._len[ids].clone(), "success": success, "collision": collision,
                        "timeout": (truncated[ids] & ~terminated[ids]).float()}  # fmt: skip
            self._ret[ids], self._cost[ids], self._len[ids] = 0.0, 0.0, 0.0
        self._prev_done = done.clone()
        if self.normalization is not None:  # after the episode statistics: those stay raw
            next_obs, real_next, reward = self.normalization.step(next_obs, real_next, reward, done)
        return Step(
            next_obs,
            reward * v,
            cost * v,
            terminated & valid,
            truncated & valid,
            real_next,
            valid,
            episodes,
        )

    def _step_numpy(self, action: torch.Tensor) -> Step:
        """:meth:`step` for a NumPy vector env on the CPU, operation for operation in NumPy on
        views of the same float32 / bool buffers (bit for bit the torch path's result, tested):
        one MuJoCo step costs ~0.4 ms, and the torch path's ~40 operations on tensors of one
        env, ~10 us of dispatch each, cost about as much again."""
        obs, reward, terminated, truncated, info = self.envs.step(self._to_env(action))
        n = self.num_envs
        f32 = np.float32
        if self._box_obs:
            next_obs = {"obs": np.asarray(obs, dtype=f32)}
        else:
            next_obs = {k: np.asarray(obs[k], dtype=f32) for k in self.obs_shapes}
        reward = np.asarray(reward, dtype=f32)
        terminated, truncated = (
            np.asarray(terminated, dtype=bool),
            np.asarray(truncated, dtype=bool),
        )
        done = terminated | truncated
        same_step = self.autoreset_mode == AutoresetMode.SAME_STEP
        prev_done = self._prev_done.numpy()
        valid = np.ones(n, dtype=bool) if same_step else ~prev_done

        cost = _info_costs(info, done, same_step, n)

        real_next = next_obs  # the same object until a final observation differs
        if same_step and bool(done.any()) and info.get("final_obs") is not None:
            real_next = {k: v.copy() for k, v in next_obs.items()}
            final, mask = info["final_obs"], info.get("_final_obs", done)
            for i in np.nonzero(np.asarray(mask))[0].tolist():
                one = {k: final[k][i] for k in final} if isinstance(final, dict) else final[i]
                for k in real_next:
                    real_next[k][i] = np.asarray(
                        one[k] if isinstance(one, dict) else one, dtype=f32
                    )

        v = valid.astype(f32)
        ret, ep_cost, length = self._ret.numpy(), self._cost.numpy(), self._len.numpy()
        ret += reward * v
        ep_cost += cost * v
        length += v
        ended = done & valid
        episodes = None
        if bool(ended.any()):
            ids = np.nonzero(ended)[0]
            ep = info.get("episode") if isinstance(info.get("episode"), dict) else None
            collision = (ep_cost[ids] > 0).astype(f32)
            if ep is not None and "success" in ep:
                success = np.asarray(ep["success"], dtype=f32)[ids]
                collision = np.asarray(ep["collision"], dtype=f32)[ids]
            else:
                success = _info_success(
                    info.get("final_info", {}) if same_step else info, ids.tolist()
                )
            episodes = {name: torch.from_numpy(x) for name, x in (
                ("return", ret[ids]), ("cost", ep_cost[ids]), ("length", length[ids]),
                ("success", success), ("collision", collision),
                ("timeout", (truncated[ids] & ~terminated[ids]).astype(f32)))}  # fmt: skip
            ret[ids], ep_cost[ids], length[ids] = 0.0, 0.0, 0.0
        prev_done[:] = done
        to_torch = torch.from_numpy
        next_t = {k: to_torch(x) for k, x in next_obs.items()}
        real_t = next_t if real_next is next_obs else {k: to_torch(x) for k, x in real_next.items()}
        reward_t = to_torch(reward)
        if self.normalization is not None:  # after the episode statistics: those stay raw
            next_t, real_t, reward_t = self.normalization.step(
                next_t, real_t, reward_t, to_torch(done)
            )
        if real_t is next_t:  # two tensors, as the torch path gives
            real_t = {k: x.clone() for k, x in next_t.items()}
        return Step(next_t, reward_t * to_torch(v), to_torch(cost * v), to_torch(terminated & valid),
                    to_torch(truncated & valid), real_t, to_torch(valid), episodes)  # fmt: skip

    def close(self) -> None:
        self.envs.close()


def is_safenav_vector(envs: gym.vector.VectorEnv) -> bool:
    """True for the native SafeNav vector env (it takes torch actions on its device)."""
    from safenav.envs.nav import SafeNavVectorEnv

    return isinstance(envs.unwrapped, SafeNavVectorEnv)


def env_horizon(envs: gym.vector.VectorEnv, default: int = 1000) -> int:
    """The env's time limit in steps (SafeNav's config, else the spec's ``max_episode_steps``)."""
    cfg = getattr(envs.unwrapped, "cfg", None)
    if cfg is not None and hasattr(cfg, "max_episode_steps"):
        return int(cfg.max_episode_steps)
    spec = getattr(envs, "spec", None)
    steps = getattr(spec, "max_episode_steps", None) if spec is not None else None
    return int(steps) if steps else default


__all__ = ["Step", "TorchVecEnv", "check_action_space", "check_env", "cost_function", "discrete_actions",
           "env_horizon", "env_spaces", "flat_observations", "is_safenav", "is_safenav_vector", "make_vec_env", "obs_layout",
           "policy_action_to_env", "reports_cost", "to_action_box", "to_discrete_action"]  # fmt: skip
