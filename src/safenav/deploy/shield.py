"""Velocity-obstacle safety shield (as NavRL deploys one): correct the policy's velocity only when
it lies inside a velocity obstacle, by the smallest change that leaves all of them.

Velocity obstacle (truncated at the time horizon ``tau``): an obstacle at relative position ``p``
(obstacle - UAV), moving at ``u``, with combined radius ``R`` (obstacle + UAV + margin) forbids
every velocity ``v`` with

    min_{0 <= t <= tau} | p - (v - u) t | < R,

i.e. a collision within ``tau`` seconds if both keep their velocities. Already closer than ``R``,
``v`` is forbidden while it still approaches (``p . (v - u) > 0``). Standing cylinders (and pillars)
are tested in the horizontal plane.

If the policy's velocity ``v_des`` is outside every velocity obstacle it is returned **unchanged**.
Otherwise the shield returns the admissible candidate nearest to ``v_des``; candidates are scaled
copies of ``v_des``, a fixed fan of directions x speeds x climb rates, and, for the nearest
obstacles, the closest points on the boundary of their own velocity obstacle (cone side and
cut-off cap; the exact minimal correction when one obstacle is involved). When no candidate is
admissible it takes the one with the latest time to collision.

All functions are pure and batched over ``N`` (vector envs, or ``N = 1`` on board) and work in any
frame in which positions and velocities are given consistently; :func:`shield_action` works on the
env's observation and action directly (goal frame):

>>> import torch
>>> from safenav.deploy.shield import ShieldConfig, shield_action
>>> obs = {"state": torch.zeros(2, 8), "lidar": torch.zeros(2, 4, 36), "dynamic": torch.zeros(2, 5, 10)}
>>> obs["lidar"][0, :, [34, 35, 0, 1, 2]] = 0.8   # env 0: a wall ~0.8 m ahead (value (4 - d) / 4)
>>> action = torch.tensor([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
>>> safe, corrected = shield_action(obs, action, ShieldConfig())
>>> corrected.tolist(), bool(torch.equal(safe[1], action[1])), float(safe[0, 0]) < 0.5
([True, False], True, True)
"""

from __future__ import annotations

import contextlib
import functools
import math
from dataclasses import dataclass

import torch

from safenav.deploy import kernels
from safenav.envs.config import EnvConfig
from safenav.envs.sensors import FAR_POINT, RangeImageSpec
from safenav.envs.world import CUBOID_HEIGHT, DYN_WIDTHS

STATE_VELOCITY = slice(5, 8)
"""The velocity in the observation's ``state`` (goal frame, / v_max): after the goal direction
(3), horizontal distance (1) and height difference (1) (``SafeNavVectorEnv`` observation)."""
#: One vehicle on the CPU goes through the compiled kernel (the onboard runtime's path); False
#: within :func:`batched_arithmetic`.
_one_vehicle_kernel = True


@contextlib.contextmanager
def batched_arithmetic():
    """Within it, one vehicle is shielded by the torch path a batch takes, not by the compiled
    kernel: the same rules with different rounding (~1 ulp), which a flight amplifies within
    seconds. ``safenav render`` flies in it, so that its episode is the same flight, bit for bit,
    as that episode in ``safenav eval``'s batch (tests/test_render_matches_eval.py)."""
    global _one_vehicle_kernel
    before, _one_vehicle_kernel = _one_vehicle_kernel, False
    try:
        yield
    finally:
        _one_vehicle_kernel = before


def _kernel_for(n: int, device: torch.device, compiled: bool | None = None) -> bool:
    """Whether ``n`` vehicles on ``device`` go through the compiled kernel: one vehicle on the
    CPU where Numba is there, unless ``compiled`` says otherwise (None: outside
    :func:`batched_arithmetic`)."""
    use = _one_vehicle_kernel if compiled is None else compiled
    return use and n == 1 and device.type == "cpu" and kernels.AVAILABLE


