"""The run configuration shared by every trainer, and dataclass <-> JSON helpers.

``config.json`` of a run directory is ``{"algo": ..., "run": RunConfig, "<algo>": AlgoConfig}``
as plain JSON; :func:`from_dict` rebuilds the (nested, frozen) dataclasses from it on resume.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from safenav.common.curriculum import DensityCurriculumConfig

MAX_SEED = 2**31 - 1
"""Seeds (training, env) lie in [0, MAX_SEED]: NumPy and torch take them, and the seeds derived
from them (``train_env_seed``) stay within int64."""
MAX_REPORT_EPISODES = 10_000
"""Most episodes per scenario in ``--select``'s final report (beyond: a typo, hours of flights)."""


@dataclass(frozen=True)
class RunConfig:
    """What to train on, for how long, where, and how to log it (shared by all algorithms)."""

    env: str = "SafeNav-v1"
    """Gymnasium env id: SafeNav-v1 or any registered id (Box actions; Box or Dict observations)."""
    preset: str | None = None
    """SafeNav-v1 preset (easy, medium, paper); None = paper. Only for SafeNav-v1."""
    env_kwargs: dict[str, int | float | bool | str] = field(default_factory=dict)
    """Keyword arguments of the env: SafeNav-v1 EnvConfig fields (e.g. ``reward_collision -100``;
    the density is the curriculum's, --density.*), else ``gymnasium.make`` kwargs of the env id.
    On the command line: ``--env-kwargs NAME VALUE [NAME VALUE ...]``; in a recipe:
    ``[run.env_kwargs]``."""
    cost_fn: str | None = None
    """``module:function`` that gives the cost of each step of an env that reports no
    ``info["cost"]`` (:class:`safenav.common.costs.CostFn`); None = the env's own cost, or 0."""
    normalize_obs: bool = False
    """Gymnasium tasks: normalise observations by their running mean and variance, clipped to
    [-10, 10] (SB3's VecNormalize, the RL Zoo's ``normalize``); the statistics are part of the
    policy (safenav.common.normalize). Not for SafeNav-v1, which scales its own observations."""
    normalize_reward: bool = False
    """Gymnasium tasks: scale rewards by the running standard deviation of the discounted return
    (the algorithm's gamma), clipped to [-10, 10] (SB3's VecNormalize); costs stay as they are,
    reported returns too. Not for SafeNav-v1."""
    num_envs: int = 16
    """Parallel envs in the training vector env."""
    seed: int = 1
    """Seed of networks, replay sampling, exploration and the training env's maps/episodes."""
    total_steps: int = 1_000_000
    """Env steps (transitions, summed over the parallel envs) to train for: 1000000, 1e6,
    1_000_000 or 1M."""
    device: str = "cpu"
    """Torch device of the env, replay buffer and networks: cpu or cuda."""
    torch_threads: int = 0
    """torch.set_num_threads for this run; 0 = one per CPU core."""
    log_every: int = 10_000
    """Env steps between progress.csv rows."""
    eval_every: int = 100_000
    """Env steps between deterministic evaluations (eval/* columns); 0 = never."""
    eval_episodes: int = 20
    """Episodes per evaluation (full density, a fixed env seed unlike training and the test seed)."""
    checkpoint_every: int = 50_000
    """Env steps between checkpoint.pt writes (also written at the end and on Ctrl-C)."""
    map_refresh_every: int = 200_000
    """SafeNav-v1: env steps (all envs together) between redraws of the training maps (new
    seeds); 0 = keep them. Raised to num_envs x the episode's time limit where it is shorter, so
    each env can finish an episode per map set (the run says so)."""
    map_refresh_mode: Literal["all", "per-env"] = "all"
    """SafeNav-v1, how the training maps are redrawn: all = every env starts an episode in the new
    maps at once (the episodes in flight are cut); per-env = each env ends its episode in the old
    map and starts the next in the new one (none cut; the env then holds two map sets)."""
    shield: bool = False
    """SafeNav-v1: train behind the velocity-obstacle safety shield (beyond the paper; the
    ``--shield`` of ``safenav eval``): the env executes the shield's correction of each action, the
    learner keeps the policy's own action (the shield is part of the env it learns in). The
    policy records its shield (``meta["shield"]``); its periodic evaluation, selection and final
    report fly behind it too."""
    shield_memory: int = 0
    """With ``shield``: its static obstacles are the range images of the last N env steps (0, 1:
    the current image; ``safenav eval --shield-memory``)."""
    shield_map: bool = False
    """With ``shield``: it also scans the height map at the UAV's lower extent (``--shield-map``)."""
    shield_mover_margin: float = 0.0
    """With ``shield``: metres more clearance from tracked moving obstacles (0-2)."""
    shield_brake: bool = False
    """With ``shield``: the braking cap (``--shield-brake``, beyond NavRL): near a static obstacle
    (and the ground and ceiling) the vehicle slows to a speed it can stop from, given its 0.4 s
    velocity lag."""
    shield_flight_brake: bool = False
    """With ``shield``: train behind the shield without the braking cap but fly with it: the
    periodic evaluation, the selection, the final report and ``safenav eval`` / ``render`` (by
    default) add the cap (``meta["flight_shield"]``; the validation choice of docs/csac-v1.md,
    "Training behind the braking cap")."""
    shield_penalty: float = 0.0
    """With ``shield``: the training reward falls by this much per m/s of the shield's correction
    of the policy's action at each step (beyond the paper; 0 = none): the policy learns to need
    the shield less. Evaluations and the logged returns are without it."""
    flight_filter: bool = False
    """SafeNav-v1: the final report (test scenario, held-out maps) and ``safenav eval`` / ``render``
    (by default) fly the policy behind the model-predictive planner filter after its shield
    (beyond the paper: ``safenav eval --planner-filter``, the observed view with the stall
    handover; ``meta["flight_filter"]``; docs/csac-v1.md). The periodic evaluations and the
    selection on validation maps fly without it, for it triples an evaluation's cost. Needs the
    observation's pillar list (``static_tracked``)."""
    keep_policies: bool = False
    """Also keep the policy of every periodic evaluation as ``policies/step_<N>.pt`` (policy-only,
    ~0.6 MB each), to compare a run's policies afterwards (experiments/checkpoint_sweep.py)."""
    select: bool = False
    """End the run by choosing its policy on validation maps only (greedy soup of the policies
    kept in its last half; implies keep_policies): ``RUN_DIR/policy.pt`` and ``selection.json``,
    then its report on the test scenario and held-out maps in ``RUN_DIR/final.json``."""
    report_episodes: int = 200
    """With ``select``: episodes of the final report on the test scenario and on each held-out map
    (200: the paper's test; fewer only for quick checks; a ``safenav reproduce`` rerun keeps the
    reports of its finished trials whatever this says now)."""
    save_buffer: bool = False
    """Store the replay buffer in checkpoint.pt (large); without it a resume refills it first."""
    matmul_precision: Literal["highest", "high", "medium"] = "highest"
    """torch.set_float32_matmul_precision: highest = exact float32 matmuls (default); medium lets
    CPUs with AMX (and GPUs) multiply in bfloat16 with float32 accumulation (docs/csac.md)."""
    tensorboard: bool = True
    """Write TensorBoard events to tb/ besides progress.csv."""
    density: DensityCurriculumConfig = field(default_factory=DensityCurriculumConfig)
    """Obstacle-density curriculum (SafeNav-v1 only)."""

    def __post_init__(self) -> None:
        counts = ("num_envs", "total_steps", "log_every", "checkpoint_every", "eval_episodes",
                  "report_episodes", "eval_every", "torch_threads", "map_refresh_every", "seed")  # fmt: skip
        for name in counts:  # a recipe file or config.json is not typed like the command line
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int):
                raise ValueError(f"{name.replace('_', '-')}={value!r} must be an integer")
        for name in ("num_envs", "total_steps", "log_every", "checkpoint_every", "eval_episodes"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name.replace('_', '-')}={getattr(self, name)} must be >= 1")
        if not 1 <= self.report_episodes <= MAX_REPORT_EPISODES:
            raise ValueError(
                f"report-episodes={self.report_episodes} must lie in [1, {MAX_REPORT_EPISODES}]"
            )
        if self.report_episodes != 200 and not self.select:
            raise ValueError("report-episodes sets --select's final report; add --select")
        if self.eval_every < 0 or self.torch_threads < 0 or self.map_refresh_every < 0:
            raise ValueError("eval-every, torch-threads and map-refresh-every must be >= 0")
        if self.map_refresh_mode not in ("all", "per-env"):
            raise ValueError(f"map-refresh-mode={self.map_refresh_mode!r} must be all or per-env")
        if not 0 <= self.seed <= MAX_SEED:
            raise ValueError(f"seed={self.seed} must lie in [0, {MAX_SEED}]")
        if "density" in self.env_kwargs:
            raise ValueError(
                "env-kwargs density: the density is the curriculum's; set it with "
                "--density.start / --density.end (or --density.no-enabled)"
            )
        asked = [f for f in ("normalize_obs", "normalize_reward") if getattr(self, f)]
        if asked and self.env.split(":")[-1].startswith("SafeNav-"):
            raise ValueError(
                f"{' / '.join(f.replace('_', '-') for f in asked)} applies to Gymnasium tasks, "
                f"not {self.env}: SafeNav scales its own observations and rewards"
            )
        self._check_shield()
        if self.select and not self.keep_policies:
            object.__setattr__(self, "keep_policies", True)  # the candidates of the selection
        if self.torch_threads > 1024:
            raise ValueError(
                f"torch-threads={self.torch_threads} must be <= 1024 (0 = one per core)"
            )

    def _check_shield(self) -> None:
        if isinstance(self.shield_memory, bool) or not isinstance(self.shield_memory, int):
            raise ValueError(f"shield-memory={self.shield_memory!r} must be an integer")
        if not 0 <= self.shield_memory <= 100:
            raise ValueError(
                f"shield-memory={self.shield_memory} must lie in [0, 100] range images"
            )
        penalty = self.shield_penalty
        if (
            isinstance(penalty, bool)
            or not isinstance(penalty, int | float)
            or not 0 <= penalty <= 10
        ):
            raise ValueError(f"shield-penalty={penalty!r} must lie in [0, 10] per m/s")
        margin = self.shield_mover_margin
        if isinstance(margin, bool) or not isinstance(margin, int | float) or not 0 <= margin <= 2:
            raise ValueError(f"shield-mover-margin={margin!r} must lie in [0, 2] m")
        extras = [name for name, on in (("shield-memory", self.shield_memory > 1),
                  ("shield-map", self.shield_map), ("shield-mover-margin", margin > 0),
                  ("shield-brake", self.shield_brake),
                  ("shield-flight-brake", self.shield_flight_brake),
                  ("shield-penalty", penalty > 0)) if on]  # fmt: skip
        if extras and not self.shield:
            raise ValueError(f"{' / '.join(extras)} set the shield: add --shield")
        if self.shield and not self.env.split(":")[-1].startswith("SafeNav-"):
            raise ValueError(f"shield: the safety shield flies SafeNav, not {self.env}")
        if self.flight_filter and not self.env.split(":")[-1].startswith("SafeNav-"):
            raise ValueError(f"flight-filter: the planner filter flies SafeNav, not {self.env}")

    def shield_spec(self) -> dict[str, Any] | None:
        """The shield the policy trains behind, as its ``meta["shield"]`` records it; None without."""
        if not self.shield:
            return None
        return {"memory": max(self.shield_memory, 1), "map": bool(self.shield_map),
                "mover_margin": float(self.shield_mover_margin),
                "brake": bool(self.shield_brake)}  # fmt: skip

    def flight_shield_spec(self) -> dict[str, Any] | None:
        """The shield the policy flies behind (evaluation, selection, report; its
        ``meta["flight_shield"]``): the training shield, with the braking cap for
        ``shield_flight_brake``; None without a shield."""
        spec = self.shield_spec()
        if spec is not None and self.shield_flight_brake:
            spec["brake"] = True
        return spec

    def train_env_seed(self, refresh: int) -> int:
        """Seed of the training maps after ``refresh`` redraws: >= 100000, so never the test
        scenario's env seed 1 nor the evaluation seed 12345."""
        return 100_000 + (self.seed * 7919 + refresh) * 1000

    def planner_env_seed(self) -> int:
        """Seed of the maps the planner flies for ``--csac.planner-share``: halfway between two
        training map sets (map ``w`` is drawn from the seed + ``w``), so none of the training,
        validation, held-out or test maps."""
        return self.train_env_seed(0) + 500


