"""Pinhole depth cameras: the body-mounted rig, a depth renderer for the simulator, back-projection.

Conventions: depth is the z-distance along the optical axis (as RealSense/ROS depth images), the
optical frame has x right, y down, z forward; the body frame is FLU (x forward, y left, z up) and
the world is ENU. A camera's pose is its camera-to-world rotation ``R`` and position ``t``:
``p_world = R @ p_cam + t``.

:func:`render_depth` is the simulator's camera: every pixel ray against axis-aligned boxes (the
pillars and moving obstacles of a SafeNav-v1 world) and the ground plane ``z = 0``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

# Optical frame axes in the body frame (FLU): x_opt = -y_body, y_opt = -z_body, z_opt = x_body.
R_BODY_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


@dataclass(frozen=True)
class PinholeCamera:
    """Intrinsics of a depth camera (pixels) and its usable range (m)."""

    width: int = 80
    height: int = 60
    fx: float = 40.0
    fy: float = 40.0
    cx: float = 39.5
    cy: float = 29.5
    max_range: float = 10.0

    @staticmethod
    def from_fov(
        width: int, height: int, hfov_deg: float, max_range: float = 10.0
    ) -> PinholeCamera:
        """Square pixels, principal point at the image centre, horizontal field of view ``hfov``."""
        f = (width / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)
        return PinholeCamera(width, height, f, f, (width - 1) / 2.0, (height - 1) / 2.0, max_range)

    def pixel_rays(self, stride: int = 1) -> np.ndarray:
        """``(h * w, 3)`` rays ``((u - cx) / fx, (v - cy) / fy, 1)`` of the pixels, row-major."""
        v, u = np.mgrid[0 : self.height : stride, 0 : self.width : stride]
        return np.stack(
            [(u - self.cx) / self.fx, (v - self.cy) / self.fy, np.ones(u.shape)], -1
        ).reshape(-1, 3)


def rotz(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rig_poses(
    position, yaw: float, n_cameras: int = 4, pitch_deg: float = 0.0
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Camera-to-world poses of ``n_cameras`` evenly spaced around the body's z axis at
    ``position`` (world), the first looking along the body's heading ``yaw`` (ENU, rad)."""
    c, s = math.cos(math.radians(pitch_deg)), math.sin(math.radians(pitch_deg))
    pitch_up = np.array([[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]])  # rotation about body y
    t = np.asarray(position, dtype=np.float64).reshape(3)
    return [
        (rotz(yaw + 2 * math.pi * i / n_cameras) @ pitch_up @ R_BODY_OPTICAL, t.copy())
        for i in range(n_cameras)
    ]


def render_depth(
    cam: PinholeCamera,
    R: np.ndarray,
    t: np.ndarray,
    box_lo: torch.Tensor,
    box_hi: torch.Tensor,
    ground: bool = True,
) -> np.ndarray:
    """Depth image ``(H, W)`` float32 (m, 0 = no return within ``max_range``) of the boxes
    ``[box_lo, box_hi]`` (``(B, 3)``, world) and the ground plane, seen from pose ``(R, t)``.

    A ray with parameter ``s`` along ``R @ (x, y, 1)`` is at z-depth ``s``, so the slab method's
    entry parameter is the depth directly.
    """
    rays = torch.as_tensor(cam.pixel_rays() @ np.asarray(R).T, dtype=torch.float32)  # (P, 3)
    o = torch.as_tensor(np.asarray(t), dtype=torch.float32)
    far = torch.full((rays.shape[0],), math.inf)
    if box_lo.shape[0] > 0:
        inv = 1.0 / torch.where(rays.abs() < 1e-9, torch.full_like(rays, 1e-9), rays)
        t1 = (box_lo[None] - o) * inv[:, None]  # (P, B, 3)
        t2 = (box_hi[None] - o) * inv[:, None]
        t_near = torch.minimum(t1, t2).amax(-1)
        t_far = torch.maximum(t1, t2).amin(-1)
        hit = (t_far >= t_near) & (t_far > 0)
        far = torch.where(hit, t_near.clamp(min=0), math.inf).amin(-1)
    if ground:
        dz = rays[:, 2]
        g = torch.where(dz < -1e-9, -o[2] / dz.clamp(max=-1e-9), math.inf)
        far = torch.minimum(far, g)
    # Range is along the ray; the ray has length |(x, y, 1)| per unit of depth.
    rng = far * rays.norm(dim=-1)
    depth = torch.where(rng <= cam.max_range, far, 0.0)
    return depth.reshape(cam.height, cam.width).numpy().astype(np.float32)