@dataclass(frozen=True)
class ShieldConfig:
    """Parameters of the velocity-obstacle shield."""

    time_horizon: float = 1.5
    """Velocity obstacles are truncated at this many seconds (``tau``)."""
    uav_radius: float = 0.3
    """The UAV's collision radius (m), as in the env."""
    margin: float = 0.1
    """Extra clearance (m) added to every combined radius."""
    mover_margin: float = 0.0
    """More clearance (m) from tracked moving obstacles only (beyond NavRL's shield): they turn at
    full speed when they reach a local goal, which no constant-velocity forecast sees coming."""
    v_max: float = 2.0
    """Velocity bound per axis (m/s); candidates are clipped to ``[-v_max, v_max]^3``."""
    lidar_range: float = 4.0
    """Range of the range image (m): beams at this distance are free."""
    lidar_v_angles: tuple[float, ...] = (-10.0, 0.0, 10.0, 20.0)
    """Beam elevations of the range image, degrees."""
    lidar_h_beams: int = 36
    """Beams per row of the range image."""
    max_static: int = 24
    """Only the nearest this many beam hits are treated as obstacles (the rest cannot matter)."""
    projected: int = 8
    """Nearest obstacles whose own minimal boundary corrections become candidates."""
    n_azimuth: int = 16
    """Directions of the fixed candidate fan."""
    speed_fractions: tuple[float, ...] = (1 / 3, 2 / 3, 1.0)
    """Horizontal speeds of the fan, as fractions of ``v_max``."""
    climb_fractions: tuple[float, ...] = (-0.5, 0.0, 0.5)
    """Vertical speeds of the fan, as fractions of ``v_max``."""
    map_beams: int = 72
    """Beams of the map scan (:func:`map_scan_hits`, ``MemoryShield(map_scan=True)``): 5° apart."""
    map_static: int = 24
    """Only the nearest this many hits of the map scan are treated as obstacles."""
    response_time: float = 0.0
    """The vehicle's velocity time constant (s) as the shield models it (beyond NavRL's shield):
    0 = a commanded velocity is flown at once (NavRL's assumption). Above 0, each candidate is
    tested from where the vehicle will really be: it keeps drifting along its current velocity
    ``v0`` while it turns to the candidate ``v``, by ``(v0 - v) T`` for a first-order tracker of
    time constant ``T`` (more while ``max_acceleration`` limits the turn), so the velocity
    obstacles of a fast vehicle are shifted towards it (:func:`response_offset`)."""
    max_acceleration: float = math.inf
    """With ``response_time``: the tracker's acceleration limit (m/s^2; the env's 3)."""
    brake_time: float = 0.0
    """The braking cap (beyond NavRL's shield): 0 = off. Above 0, the velocity the shield returns
    is scaled down until its closing speed ``c`` on every static obstacle is one the vehicle can
    still stop from before the combined radius, for a first-order tracker of this time constant
    (s) and ``brake_acceleration``: ``c T + c^2 / (2 a) <= d`` with ``d`` the distance beyond the
    combined radius (:func:`braking_speed`). It slows the vehicle in clutter, where the velocity
    obstacles alone let it fly at full speed past pillars it then drifts into. Where the slower
    velocity would enter a moving obstacle's velocity obstacle, the velocity is left as it was.
    ``ShieldConfig.braking_of(env_config)`` sets the env's 0.4 s."""
    brake_slide: bool = False
    """With ``brake_time``: remove only the excess closing speed on each static obstacle (the
    velocity keeps its component along the pillar and slides past it: :func:`braking_slide`)
    instead of scaling the whole velocity down, which stops a vehicle that keeps asking to fly
    into a pillar it is close to, for good. The slid velocity is kept only where it enters no
    velocity obstacle; elsewhere the scaled one is."""
    brake_acceleration: float = 2.0
    """With ``brake_time``: the deceleration (m/s^2) the cap counts on (the env's tracker allows 3;
    2 measured better on the validation maps, docs/deployment.md)."""
    z_min: float = 0.2
    """With ``brake_time`` and the vehicle's altitude known (:class:`MemoryShield`): the ground,
    below which the env counts a collision; the cap limits the descent speed as for a wall."""
    z_max: float = 4.0
    """Likewise the ceiling."""
    keep_moving: float = 0.0
    """The candidate choice (beyond NavRL's shield): 0 = the admissible candidate nearest the
    policy's velocity (NavRL's). Above 0, where that one keeps less than this fraction of the
    policy's horizontal speed, the nearest admissible candidate that keeps at least that fraction
    and does not turn back (horizontal component along the policy's >= 0) is taken, if one
    exists. Why: in a pocket among pillars the nearest admissible velocity is a hover (any
    sideways velocity is further from a goal-ward ``v_des`` than standing still), and a policy
    that pursues the goal asks for the way through again at every step, so nothing moves the
    vehicle round. Measured on validation (five policies trained behind the shield): K 0.5 and
    1.0 change neither timeouts nor success, 0.5 adds crashes with movers; off by default
    (docs/csac-v1.md, "A shield that keeps moving")."""

    @staticmethod
    def response_of(cfg: EnvConfig) -> dict[str, float]:
        """``response_time`` and ``max_acceleration`` as the env's velocity tracker has them."""
        return {
            "response_time": cfg.velocity_time_constant,
            "max_acceleration": cfg.max_acceleration,
        }

    @staticmethod
    def braking_of(cfg: EnvConfig) -> dict[str, float]:
        """``brake_time`` as the env's velocity tracker has it (the braking cap on)."""
        return {"brake_time": cfg.velocity_time_constant}

    @staticmethod
    def for_env(cfg: EnvConfig, **overrides) -> ShieldConfig:
        base = dict(uav_radius=cfg.uav_radius, v_max=cfg.v_max, lidar_range=cfg.lidar_range,
                    lidar_v_angles=tuple(cfg.lidar_v_angles), lidar_h_beams=cfg.lidar_h_beams,
                    z_min=cfg.z_min, z_max=cfg.z_max)  # fmt: skip
        return ShieldConfig(**{**base, **overrides})


def response_offset(v0: torch.Tensor, v: torch.Tensor, cfg: ShieldConfig) -> torch.Tensor:
    """How far the vehicle ends up from the straight path of a commanded velocity ``v`` ``(N, C,
    3)`` when it flies ``v0`` ``(N, 3)`` now: the integral of ``v(t) - v`` of a first-order
    tracker (time constant ``T = cfg.response_time``) whose acceleration is limited to ``a``:
    ``dv T`` while ``|dv| <= a T``, else ``(|dv|^2 - (a T)^2) / (2 a) + a T^2`` along ``dv``."""
    dv = v0[:, None, :] - v
    n = dv.norm(dim=-1, keepdim=True)
    t, a = cfg.response_time, cfg.max_acceleration
    if math.isinf(a):
        return dv * t
    knee = a * t
    far = (n * n - knee * knee) / (2 * a) + knee * t
    return torch.where(n <= knee, dv * t, dv / n.clamp(min=1e-9) * far)


def braking_speed(d: torch.Tensor, cfg: ShieldConfig) -> torch.Tensor:
    """The largest closing speed ``c`` from which a vehicle with velocity time constant ``T =
    cfg.brake_time`` and deceleration ``a = cfg.brake_acceleration`` stops within ``d`` metres:
    the root of ``c T + c^2 / (2 a) = d`` (0 where ``d <= 0``)."""
    t, a = cfg.brake_time, cfg.brake_acceleration
    d = d.clamp(min=0.0)
    return a * (torch.sqrt(t * t + 2.0 * d / a) - t)


def braking_cap(v: torch.Tensor, rel: torch.Tensor, valid: torch.Tensor, planar: torch.Tensor,
                radius: torch.Tensor, cfg: ShieldConfig) -> tuple[torch.Tensor, torch.Tensor]:  # fmt: skip
    """Scale velocities ``v`` ``(N, 3)`` down so that the closing speed on each static obstacle
    (``rel`` ``(N, M, 3)``, columns ``planar`` measured in the horizontal plane) is at most
    :func:`braking_speed` of its distance beyond ``radius`` ``(N, M)``. Scaling a velocity down
    never enters a static obstacle's velocity obstacle (its path is a prefix of the unscaled
    one). Returns ``(v, capped)``."""
    w = torch.ones_like(rel)
    w[..., 2] = (~planar).to(v.dtype)
    p = rel * w
    dist = p.norm(dim=-1).clamp(min=1e-6)
    closing = (p * v[:, None, :]).sum(-1) / dist  # (N, M)
    allowed = braking_speed(dist - radius, cfg)
    ratio = torch.where(valid & (closing > allowed), allowed / closing.clamp(min=1e-9), 1.0)
    scale = ratio.amin(-1) if ratio.shape[-1] else torch.ones_like(v[:, 0])
    return v * scale[:, None], scale < 1.0


