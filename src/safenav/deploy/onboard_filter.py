"""The planner filter on board (``safenav fly --planner-filter``, beyond the paper and NavRL).

:class:`~safenav.envs.planner.PlannerFilter` in its observed view reads only what a vehicle has:
the observation's pillar list and tracked moving obstacles, its odometry, its goal and the
arena's wall (its geofence). :class:`OnboardFilter` gives it those of one vehicle of the onboard
runtime (:class:`~safenav.deploy.runtime.OnboardRuntime`) in the place of an env
(:class:`VehicleView`), at any setpoint rate: each setpoint's command is tested by the same 2 s
rollout through the env's velocity tracker, and the stall handover counts seconds of flight
rather than env steps. Nothing tells it a flight has ended, so it filters until the goal changes.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np
import torch

from safenav.envs.config import EnvConfig
from safenav.envs.planner import (
    FILTER_SHORT_MOVES,
    FILTER_STALL,
    FILTER_STALL_TEST,
    PlannerFilter,
    observes_pillars,
)


@dataclass
class VehicleView:
    """The part of a :class:`~safenav.envs.nav.SafeNavVectorEnv` of one env that the observed
    view of :class:`~safenav.envs.planner.PlannerFilter` reads, filled from a vehicle's odometry
    and mission: ``(1, ...)`` tensors, world ENU; ``time`` seconds since the goal was set."""

    cfg: EnvConfig
    pos: torch.Tensor
    vel: torch.Tensor
    goal: torch.Tensor
    yaw: torch.Tensor
    band: torch.Tensor
    time: float
    num_envs: int = 1
    device: torch.device = torch.device("cpu")

    @classmethod
    def of(cls, cfg: EnvConfig, pos, vel, goal, yaw: float, start_z: float,
           time: float) -> VehicleView:  # fmt: skip
        """The view of a vehicle at ``pos`` with ``vel``, flying to ``goal`` in the goal frame of
        ``yaw`` (rad) from a start at altitude ``start_z`` (NavRL's altitude band, as the env's)."""
        as_row = lambda x: torch.tensor(np.asarray(x, dtype=np.float32).reshape(1, 3))  # noqa: E731
        goal_z = float(goal[2])
        band = torch.tensor([[min(start_z, goal_z) - 0.2, max(start_z, goal_z) + 0.2]])
        return cls(cfg, as_row(pos), as_row(vel), as_row(goal), torch.tensor([float(yaw)]),
                   band, float(time))  # fmt: skip

    @property
    def cos_yaw(self) -> torch.Tensor:
        return torch.cos(self.yaw)

    @property
    def sin_yaw(self) -> torch.Tensor:
        return torch.sin(self.yaw)


class OnboardFilter(PlannerFilter):
    """:class:`~safenav.envs.planner.PlannerFilter` (observed view, the stall handover of
    ``stall`` and ``stall_test``, default the adopted :data:`~safenav.envs.planner.FILTER_STALL`,
    tested in seconds of flight; the planner's ``short_moves``, default the adopted
    :data:`~safenav.envs.planner.FILTER_SHORT_MOVES`) over one vehicle's
    :class:`VehicleView`: ``action = filter(view, obs, action)``, ``overridden[0]`` whether the
    planner's command replaced the policy's. A new goal, or :meth:`new_flight`, starts a new
    flight."""

    def __init__(self, stall: tuple[float, float, float] | None = FILTER_STALL,
                 stall_test: str = FILTER_STALL_TEST,
                 short_moves: bool = FILTER_SHORT_MOVES) -> None:  # fmt: skip
        super().__init__(view="observation", stall=stall, stall_test=stall_test,
                         short_moves=short_moves)  # fmt: skip

    def _start(self, env) -> None:  # type: ignore[override]
        super()._start(env)
        self._mark_time, self._mark_dist, self._handover_until = -math.inf, math.inf, -math.inf
        self._seen: deque[tuple[float, float]] = deque()  # (time, distance): the sliding window

    def new_flight(self) -> None:
        """Start afresh at the next call (a new goal, or the same goal flown again)."""
        self._goals = None

    def _step_start(self, obs, env) -> torch.Tensor:  # type: ignore[override]
        """A new flight where the goal changed (each step brings a new view of the vehicle);
        on board no simulator says a flight collided or ended: it is filtered throughout."""
        if self._goals is None or not torch.equal(env.goal, self._goals):
            self._start(env)
        self._env = env
        return torch.zeros(1, dtype=torch.long)

    def _handing_over(self, env, ids: torch.Tensor) -> torch.Tensor:  # type: ignore[override]
        """``stall``'s test in seconds of flight: where the vehicle came less than ``progress`` m
        nearer its goal over the last ``window`` s, the planner flies the next ``handover`` s."""
        window, progress, handover = self.stall
        t, d = env.time, float((env.goal[0] - env.pos[0]).norm())
        eps = 1e-6  # seconds: 100 steps of 0.1 s are 10 s, whatever the rounding of the clock
        test = self._sliding_stalled_s if self.stall_test == "sliding" else self._tumbling_stalled_s
        if test(t, d, window, progress, handover, eps):
            self._handover_until = t + handover
            if self.stall_test == "sliding":
                self._mark_time = t + handover  # a full window after it ends
        handing = t < self._handover_until - eps
        self.handovers += int(handing)
        return torch.tensor([handing])

    def _tumbling_stalled_s(self, t: float, d: float, window: float, progress: float,
                            handover: float, eps: float) -> bool:  # fmt: skip
        """The ``"tumbling"`` test in seconds: at the end of each window, progress over it."""
        if not math.isfinite(self._mark_time) or t < self._mark_time:  # a new flight's window
            self._mark_time, self._mark_dist, self._handover_until = t, d, -math.inf
            return False
        if t - self._mark_time < window - eps:
            return False
        stalled = self._mark_dist - d < progress
        self._mark_time, self._mark_dist = t, d
        return stalled

    def _sliding_stalled_s(self, t: float, d: float, window: float, progress: float,
                           handover: float, eps: float) -> bool:  # fmt: skip
        """The ``"sliding"`` test in seconds: the distance now against the last one at least
        ``window`` s old, every call, once ``window`` s have passed since the flight's start or
        the last handover's end (``PlannerFilter._sliding_stalled`` on the env's steps)."""
        if not math.isfinite(self._mark_time) or (self._seen and t < self._seen[-1][0]):
            self._mark_time, self._handover_until = t, -math.inf  # a new flight: its clock from 0
            self._seen.clear()
        self._seen.append((t, d))
        while len(self._seen) > 1 and self._seen[1][0] <= t - window + eps:
            self._seen.popleft()  # keep one entry at least ``window`` old
        then_t, then_d = self._seen[0]
        free = t >= self._handover_until - eps
        due = free and t - self._mark_time >= window - eps and then_t <= t - window + eps
        return due and then_d - d < progress


def check_planner_filter(planner_filter: bool, cfg: EnvConfig | None, what: str) -> None:
    """``safenav fly --planner-filter`` flies on the policy's pillar list: refused, before any
    flight, for a policy (``what``) without one."""
    from safenav.errors import SafenavError

    if planner_filter and not observes_pillars(cfg):
        raise SafenavError(f"--planner-filter flies on the policy's pillar list, which {what} "
                           "does not observe (static_tracked 0): fly it without the filter")  # fmt: skip


__all__ = ["OnboardFilter", "VehicleView", "check_planner_filter"]