def backproject(
    depth,
    fx,
    fy,
    cx,
    cy,
    R,
    t,
    stride: int = 1,
    max_range: float = math.inf,
    with_normals: bool = False,
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """World points ``(P, 3)`` of the valid pixels (finite, > 0, within ``max_range`` of the
    camera) of depth images ``(H, W)`` or a batch ``(B, H, W)`` (intrinsics scalars or ``(B,)``,
    poses ``(B, 3, 3)`` and ``(B, 3)``), every ``stride``-th pixel in both directions. NumPy
    float32 in and out (array-likes and CPU tensors are accepted).

    ``with_normals``: also return unit surface normals ``(P, 3)`` facing the camera, from forward
    differences to the neighbouring pixels; where a neighbour is missing or farther than a quarter
    of the depth (an edge, or a surface seen at more than ~84 degrees), the reversed viewing ray.

    Computed on the valid pixels only, coordinate by coordinate, in NumPy: the arrays are small and
    per-operation overhead is what costs.
    """
    f32 = lambda x: np.asarray(x, dtype=np.float32)  # noqa: E731
    depth, R, t = f32(depth), f32(R), f32(t)
    if depth.ndim == 2:
        depth, R, t = depth[None], R[None], t[None]
    b = depth.shape[0]
    fx, fy, cx, cy = (
        np.broadcast_to(f32(v).reshape(-1), (b,))[:, None, None] for v in (fx, fy, cx, cy)
    )
    d = depth[:, ::stride, ::stride]
    _, h, w = d.shape
    # World-frame ray of every pixel, R @ ((u - cx) / fx, (v - cy) / fy, 1): a point is t + z * ray.
    x = (
        np.arange(0, depth.shape[2], stride, dtype=np.float32)[None, None, :] - cx
    ) / fx  # (B, 1, w)
    y = (
        np.arange(0, depth.shape[1], stride, dtype=np.float32)[None, :, None] - cy
    ) / fy  # (B, h, 1)
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(d) & (d > 0)
        if math.isfinite(max_range):
            valid &= d * np.sqrt(1.0 + x * x + y * y) <= max_range
    idx = np.flatnonzero(valid)
    flat_d = np.where(valid, d, 0.0).reshape(-1)
    Rb = R[:, :, :, None, None]
    rays = [(Rb[:, i, 0] * x + Rb[:, i, 1] * y + Rb[:, i, 2]).reshape(-1) for i in range(3)]
    cam = idx // (h * w)

    def offsets(index: np.ndarray) -> list[np.ndarray]:  # z * ray = the point minus t
        z = flat_d[index]
        return [r[index] * z for r in rays]

    c = offsets(idx)
    pts = np.stack(c, -1) + t[cam]
    if not with_normals:
        return pts
    inner = np.zeros_like(valid)  # pixels whose right and lower neighbours are valid
    inner[:, :-1, :-1] = valid[:, :-1, :-1] & valid[:, :-1, 1:] & valid[:, 1:, :-1]
    last = flat_d.size - 1
    r, dn = offsets(np.minimum(idx + 1, last)), offsets(np.minimum(idx + w, last))
    du = [r[i] - c[i] for i in range(3)]
    dv = [dn[i] - c[i] for i in range(3)]
    lim = (0.25 * flat_d[idx]) ** 2
    ok = inner.reshape(-1)[idx]
    ok &= (du[0] ** 2 + du[1] ** 2 + du[2] ** 2 < lim) & (
        dv[0] ** 2 + dv[1] ** 2 + dv[2] ** 2 < lim
    )
    n = (
        du[1] * dv[2] - du[2] * dv[1],
        du[2] * dv[0] - du[0] * dv[2],
        du[0] * dv[1] - du[1] * dv[0],
    )
    inv = 1.0 / np.sqrt(np.maximum(n[0] ** 2 + n[1] ** 2 + n[2] ** 2, 1e-20))
    # Face the camera (n . (p - t) < 0); elsewhere the reversed viewing ray.
    sign = np.where(n[0] * c[0] + n[1] * c[1] + n[2] * c[2] > 0, -inv, inv)
    back = -1.0 / np.sqrt(np.maximum(c[0] ** 2 + c[1] ** 2 + c[2] ** 2, 1e-20))
    normals = np.stack([np.where(ok, n[i] * sign, c[i] * back) for i in range(3)], -1)
    return pts, normals.astype(np.float32)


__all__ = ["R_BODY_OPTICAL", "PinholeCamera", "backproject", "render_depth", "rig_poses", "rotz"]