def braking_slide(v: torch.Tensor, rel: torch.Tensor, valid: torch.Tensor, planar: torch.Tensor,
                  radius: torch.Tensor, cfg: ShieldConfig,
                  passes: int = 4) -> tuple[torch.Tensor, torch.Tensor]:  # fmt: skip
    """:func:`braking_cap` by removal rather than scaling: ``passes`` times, the closing speed on
    the obstacle whose closing speed most exceeds :func:`braking_speed` of its distance is cut
    to that speed, along the direction to it, so the velocity keeps its other components (it
    slides along the pillar); what still exceeds after the passes is then scaled as
    :func:`braking_cap` does, so every closing speed ends within its bound. Returns ``(v,
    changed)``."""
    w = torch.ones_like(rel)
    w[..., 2] = (~planar).to(v.dtype)
    p = rel * w
    dist = p.norm(dim=-1).clamp(min=1e-6)
    unit = p / dist[..., None]  # (N, M, 3) towards each obstacle
    allowed = braking_speed(dist - radius, cfg)
    out = v
    for _ in range(passes if rel.shape[1] else 0):
        closing = (unit * out[:, None, :]).sum(-1)
        excess = torch.where(valid, (closing - allowed).clamp(min=0.0), 0.0)
        worst = excess.argmax(-1)
        cut = excess.gather(1, worst[:, None])  # (N, 1)
        out = out - cut * unit[torch.arange(out.shape[0], device=v.device), worst]
    out, _ = braking_cap(out, rel, valid, planar, radius, cfg)
    return out, (out != v).any(-1)


def altitude_cap(v: torch.Tensor, altitude: torch.Tensor,
                 cfg: ShieldConfig) -> tuple[torch.Tensor, torch.Tensor]:  # fmt: skip
    """Limit the vertical speed of ``v`` ``(N, 3)`` towards the ground (``cfg.z_min``) and the
    ceiling (``cfg.z_max``) to :func:`braking_speed` of the vehicle's ``altitude`` ``(N,)``
    distance to them beyond ``cfg.margin``. Returns ``(v, clamped)``."""
    z = altitude.to(v.dtype)
    down = braking_speed(z - cfg.z_min - cfg.margin, cfg)
    up = braking_speed(cfg.z_max - z - cfg.margin, cfg)
    vz = torch.minimum(torch.maximum(v[:, 2], -down), up)
    return torch.cat([v[:, :2], vz[:, None]], 1), vz != v[:, 2]


def _vo_test(v: torch.Tensor, rel: torch.Tensor, ovel: torch.Tensor, radius: torch.Tensor,
             valid: torch.Tensor, planar: torch.Tensor, tau: float,
             offset: torch.Tensor | None = None,
             need_ttc: bool = True) -> tuple[torch.Tensor, torch.Tensor | None]:  # fmt: skip
    """For candidates ``v`` ``(N, C, 3)``: inside-any-VO ``(N, C)`` and min time to collision
    (None with ``need_ttc=False``: a third of the work, where only the first is used).

    ``offset`` ``(N, C, 3)``: how far each candidate leaves the vehicle from its straight path
    (:func:`response_offset`). The candidate is then tested from the shifted start, and the drift
    there (the segment from now to the shifted start) must clear every obstacle too; an obstacle
    the vehicle is already inside is left as without the offset (moving away is admissible)."""
    vr = v[:, :, None, :] - ovel[:, None, :, :]  # (N, C, M, 3)
    p0 = rel[:, None, :, :]
    p = p0 if offset is None else p0 - offset[:, :, None, :]
    # Planar obstacles (columns) are tested in the horizontal plane: z weighs 0 in the products.
    wz = torch.ones_like(rel)
    wz[..., 2] = (~planar).to(v.dtype)
    w = wz[:, None]  # (N, 1, M, 3)
    pw = p * w  # p with z dropped where planar
    pv = (pw * vr).sum(-1)
    vv = (vr * vr * w).sum(-1).clamp(min=1e-12)
    pp = (pw * p).sum(-1)
    r2 = (radius * radius)[:, None, :]
    t = (pv / vv).clamp(0.0, tau)
    d2 = pp - 2 * t * pv + t * t * vv  # |p - vr t|^2
    penetrating = pp < r2
    if offset is None:
        inside = torch.where(penetrating, pv > 0, d2 < r2) & valid[:, None, :]
    else:
        o = offset[:, :, None, :] * w
        po, oo = (p0 * o).sum(-1), (o * o).sum(-1).clamp(min=1e-12)
        pp0 = (p0 * p0 * w).sum(-1)
        s = (po / oo).clamp(0.0, 1.0)
        drift_hit = pp0 - 2 * s * po + s * s * oo < r2  # |p0 - s o|^2 < R^2 on the way
        now_in = pp0 < r2
        leaving = (p0 * w * vr).sum(-1) <= 0
        inside = torch.where(now_in, ~leaving, drift_hit | (d2 < r2)) & valid[:, None, :]
    if not need_ttc:
        return inside.any(-1), None
    # Time to collision: smallest t >= 0 with |p - vr t| = R (inf if none / receding).
    disc = pv * pv - vv * (pp - r2)
    ttc = (pv - disc.clamp(min=0).sqrt()) / vv
    ttc = torch.where(penetrating, torch.where(pv > 0, 0.0, math.inf), ttc)
    ttc = torch.where((disc < 0) | (pv <= 0) | ~valid[:, None, :], math.inf, ttc.clamp(min=0))
    return inside.any(-1), ttc.amin(-1) if ttc.shape[-1] else torch.full(inside.shape[:2], math.inf)


