"""Scripted policies that act on SafeNav observations alone (baselines, demos, tests).

:func:`go_to_goal` flies straight at the goal; :func:`potential_field` adds repulsion from the
range-image beams and the tracked moving obstacles (a classic artificial-potential-field
controller, the kind of hand-written planner learned policies are compared against).
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


__all__ = ["go_to_goal", "potential_field"]
