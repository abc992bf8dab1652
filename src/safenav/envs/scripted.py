"""Scripted policies that act on SafeNav observations alone (baselines, demos, tests).

:func:`go_to_goal` flies straight at the goal; :func:`potential_field` adds repulsion from the
range-image beams and the tracked moving obstacles (a classic artificial-potential-field
controller, the kind of hand-written planner learned policies are compared against);
:class:`BorderFollower` flies around the field along the border (the probe that shows no path
around the obstacle field exists).
"""

from __future__ import annotations

import math

import torch


def go_to_goal(obs: dict[str, torch.Tensor], speed: float = 1.0) -> torch.Tensor:
    """Normalised velocity command straight toward the goal, slowing down inside the last metre.

    ``obs["state"][:, :3]`` is the unit vector to the goal in the goal frame; ``[:, 3]`` the
    horizontal distance / 20 m and ``[:, 4]`` the z distance / 4 m.
    """
    state = obs["state"]
    unit = state[:, :3]
    dist = torch.sqrt((state[:, 3] * 20.0) ** 2 + (state[:, 4] * 4.0) ** 2)
    gain = (dist / 1.0).clamp(max=1.0)[:, None]  # slow down close to the goal
    return (unit * speed * gain).clamp(-1.0, 1.0)


def potential_field(
    obs: dict[str, torch.Tensor],
    v_angles_deg: tuple[float, ...] = (-10.0, 0.0, 10.0, 20.0),
    speed: float = 0.8,
    repulsion: float = 1.5,
) -> torch.Tensor:
    """Attraction to the goal plus repulsion from close beams and moving obstacles.

    Beam values are ``(4 - d) / 4``; a beam ``j`` of elevation ``e`` points at azimuth ``10 j``
    degrees in the goal frame, so its repulsion pushes along ``-(cos e cos a, cos e sin a, sin e)``.
    """
    lidar = obs["lidar"]  # (N, V, H)
    nv, nh = lidar.shape[-2:]
    dev = lidar.device
    az = torch.arange(nh, device=dev, dtype=torch.float32) * (2 * math.pi / nh)
    el = torch.tensor(v_angles_deg[:nv], device=dev) * (math.pi / 180)
    dirs = torch.stack([
        torch.cos(el)[:, None] * torch.cos(az)[None, :],
        torch.cos(el)[:, None] * torch.sin(az)[None, :],
        torch.sin(el)[:, None].expand(nv, nh),
    ], -1)  # fmt: skip
    # Only obstacles (not the ground under the downward beams) repel horizontally.
    weight = lidar**3
    push = -(weight[..., None] * dirs).sum((1, 2))
    push[:, 2] = push[:, 2].clamp(min=0) * 0.2
    dyn = obs["dynamic"]
    near = (1.0 - dyn[..., 3]).clamp(min=0) * (dyn[..., :3].abs().sum(-1) > 0)
    push = push - (near[..., None] ** 2 * dyn[..., :3]).sum(1) * 2.0
    cmd = go_to_goal(obs, speed) + repulsion * push / nh
    return cmd.clamp(-1.0, 1.0)


class BorderFollower:
    """The loophole probe: fly to the nearest border, then along it toward the goal (the shorter
    way round), at ``edge_margin / 2`` from the wall, then straight to the goal once within
    ``final_approach`` m. It reads the env's state (positions), not observations alone, so it is
    called as ``policy(obs, env)`` (``needs_env``).

    In SafeNav-v0's open arena an obstacle-free ring along the border made this a winning
    strategy; in v1 the band is as cluttered as the interior and the border is a wall, so it must
    fail: it never avoids anything.
    """

    needs_env = True

    def __init__(self, speed: float = 1.0, final_approach: float = 2.5) -> None:
        self.speed = speed
        self.final_approach = final_approach

    @staticmethod
    def _perimeter(xy: torch.Tensor, ring: float) -> torch.Tensor:
        """Counter-clockwise arc length along the square ring ``|x|, |y| = ring`` of the ring
        point nearest ``xy`` (0 at the south-east corner; east side first)."""
        x, y = xy[..., 0].clamp(-ring, ring), xy[..., 1].clamp(-ring, ring)
        east, north, west = x >= y.abs(), y > x.abs(), -x >= y.abs()
        return torch.where(east, y + ring, torch.where(north, 3 * ring - x,
                           torch.where(west, 5 * ring - y, 7 * ring + x)))  # fmt: skip

    def __call__(self, obs: dict[str, torch.Tensor], env) -> torch.Tensor:
        from safenav.envs.dynamics import world_to_goal_frame

        cfg = env.cfg
        ring = cfg.half - cfg.edge_margin / 2
        pos, goal = env.pos, env.goal
        xy = pos[:, :2]
        # Nearest ring point (the border line at ring distance), and the tangent there.
        inward = xy.abs().amax(-1) < ring
        ax = xy[:, 0].abs() >= xy[:, 1].abs()  # nearest to an east/west side
        target = torch.where(ax[:, None], torch.stack([torch.sign(xy[:, 0]) * ring, xy[:, 1].clamp(-ring, ring)], -1),
                             torch.stack([xy[:, 0].clamp(-ring, ring), torch.sign(xy[:, 1]) * ring], -1))  # fmt: skip
        perim = 8 * ring
        gap = (self._perimeter(goal[:, :2], ring) - self._perimeter(xy, ring)) % perim
        sense = torch.where(gap < perim / 2, 1.0, -1.0)  # +1: counter-clockwise
        # Counter-clockwise tangent of the side the UAV is on (east: +y, north: -x, ...).
        east, north, west = (
            xy[:, 0] >= xy[:, 1].abs(),
            xy[:, 1] > xy[:, 0].abs(),
            -xy[:, 0] >= xy[:, 1].abs(),
        )
        zero = torch.zeros_like(xy[:, 0])
        tangent = torch.where(east[:, None], torch.stack([zero, zero + 1], -1),
                  torch.where(north[:, None], torch.stack([zero - 1, zero], -1),
                  torch.where(west[:, None], torch.stack([zero, zero - 1], -1),
                              torch.stack([zero + 1, zero], -1))))  # fmt: skip
        along = tangent * sense[:, None] * (1.0 - 0.5 * inward.float())[:, None]
        # Slow down near corners: the velocity tracker's lag would carry it into the wall.
        corner = (xy.abs() > ring - 2.5).all(-1)
        along = along * torch.where(corner, 0.35, 1.0)[:, None]
        v_xy = along + (target - xy) * 1.5  # follow the side, pulled onto the ring
        to_goal = goal - pos
        v = torch.cat([v_xy, to_goal[:, 2:3].clamp(-1, 1)], -1)
        close = to_goal[:, :2].norm(dim=-1) < self.final_approach
        v = torch.where(close[:, None], to_goal, v)
        v = (
            v
            / v.norm(dim=-1, keepdim=True).clamp(min=1e-6)
            * torch.minimum(v.norm(dim=-1, keepdim=True), torch.tensor(1.0))
        )
        cmd = world_to_goal_frame(v * cfg.v_max * self.speed, env.cos_yaw, env.sin_yaw) / cfg.v_max
        return cmd.clamp(-1.0, 1.0)


__all__ = ["BorderFollower", "go_to_goal", "potential_field"]