def _boundary_candidates(v_des, rel, ovel, radius, valid, planar, tau, k, dist=None):
    """Closest points on the VO boundary (cone side and cap) of the ``k`` nearest obstacles
    (nearest by ``dist`` ``(N, M)`` if given, else by ``|rel|``)."""
    n, m = rel.shape[:2]
    k = min(k, m)
    dist = torch.where(valid, rel.norm(dim=-1) if dist is None else dist, math.inf)
    _, idx = nearest(dist, k)
    g3 = lambda t: torch.gather(t, 1, idx[..., None].expand(-1, -1, 3))  # noqa: E731
    p, u = g3(rel), g3(ovel)
    r = torch.gather(radius, 1, idx)
    flat = torch.gather(planar, 1, idx)[..., None]
    mask = p.new_tensor([1.0, 1.0, 0.0])
    p = torch.where(flat, p * mask, p)
    vr = v_des[:, None, :] - u
    vr_z = vr[..., 2:3]
    vr = torch.where(flat, vr * mask, vr)
    dist = p.norm(dim=-1, keepdim=True).clamp(min=1e-6)
    ph = p / dist
    # Cone side: rotate vr's direction just outside the cone of half-angle alpha about ph. Inside
    # the obstacle (r >= dist) alpha is pi/2 + 0.03: slightly receding, not tangential, so that
    # the candidate is admissible beyond rounding.
    alpha = torch.asin((r[..., None] / dist).clamp(max=1.0)) + 0.03
    a = (vr * ph).sum(-1, keepdim=True)
    radial = vr - a * ph
    rho = radial.norm(dim=-1, keepdim=True)
    side = torch.cross(ph, ph.new_tensor([0.0, 0.0, 1.0]).expand_as(ph), dim=-1)
    side = torch.where(
        side.norm(dim=-1, keepdim=True) < 1e-6, ph.new_tensor([0.0, 1.0, 0.0]).expand_as(ph), side
    )
    rh = torch.where(
        rho > 1e-6, radial / rho.clamp(min=1e-9), side / side.norm(dim=-1, keepdim=True)
    )
    s = (a * torch.cos(alpha) + rho * torch.sin(alpha)).clamp(min=0.0)
    leg = s * (torch.cos(alpha) * ph + torch.sin(alpha) * rh)
    # Cut-off cap: push radially out of the sphere of radius R / tau around p / tau.
    c = p / tau
    w = vr - c
    wn = w.norm(dim=-1, keepdim=True)
    wh = torch.where(wn > 1e-6, w / wn.clamp(min=1e-9), -ph)
    cap = c + wh * (r[..., None] / tau) * 1.05
    # Planar obstacles leave the vertical component as it was.
    leg = torch.where(flat, leg + vr_z * ph.new_tensor([0.0, 0.0, 1.0]), leg)
    cap = torch.where(flat, cap + vr_z * ph.new_tensor([0.0, 0.0, 1.0]), cap)
    return torch.cat([u + leg, u + cap], dim=1)  # (N, 2k, 3)