def flight_shield_spec(meta: dict[str, Any]) -> dict[str, Any] | None:
    """The shield a policy's ``meta`` says it flies behind: ``flight_shield`` (``safenav train
    --shield-flight-brake`` adds the braking cap there), else the one it trained behind (policies
    from before ``flight_shield``), else None."""
    return meta.get("flight_shield") or meta.get("shield")


def to_dict(obj: Any) -> Any:
    """A dataclass (nested) as JSON-ready data (tuples become lists, Paths strings)."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: to_dict(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, (list, tuple)):
        return [to_dict(v) for v in obj]
    if isinstance(obj, Path):
        return str(obj)
    return obj


def _convert(tp: Any, value: Any) -> Any:
    if value is None:
        return None
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        for arg in typing.get_args(tp):
            if arg is not type(None):
                return _convert(arg, value)
    if dataclasses.is_dataclass(tp) and isinstance(value, dict):
        return from_dict(tp, value)
    if origin is tuple and isinstance(value, (list, tuple)):
        return tuple(value)
    if tp is Path:
        return Path(value)
    return value


def from_dict(cls: type, data: dict[str, Any]) -> Any:
    """Rebuild dataclass ``cls`` from :func:`to_dict` output; unknown keys are an error."""
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise ValueError(f"{cls.__name__}: unknown field(s) {unknown}")
    return cls(**{k: _convert(hints[k], v) for k, v in data.items()})


__all__ = ["RunConfig", "from_dict", "to_dict"]
