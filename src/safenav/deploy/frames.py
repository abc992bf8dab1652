"""Coordinate frames of deployment: the world (ENU), PX4's local NED frame, and the goal frame.

- **World** = the map frame of SafeNav-v1: x east, y north, z up (ENU), metres. Perception (the
  occupancy map, tracked obstacles, camera poses) and the goal are expressed in it.
- **Local NED** = PX4's ``LOCAL_POSITION_NED`` / ``SET_POSITION_TARGET_LOCAL_NED`` frame: x north,
  y east, z down, with its origin at ``origin`` in world coordinates (PX4's EKF origin; with a
  motion-capture system feeding PX4 it is the mocap origin, i.e. ``origin = 0``).
- **Goal frame** = the policy's frame: x from the start toward the goal with z zeroed, z up; yaw
  ``psi`` fixed when the goal is set (the env fixes it at reset).

``ned = (y, x, -z)`` for a vector ``(x, y, z)`` in ENU, and the map is an involution (ENU = NED of
NED). Yaw angles: ``yaw_ned = pi/2 - yaw_enu`` (ENU yaw from east counter-clockwise, NED yaw from
north clockwise).
"""

from __future__ import annotations

import math

import numpy as np


def enu_to_ned(v) -> np.ndarray:
    """ENU vector(s) ``(..., 3)`` -> NED: ``(north, east, down) = (y, x, -z)``."""
    v = np.asarray(v, dtype=np.float64)
    return np.stack([v[..., 1], v[..., 0], -v[..., 2]], axis=-1)


def ned_to_enu(v) -> np.ndarray:
    """NED vector(s) ``(..., 3)`` -> ENU (the same swap; it is its own inverse)."""
    return enu_to_ned(v)


def world_to_local_ned(p_world, origin=(0.0, 0.0, 0.0)) -> np.ndarray:
    """World ENU position -> PX4 local NED position, ``origin`` = NED origin in world ENU."""
    return enu_to_ned(np.asarray(p_world, dtype=np.float64) - np.asarray(origin, dtype=np.float64))


def local_ned_to_world(p_ned, origin=(0.0, 0.0, 0.0)) -> np.ndarray:
    """PX4 local NED position -> world ENU position."""
    return ned_to_enu(p_ned) + np.asarray(origin, dtype=np.float64)


def yaw_enu_to_ned(yaw_enu: float) -> float:
    """ENU yaw (rad, from +x east, counter-clockwise) -> NED yaw (rad, from north, clockwise)."""
    return math.remainder(math.pi / 2 - yaw_enu, 2 * math.pi)


def goal_frame_yaw(start, goal) -> float:
    """Yaw (ENU, rad) of the goal frame's x axis: from ``start`` toward ``goal``, z zeroed."""
    d = np.asarray(goal, dtype=np.float64)[:2] - np.asarray(start, dtype=np.float64)[:2]
    return math.atan2(d[1], d[0])


__all__ = [
    "enu_to_ned",
    "goal_frame_yaw",
    "local_ned_to_world",
    "ned_to_enu",
    "world_to_local_ned",
    "yaw_enu_to_ned",
]