def nearest(dist: torch.Tensor, k: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The ``k`` smallest of ``dist`` ``(N, M)`` along the last axis, ties to the lower index (a
    stable sort, unlike ``torch.topk``), so that the compiled one-vehicle path picks the same."""
    values, idx = torch.sort(dist, dim=-1, stable=True)
    return values[..., :k], idx[..., :k]


@functools.lru_cache(maxsize=16)
def _fan(cfg: ShieldConfig, device, dtype) -> torch.Tensor:
    az = torch.arange(cfg.n_azimuth, device=device, dtype=dtype) * (2 * math.pi / cfg.n_azimuth)
    sp = torch.tensor(cfg.speed_fractions, device=device, dtype=dtype) * cfg.v_max
    cl = torch.tensor(cfg.climb_fractions, device=device, dtype=dtype) * cfg.v_max
    a, s, c = torch.meshgrid(az, sp, cl, indexing="ij")
    return torch.stack([s * torch.cos(a), s * torch.sin(a), c], -1).reshape(-1, 3)


def velocity_obstacle_shield(
    v_des: torch.Tensor,
    rel: torch.Tensor,
    obs_vel: torch.Tensor,
    radius: torch.Tensor,
    valid: torch.Tensor,
    planar: torch.Tensor | None = None,
    cfg: ShieldConfig = ShieldConfig(),
    compiled: bool | None = None,
    dist: torch.Tensor | None = None,
    v_now: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Shield desired velocities ``v_des`` ``(N, 3)`` against ``M`` obstacles per env.

    Args:
        rel: ``(N, M, 3)`` obstacle position - UAV position; obs_vel: ``(N, M, 3)`` their velocities.
        radius: ``(N, M)`` combined radii (obstacle + UAV + margin); valid: ``(N, M)`` mask.
        planar: ``(N, M)`` obstacles that span all altitudes (tested in the horizontal plane).
        dist: ``(N, M)`` distances that rank the obstacles for the boundary candidates (default
            ``|rel|``).
        v_now: ``(N, 3)`` the vehicle's velocity now, for ``cfg.response_time > 0`` (else unused).

    Returns ``(v, corrected)``: the shielded velocities ``(N, 3)`` (``v_des`` itself, bit for bit,
    where it was admissible) and which envs were corrected ``(N,)``.

    One vehicle on the CPU (the onboard runtime) goes through the compiled kernel
    (:mod:`safenav.deploy.kernels`, same rules, ~10x faster) unless ``compiled=False``.
    """
    n, dev, dt = v_des.shape[0], v_des.device, v_des.dtype
    if planar is None:
        planar = torch.zeros_like(valid)
    if rel.shape[1] == 0:
        return v_des.clone(), torch.zeros(n, dtype=torch.bool, device=dev)
    tau, vm = cfg.time_horizon, cfg.v_max
    lagged = cfg.response_time > 0
    if lagged and v_now is None:
        raise ValueError("a shield with response_time > 0 needs the vehicle's velocity (v_now)")
    if _kernel_for(n, dev, compiled) and not lagged and not cfg.keep_moving:
        return _shield_one_compiled(v_des, rel, obs_vel, radius, valid, planar, cfg, dist)
    offset = response_offset(v_now, v_des[:, None, :], cfg) if lagged else None
    inside_des, _ = _vo_test(v_des[:, None, :], rel, obs_vel, radius, valid, planar, tau, offset,
                             need_ttc=False)  # fmt: skip
    corrected = inside_des[:, 0]
    out = v_des.clone()
    if not bool(corrected.any()):
        return out, corrected
    # Only the envs that need a correction go through the candidate search.
    rows = corrected.nonzero().squeeze(1)
    v_des, rel, obs_vel = v_des[rows], rel[rows], obs_vel[rows]
    radius, valid, planar = radius[rows], valid[rows], planar[rows]
    dist = dist[rows] if dist is not None else None
    v_now = v_now[rows] if lagged else None
    scales = v_des.new_tensor([0.75, 0.5, 0.25, 0.0])
    cands = torch.cat([
        v_des[:, None, :] * scales[None, :, None],
        _fan(cfg, dev, dt)[None].expand(rows.shape[0], -1, -1),
        _boundary_candidates(v_des, rel, obs_vel, radius, valid, planar, tau, cfg.projected, dist),
    ], dim=1).clamp(-vm, vm)  # fmt: skip
    offsets = response_offset(v_now, cands, cfg) if lagged else None
    inside, _ = _vo_test(cands, rel, obs_vel, radius, valid, planar, tau, offsets, need_ttc=False)
    cost = (cands - v_des[:, None, :]).square().sum(-1)
    best = torch.argmin(torch.where(inside, math.inf, cost), dim=-1)
    if cfg.keep_moving > 0:
        best = _keep_moving(best, cands, v_des, inside, cost, cfg.keep_moving)
    # Nothing admissible: latest time to collision, then nearest to v_des. The times are computed
    # for those envs only (row by row the same arithmetic as for all of them).
    choice = best
    stuck = inside.all(-1).nonzero().squeeze(1)
    if stuck.numel():
        _, ttc = _vo_test(cands[stuck], rel[stuck], obs_vel[stuck], radius[stuck], valid[stuck],
                          planar[stuck], tau, offsets[stuck] if lagged else None)  # fmt: skip
        fallback = torch.argmax(ttc.clamp(max=1e6) - 1e-3 * cost[stuck], dim=-1)
        choice = best.clone()
        choice[stuck] = fallback
    out[rows] = torch.gather(cands, 1, choice[:, None, None].expand(-1, 1, 3))[:, 0]
    return out, corrected


def _keep_moving(best, cands, v_des, inside, cost, fraction: float) -> torch.Tensor:
    """``ShieldConfig.keep_moving``: where the candidate ``best`` ``(N,)`` keeps less than
    ``fraction`` of ``v_des``'s horizontal speed, the nearest admissible one that keeps at least
    that and does not turn back, if there is one."""
    h = cands[..., :2]
    speed = h.norm(dim=-1)  # (N, C)
    need = fraction * v_des[:, :2].norm(dim=-1, keepdim=True)  # (N, 1)
    moving = ~inside & (speed >= need) & ((h * v_des[:, None, :2]).sum(-1) >= 0)
    other = torch.argmin(torch.where(moving, cost, math.inf), dim=-1)
    slow = torch.gather(speed, 1, best[:, None])[:, 0] < need[:, 0]
    return torch.where(slow & moving.any(-1), other, best)


def _shield_one_compiled(v_des, rel, obs_vel, radius, valid, planar, cfg, dist=None):
    """velocity_obstacle_shield for ``N = 1`` through :func:`safenav.deploy.kernels.shield_kernel`."""
    f64 = lambda t: t[0].detach().double().contiguous().numpy()  # noqa: E731
    k = min(cfg.projected, rel.shape[1])
    # The nearest obstacles are picked exactly as _boundary_candidates picks them.
    dist = torch.where(valid, rel.norm(dim=-1) if dist is None else dist, math.inf)
    idx = nearest(dist, k)[1][0].numpy()
    fan = _fan(cfg, torch.device("cpu"), torch.float64).numpy()
    v, corrected = kernels.shield_kernel(
        f64(v_des), f64(rel), f64(obs_vel), f64(radius), valid[0].numpy(), planar[0].numpy(),
        idx, fan, float(cfg.time_horizon), float(cfg.v_max),
    )  # fmt: skip
    if not corrected:
        return v_des.clone(), torch.zeros(1, dtype=torch.bool)
    return torch.from_numpy(v).to(v_des.dtype)[None], torch.ones(1, dtype=torch.bool)


@functools.lru_cache(maxsize=16)
def _beams(spec: RangeImageSpec, device) -> tuple[torch.Tensor, torch.Tensor]:
    """Unit directions ``(V * H, 3)`` of the range image's beams and which point level or up."""
    az = spec.azimuths(device)  # (H,)
    el = spec.elevations(device)  # (V,)
    dirs = torch.stack([
        torch.cos(el)[:, None] * torch.cos(az)[None, :],
        torch.cos(el)[:, None] * torch.sin(az)[None, :],
        torch.sin(el)[:, None].expand(-1, az.shape[0]),
    ], -1).reshape(-1, 3)  # fmt: skip
    upward = (el >= 0)[:, None].expand(-1, az.shape[0]).reshape(-1)
    return dirs, upward


def static_obstacles_from_ranges(
    ranges: torch.Tensor, spec: RangeImageSpec, k: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The ``k`` nearest beam hits of range images ``(N, V, H)`` (metres) as points relative to
    the sensor, in the sensor's heading frame (column 0 along +x): ``(rel, valid, planar)``.

    Hits of level and upward beams are columns (``planar``): static obstacles are pillars standing
    on the ground, so the column extends below the hit. Hits of downward beams may be the ground and
    stay points."""
    rel, valid, planar, _ = _static_hits(ranges, spec, k)
    return rel, valid, planar


def _static_hits(ranges, spec, k):
    """static_obstacles_from_ranges plus the hits' distances (inf where none)."""
    n = ranges.shape[0]
    dirs, upward = _beams(spec, ranges.device)
    d = ranges.reshape(n, -1)
    k = min(k, d.shape[1])
    dsel, idx = nearest(torch.where(d < spec.max_range - 1e-3, d, math.inf), k)
    valid = torch.isfinite(dsel)
    rel = dirs[idx] * torch.where(valid, dsel, 0.0)[..., None]
    return rel, valid, upward[idx], dsel


def dynamic_obstacles_from_features(dynamic: torch.Tensor, lidar_range: float, v_max: float):
    """Decode the env's ``dynamic`` features ``(N, k, 10)`` back into geometry in the goal frame:
    ``(rel, vel, radius, valid, planar)``; radius is the obstacle's own (no UAV radius)."""
    rel, vel, radius, valid, planar, _ = _decode_dynamic(dynamic, lidar_range, v_max)
    return rel, vel, radius, valid, planar


def _decode_dynamic(dynamic, lidar_range, v_max):
    """dynamic_obstacles_from_features plus the obstacles' distances."""
    unit = dynamic[..., 0:3]
    d2 = dynamic[..., 3] * lidar_range
    dz = dynamic[..., 4] * lidar_range
    dist = torch.sqrt(d2 * d2 + dz * dz)
    rel = unit * dist[..., None]
    vel = dynamic[..., 5:8] * v_max
    width = (dynamic[..., 8] * (len(DYN_WIDTHS) - 1) + 1.0) * DYN_WIDTHS[0]
    cuboid = dynamic[..., 9] > 0.5
    half = width / 2
    radius = torch.where(cuboid, torch.sqrt(2 * half * half + (CUBOID_HEIGHT / 2) ** 2), half)
    valid = dynamic.abs().sum(-1) > 0
    return rel, vel, radius, valid, ~cuboid, dist


@functools.lru_cache(maxsize=16)
def _spec(cfg: ShieldConfig) -> RangeImageSpec:
    return RangeImageSpec(
        h_beams=cfg.lidar_h_beams, v_angles=tuple(cfg.lidar_v_angles), max_range=cfg.lidar_range
    )


def shield_action(
    obs: dict[str, torch.Tensor], action: torch.Tensor, cfg: ShieldConfig
) -> tuple[torch.Tensor, torch.Tensor]:
    """Shield normalised goal-frame actions ``(N, 3)`` in ``[-1, 1]`` using the env's own
    observation (``state``, ``lidar``, ``dynamic`` tensors, batched). Returns ``(action,
    corrected)``; unchanged actions are returned bit for bit.

    Static obstacles are the range image's beam hits; moving obstacles are the tracked ones,
    decoded from the ``dynamic`` features. This is exactly what the onboard runtime runs. Rows
    after the current image's (a memory image, ``EnvConfig.lidar_memory``) are not read.
    """
    spec = _spec(cfg)
    lidar, dyn = obs["lidar"][:, : len(cfg.lidar_v_angles)], obs["dynamic"]
    plain = cfg.response_time == 0 and cfg.brake_time == 0 and not cfg.keep_moving  # the kernel's
    if plain and _kernel_for(action.shape[0], action.device):
        return _shield_action_compiled(lidar, dyn, action, cfg, spec)
    ranges = cfg.lidar_range * (1.0 - lidar.to(action.dtype))
    rel, valid, planar, dist = _static_hits(ranges, spec, cfg.max_static)
    return _shield_static_and_tracked(rel, valid, planar, dist, dyn, action, cfg, obs.get("state"))


def _shield_static_and_tracked(rel, valid, planar, dist, dyn, action, cfg: ShieldConfig,
                               state: torch.Tensor | None = None,
                               altitude: torch.Tensor | None = None):  # fmt: skip
    """shield_action's search once the static obstacles are chosen: they ``(N, M, 3)`` in the
    heading frame (with ``valid``, ``planar``, ``dist``) and the tracked ones decoded from ``dyn``."""
    base = cfg.uav_radius + cfg.margin
    m = rel.shape[1]  # the static obstacles are the first m columns; tracked ones follow
    vel = torch.zeros_like(rel)
    radius = torch.full_like(rel[..., 0], base)
    if bool((dyn != 0).any()):  # tracked moving obstacles (rows of zeros are empty slots)
        d_rel, d_vel, d_rad, d_valid, d_planar, d_dist = _decode_dynamic(
            dyn.to(action.dtype), cfg.lidar_range, cfg.v_max)  # fmt: skip
        rel, vel = torch.cat([rel, d_rel], 1), torch.cat([vel, d_vel], 1)
        radius = torch.cat([radius, d_rad + (base + cfg.mover_margin)], 1)
        valid, planar = torch.cat([valid, d_valid], 1), torch.cat([planar, d_planar], 1)
        dist = torch.cat([dist, d_dist], 1)
    v_now = None
    if cfg.response_time > 0:  # the observation's velocity, in the same (goal) frame as actions
        v_now = state[:, STATE_VELOCITY].to(action.dtype) * cfg.v_max
    v, corrected = velocity_obstacle_shield(
        action * cfg.v_max, rel, vel, radius, valid, planar, cfg, dist=dist, v_now=v_now
    )
    if cfg.brake_time > 0:
        slow, capped = braking_cap(v, rel[:, :m], valid[:, :m], planar[:, :m], radius[:, :m], cfg)
        if cfg.brake_slide:  # slide along the pillar where that enters no velocity obstacle
            slid, _ = braking_slide(v, rel[:, :m], valid[:, :m], planar[:, :m], radius[:, :m], cfg)
            into, _ = _vo_test(slid[:, None], rel, vel, radius, valid, planar, cfg.time_horizon,
                               need_ttc=False)  # fmt: skip
            slow = torch.where((capped & ~into[:, 0])[:, None], slid, slow)
        # Slowing down may leave a moving obstacle's path too late: there, the velocity stays.
        into, _ = _vo_test(slow[:, None], rel, vel, radius, valid, planar, cfg.time_horizon,
                           need_ttc=False)  # fmt: skip
        capped = capped & ~into[:, 0]
        v = torch.where(capped[:, None], slow, v)
        corrected = corrected | capped
        if altitude is not None:
            v, clamped = altitude_cap(v, altitude, cfg)
            corrected = corrected | clamped
    out = torch.where(corrected[:, None], (v / cfg.v_max).clamp(-1.0, 1.0), action)
    return out, corrected


def _shield_action_compiled(lidar, dyn, action, cfg: ShieldConfig, spec: RangeImageSpec):
    """shield_action for one vehicle in one call of :func:`safenav.deploy.kernels.shield_obs_kernel`
    (the same float32 decoding, the same stable nearest-first selection, then the VO search)."""
    dirs, upward = _beams(spec, torch.device("cpu"))
    out, corrected = kernels.shield_obs_kernel(
        action[0].detach().float().contiguous().numpy(),
        lidar[0].detach().float().contiguous().numpy().reshape(-1),
        dyn[0].detach().float().contiguous().numpy(),
        dirs.numpy(), upward.numpy(), _fan(cfg, torch.device("cpu"), torch.float64).numpy(),
        min(cfg.max_static, dirs.shape[0]), cfg.projected, float(cfg.lidar_range), float(cfg.v_max),
        float(cfg.uav_radius + cfg.margin), float(cfg.uav_radius + cfg.margin + cfg.mover_margin),
        float(DYN_WIDTHS[0]), len(DYN_WIDTHS), float(CUBOID_HEIGHT),
        float(cfg.time_horizon), float(spec.max_range - 1e-3),
    )  # fmt: skip
    if not corrected:
        return action.clone(), torch.zeros(1, dtype=torch.bool)
    return torch.from_numpy(out)[None].to(action.dtype), torch.ones(1, dtype=torch.bool)


def env_shield(env, obs: dict[str, torch.Tensor], action: torch.Tensor) -> torch.Tensor:
    """The shield as evaluation calls it: ``action = env_shield(env, obs, action)`` for a
    :class:`~safenav.envs.nav.SafeNavVectorEnv` with torch output (its ``cfg`` sets radii, v_max
    and the beam layout). With a range-image history it reads the current image (the first rows)."""
    obs = {**obs, "lidar": obs["lidar"][:, : len(env.cfg.lidar_v_angles)]}
    out, _ = shield_action(obs, action, ShieldConfig.for_env(env.cfg))
    return out


def map_scan_hits(heights: torch.Tensor, grid_origin: float, grid_size: int, resolution: float,
                  pos: torch.Tensor, yaw: torch.Tensor, cfg: ShieldConfig,
                  map_index: torch.Tensor | None = None):  # fmt: skip
    """The map scan (beyond NavRL): ``cfg.map_beams`` level beams cast on the height map from the
    UAV's lower extent (its altitude less ``uav_radius + margin``, at least 5 cm above the
    ground), to the range image's range. A beam stops at the first column whose top rises above
    that level: every pillar the UAV could strike passing over or beside it, whether or not the
    range image's beams see it now. Returns the nearest ``cfg.map_static`` hits as the range
    image's are (:func:`static_obstacles_from_ranges`, plus distances): columns in the heading frame.

    ``heights``: the quantised height map(s) the range image is cast on (the env's
    ``heights`` with ``map_index`` its ``world_idx``; on board the runtime's ``map.cast_map``);
    ``pos`` ``(N, 3)``, ``yaw`` ``(N,)`` the heading frame's yaw."""
    from safenav.envs.sensors import raycast_height_map

    spec = RangeImageSpec(h_beams=cfg.map_beams, v_angles=(0.0,), max_range=cfg.lidar_range,
                          resolution=resolution)  # fmt: skip
    low = torch.cat([pos[:, :2], (pos[:, 2:] - (cfg.uav_radius + cfg.margin)).clamp(min=0.05)], 1)
    ranges = raycast_height_map(heights, grid_origin, grid_size, low.float(), yaw.float(), spec,
                                map_index)  # fmt: skip
    rel, valid, planar, dist = _static_hits(ranges.to(pos.dtype), spec, cfg.map_static)
    return rel, valid, planar, dist


class MemoryShield:
    """The shield with a memory of the range image (beyond NavRL's shield, which sees only the
    current image): the static obstacles are the beam hits of the last ``memory`` images, the
    current one included, kept where they were seen in the world and brought into the current
    heading frame each step.

    Why: a pillar whose top is a little below the UAV is seen only by the lowest beam (−10°), and
    leaves it as the UAV closes in (at horizontal range ``r`` once the top is more than
    ``r tan 10°`` below), so a memoryless shield forgets the pillar just before the UAV is over
    it; most of the policies' collisions with pillars are of this kind (docs/csac-v1.md). The
    remembered hit lies on the pillar's side within a few decimetres of its top, inside the
    combined radius of a UAV passing over it.

    It needs the vehicle's position and heading (odometry on board; the env's state in the
    simulator) and keeps one memory per env: ``shield = MemoryShield(10)`` and then ``action =
    shield(env, obs, action)`` for a :class:`~safenav.envs.nav.SafeNavVectorEnv` with torch
    output, as :func:`env_shield` is called. An env whose episode has just begun
    (``env.steps == 0``) forgets what it saw before. The onboard runtime, which has no env, calls
    :meth:`apply` with its odometry (``RuntimeConfig.shield_memory``). ``memory=1`` gives :func:`env_shield`'s
    actions to rounding (its points go to the world frame and back; tested). Static hits beyond the range image's range are not obstacles (as the current
    image's misses); the nearest ``max_static`` points of all remembered ones are (default: the
    config's ``max_static`` times ``min(memory, 4)``: one pillar leaves a hit in every image).

    ``map_scan=True`` adds the hits of :func:`map_scan_hits` on the height map the range image is
    cast from (the env's; on board the map the runtime builds from depth images): the pillars at
    the UAV's lower extent, seen or not by the image's beams now.
    """

    def __init__(self, memory: int, cfg: ShieldConfig | None = None, max_static: int | None = None,
                 map_scan: bool = False, mover_margin: float = 0.0,
                 response: bool = False, brake: bool | str = False,
                 keep_moving: float = 0.0):  # fmt: skip
        if not 1 <= memory <= 100:
            raise ValueError(f"memory must lie in [1, 100] range images, got {memory}")
        if not 0.0 <= mover_margin <= 2.0:
            raise ValueError(f"mover_margin must lie in [0, 2] m, got {mover_margin}")
        self.memory, self.cfg, self.max_static = int(memory), cfg, max_static
        self.map_scan = bool(map_scan)
        self.mover_margin = float(mover_margin)  # with the env's config (cfg None) only
        if not 0.0 <= keep_moving <= 1.0:
            raise ValueError(
                f"keep_moving must lie in [0, 1] (of the policy's speed), got {keep_moving}"
            )
        self.keep_moving = float(keep_moving)  # ditto: ShieldConfig.keep_moving
        self.response = bool(response)  # ditto: the env's velocity tracker (response_time)
        brake = brake_setting(brake)
        self.brake = bool(brake)  # ditto: the braking cap (brake_time)
        self.brake_slide = brake == "slide"  # ditto: ShieldConfig.brake_slide
        self._points: torch.Tensor | None = None  # (N, memory, beams, 3) world; FAR = no hit
        self._slot = 0

    def reset(self) -> None:
        """Forget everything (a new env, or one reset from outside its own steps)."""
        self._points, self._slot = None, 0

    def __call__(self, env, obs: dict[str, torch.Tensor], action: torch.Tensor) -> torch.Tensor:
        cfg = self.cfg or ShieldConfig.for_env(
            env.cfg, mover_margin=self.mover_margin,
            **(ShieldConfig.response_of(env.cfg) if self.response else {}),
            **(ShieldConfig.braking_of(env.cfg) if self.brake else {}),
            brake_slide=self.brake_slide, keep_moving=self.keep_moving)  # fmt: skip
        extra = None
        if self.map_scan:
            extra = map_scan_hits(env.heights, env.grid.origin, env.grid.size, env.cfg.grid_resolution,
                                  env.pos.to(action.dtype), env.yaw.to(action.dtype), cfg, env.world_idx)  # fmt: skip
        out, _ = self.apply(obs, action, env.pos, env.yaw, env.steps == 0, cfg, extra)
        return out

    def apply(self, obs: dict[str, torch.Tensor], action: torch.Tensor, pos: torch.Tensor,
              yaw: torch.Tensor, fresh: torch.Tensor, cfg: ShieldConfig | None = None,
              extra=None) -> tuple[torch.Tensor, torch.Tensor]:  # fmt: skip
        """The shield without an env: ``pos`` ``(N, 3)`` world positions, ``yaw`` ``(N,)`` the
        heading frames' yaw (the goal frame's), ``fresh`` ``(N,)`` bool, True where an episode
        begins now (its memory is cleared first); ``extra``: more static obstacles, ``(rel,
        valid, planar, dist)`` in the heading frame (:func:`map_scan_hits`). Returns ``(action,
        corrected)`` as :func:`shield_action` does."""
        from safenav.envs.sensors import beam_hit_points

        cfg = cfg or self.cfg
        if cfg is None:
            raise ValueError("MemoryShield.apply needs a ShieldConfig (here or at construction)")
        spec = _spec(cfg)
        lidar = obs["lidar"][:, : len(cfg.lidar_v_angles)]
        ranges = cfg.lidar_range * (1.0 - lidar.to(action.dtype))
        pos, yaw = pos.to(action.dtype), yaw.to(action.dtype)
        hits = beam_hit_points(ranges, pos, yaw, spec, far=FAR_POINT)  # (N, B, 3) world
        n, b = hits.shape[:2]
        if self._points is None or self._points.shape[0] != n or self._points.shape[2] != b:
            self._points = torch.full((n, self.memory, b, 3), FAR_POINT, dtype=hits.dtype,
                                      device=hits.device)  # fmt: skip
            self._slot = 0
        self._slot = (self._slot + 1) % self.memory
        self._points[:, self._slot] = hits
        fresh = fresh.to(torch.bool)  # episodes that begin now: nothing older belongs to them
        if bool(fresh.any()):
            keep = self._points[fresh, self._slot].clone()
            self._points[fresh] = FAR_POINT
            self._points[fresh, self._slot] = keep
        # Into the current heading frame (column 0 of the image along +x).
        world = self._points.flatten(1, 2) - pos[:, None]
        c, s = torch.cos(yaw)[:, None], torch.sin(yaw)[:, None]
        rel = torch.stack([c * world[..., 0] + s * world[..., 1],
                           -s * world[..., 0] + c * world[..., 1], world[..., 2]], -1)  # fmt: skip
        _, upward = _beams(spec, hits.device)
        planar = upward.repeat(self.memory)[None].expand(n, -1)
        d = rel.norm(dim=-1)
        k = self.max_static or cfg.max_static * min(self.memory, 4)
        dsel, idx = nearest(torch.where(d < spec.max_range - 1e-3, d, math.inf), min(k, d.shape[1]))
        valid = torch.isfinite(dsel)
        rel = torch.gather(rel, 1, idx[..., None].expand(-1, -1, 3)) * valid[..., None]
        planar = torch.gather(planar, 1, idx)
        if extra is not None:
            rel, valid, planar, dsel = (torch.cat([a, b.to(a.dtype)], 1)
                                        for a, b in zip((rel, valid, planar, dsel), extra, strict=True))  # fmt: skip
        return _shield_static_and_tracked(rel, valid, planar, dsel, obs["dynamic"], action, cfg,
                                          obs.get("state"), pos[:, 2])  # fmt: skip


def shield_for_memory(memory: int, map_scan: bool = False, mover_margin: float = 0.0,
                      response: bool = False, brake: bool | str = False,
                      keep_moving: float = 0.0):  # fmt: skip
    """The evaluation shield of a memory setting (``--shield-memory``): ``None`` for 0 (no
    shield), :func:`env_shield` for 1, a fresh :class:`MemoryShield` of ``memory`` images above;
    with ``map_scan`` (``--shield-map``) or a ``mover_margin`` (m, ``--shield-mover-margin``) a
    fresh ``MemoryShield(max(memory, 1), map_scan=..., mover_margin=...)``; ``response``: it
    models the env's velocity tracker (``ShieldConfig.response_time``); ``brake``
    (``--shield-brake``): the braking cap (``ShieldConfig.brake_time``), ``"slide"`` its sliding
    form (``ShieldConfig.brake_slide``); ``keep_moving``: ``ShieldConfig.keep_moving``."""
    if map_scan or mover_margin or response or brake or keep_moving:
        return MemoryShield(max(memory, 1), map_scan=map_scan, mover_margin=mover_margin,
                            response=response, brake=brake, keep_moving=keep_moving)  # fmt: skip
    if memory <= 0:
        return None
    return env_shield if memory == 1 else MemoryShield(memory)


def shield_from_spec(spec: dict | None):
    """A fresh shield as a policy's ``meta["shield"]`` records the one it trained behind
    (``{"memory": N, "map": bool, "mover_margin": m, "brake": bool or "slide"}``, ``safenav
    train --shield``); None for a policy trained without one."""
    if not spec:
        return None
    return shield_for_memory(int(spec["memory"]), bool(spec.get("map", False)),
                             float(spec.get("mover_margin", 0.0)),
                             brake=brake_setting(spec.get("brake", False)))  # fmt: skip


def brake_setting(value) -> bool | str:
    """A spec's ``brake``: ``False``, ``True`` (the scaled cap, also ``"scale"``) or ``"slide"``."""
    if isinstance(value, str) and value in ("scale", "slide"):
        return True if value == "scale" else value
    if isinstance(value, bool):
        return value
    raise ValueError(f"shield spec: brake must be false, true, 'scale' or 'slide', got {value!r}")


__all__ = [
    "MemoryShield",
    "ShieldConfig",
    "batched_arithmetic",
    "brake_setting",
    "env_shield",
    "dynamic_obstacles_from_features",
    "map_scan_hits",
    "shield_action",
    "static_obstacles_from_ranges",
    "shield_for_memory",
    "shield_from_spec",
    "velocity_obstacle_shield",
]
