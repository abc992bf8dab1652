"""Compiled (Numba) per-vehicle kernels of the onboard runtime's hot path.

The runtime works on one vehicle: batch 1, where NumPy's and torch's per-operation overhead, not
arithmetic, is the cost. Two parts of the sensor -> setpoint step are written here as loops:

**Depth insertion.** :meth:`safenav.deploy.mapping.HeightMap.insert_depth` is, in NumPy, ~40 array operations on a
few thousand pixels (:func:`~safenav.deploy.camera.backproject` with normals, then
:meth:`~safenav.deploy.mapping.HeightMap.insert_points`): per-operation overhead, not arithmetic,
made it ~1 ms per 4-camera frame, half of the sensor -> setpoint budget (``safenav bench
latency``). This kernel does the same per pixel in one loop: back-projection, the surface normal
from the right and lower neighbours, the half-cell shift into steep surfaces, the ground band,
the tracked-obstacle exclusion (footprint mask, then the exact box test) and the column ``amax``.

**Velocity-obstacle shield.** :func:`safenav.deploy.shield.velocity_obstacle_shield` for one
vehicle: ~100 small torch operations (~0.4 ms, ~1 ms when it corrects, which set the p99) become
one loop over candidates x obstacles. The nearest obstacles whose boundary corrections become
candidates are still chosen by ``torch.topk`` (passed in as ``idx``), so that ties break alike.

Both are the batched paths' rules written once more; ``tests/test_deploy_kernels.py`` checks each
against its batched original. Without Numba installed (it comes with ``safenav[deploy]``), the
runtime uses the batched paths.
"""

from __future__ import annotations

import math

import numpy as np

try:
    from numba import njit
except ImportError:  # pragma: no cover -- the NumPy path is used instead
    njit = None

AVAILABLE = njit is not None


def _insert_depth(depth, fx, fy, cx, cy, R, t, stride, max_range, ground_band, surface_offset,
                  origin, res, lo, hi, mask, heights, touched):  # fmt: skip
    """Insert the batch ``depth (B, H, W)`` into ``heights (g * g,)``; returns the number of
    cells written, whose flat indices are ``touched[:n]`` (for the uint8 cast map)."""
    b, full_h, full_w = depth.shape
    g = mask.shape[0]
    h = (full_h + stride - 1) // stride
    w = (full_w + stride - 1) // stride
    f0 = np.float32(0.0)
    quarter = np.float32(0.25)
    half_sq = np.float32(0.5)
    tiny = np.float32(1e-20)
    # Footprints of the (already inflated) tracked-obstacle boxes, marked on the scratch mask.
    m = lo.shape[0]
    c0 = np.empty((m, 2), np.int64)
    c1 = np.empty((m, 2), np.int64)
    for j in range(m):
        for a in range(2):
            c0[j, a] = min(max(int(math.floor((lo[j, a] - origin) / res)), 0), g)
            c1[j, a] = min(max(int(math.floor((hi[j, a] - origin) / res)) + 1, 0), g)
        mask[c0[j, 0] : c1[j, 0], c0[j, 1] : c1[j, 1]] = True
    n = 0
    for k in range(b):
        for v in range(h):
            yv = (np.float32(v * stride) - cy[k]) / fy[k]
            for u in range(w):
                z = depth[k, v * stride, u * stride]
                if not (z > f0) or not math.isfinite(z):  # NaN, 0 (no return) or Inf
                    continue
                xu = (np.float32(u * stride) - cx[k]) / fx[k]
                if z * math.sqrt(1.0 + xu * xu + yv * yv) > max_range:
                    continue
                # The offset z * ray from the camera, ray = R @ (xu, yv, 1).
                c_x = (R[k, 0, 0] * xu + R[k, 0, 1] * yv + R[k, 0, 2]) * z
                c_y = (R[k, 1, 0] * xu + R[k, 1, 1] * yv + R[k, 1, 2]) * z
                c_z = (R[k, 2, 0] * xu + R[k, 2, 1] * yv + R[k, 2, 2]) * z
                px, py, pz = c_x + t[k, 0], c_y + t[k, 1], c_z + t[k, 2]
                if not (pz > ground_band):
                    continue
                # Surface normal from the right and lower neighbours where both are valid and
                # near (else the reversed viewing ray), as camera.backproject.
                ok = False
                nx = ny = nz = f0
                if u < w - 1 and v < h - 1:
                    zr = depth[k, v * stride, (u + 1) * stride]
                    zd = depth[k, (v + 1) * stride, u * stride]
                    xr = (np.float32((u + 1) * stride) - cx[k]) / fx[k]
                    yd = (np.float32((v + 1) * stride) - cy[k]) / fy[k]
                    if (zr > f0 and math.isfinite(zr) and zr * math.sqrt(1.0 + xr * xr + yv * yv) <= max_range
                            and zd > f0 and math.isfinite(zd)
                            and zd * math.sqrt(1.0 + xu * xu + yd * yd) <= max_range):  # fmt: skip
                        du_x = (R[k, 0, 0] * xr + R[k, 0, 1] * yv + R[k, 0, 2]) * zr - c_x
                        du_y = (R[k, 1, 0] * xr + R[k, 1, 1] * yv + R[k, 1, 2]) * zr - c_y
                        du_z = (R[k, 2, 0] * xr + R[k, 2, 1] * yv + R[k, 2, 2]) * zr - c_z
                        dv_x = (R[k, 0, 0] * xu + R[k, 0, 1] * yd + R[k, 0, 2]) * zd - c_x
                        dv_y = (R[k, 1, 0] * xu + R[k, 1, 1] * yd + R[k, 1, 2]) * zd - c_y
                        dv_z = (R[k, 2, 0] * xu + R[k, 2, 1] * yd + R[k, 2, 2]) * zd - c_z
                        lim = (quarter * z) * (quarter * z)
                        if (du_x * du_x + du_y * du_y + du_z * du_z < lim
                                and dv_x * dv_x + dv_y * dv_y + dv_z * dv_z < lim):  # fmt: skip
                            ok = True
                            nx = du_y * dv_z - du_z * dv_y
                            ny = du_z * dv_x - du_x * dv_z
                            nz = du_x * dv_y - du_y * dv_x
                            inv = np.float32(1.0) / math.sqrt(
                                max(nx * nx + ny * ny + nz * nz, tiny)
                            )
                            if nx * c_x + ny * c_y + nz * c_z > f0:  # face the camera
                                inv = -inv
                            nx, ny = nx * inv, ny * inv
                if not ok:
                    back = np.float32(-1.0) / math.sqrt(
                        max(c_x * c_x + c_y * c_y + c_z * c_z, tiny)
                    )
                    nx, ny = c_x * back, c_y * back
                # Steep surface: move the point half a cell into it (HeightMap.insert_points).
                nn = math.sqrt(nx * nx + ny * ny)
                if surface_offset > f0 and nn > half_sq:
                    s = -surface_offset / max(nn, np.float32(1e-6))
                    px, py = px + nx * s, py + ny * s
                ix = int(math.floor((px - origin) / res))
                iy = int(math.floor((py - origin) / res))
                if ix < 0 or ix >= g or iy < 0 or iy >= g:
                    continue
                if mask[ix, iy]:
                    inside = False
                    for j in range(m):
                        if (lo[j, 0] <= px <= hi[j, 0] and lo[j, 1] <= py <= hi[j, 1]
                                and lo[j, 2] <= pz <= hi[j, 2]):  # fmt: skip
                            inside = True
                            break
                    if inside:
                        continue
                cell = ix * g + iy
                if pz > heights[cell]:
                    heights[cell] = pz
                touched[n] = cell
                n += 1
    for j in range(m):
        mask[c0[j, 0] : c1[j, 0], c0[j, 1] : c1[j, 1]] = False
    return n


def _vo(vx, vy, vz, rel, ovel, radius, valid, planar, tau):
    """Is velocity ``v`` inside any velocity obstacle, and the earliest time to collision
    (shield._vo_test for one candidate)."""
    inside = False
    ttc_min = math.inf
    for m in range(rel.shape[0]):
        kz = 0.0 if planar[m] else 1.0
        px, py, pz = rel[m, 0], rel[m, 1], rel[m, 2]
        rx, ry, rz = vx - ovel[m, 0], vy - ovel[m, 1], vz - ovel[m, 2]
        pv = px * rx + py * ry + (pz * kz) * rz
        vv = max(rx * rx + ry * ry + rz * rz * kz, 1e-12)
        pp = px * px + py * py + (pz * kz) * pz
        r2 = radius[m] * radius[m]
        t = min(max(pv / vv, 0.0), tau)
        d2 = pp - 2 * t * pv + t * t * vv
        penetrating = pp < r2
        if valid[m] and ((pv > 0) if penetrating else (d2 < r2)):
            inside = True
        disc = pv * pv - vv * (pp - r2)
        if penetrating:
            ttc = 0.0 if pv > 0 else math.inf
        else:
            ttc = (pv - math.sqrt(max(disc, 0.0))) / vv
        if disc < 0 or pv <= 0 or not valid[m]:
            ttc = math.inf
        ttc_min = min(ttc_min, max(ttc, 0.0))
    return inside, ttc_min


def _boundary(v_des, p, u, r, flat, tau):
    """The cone-side and cap candidates of one obstacle (shield._boundary_candidates)."""
    px, py, pz = p[0], p[1], 0.0 if flat else p[2]
    rx, ry, rz = v_des[0] - u[0], v_des[1] - u[1], v_des[2] - u[2]
    vr_z = rz
    if flat:
        rz = 0.0
    dist = max(math.sqrt(px * px + py * py + pz * pz), 1e-6)
    hx, hy, hz = px / dist, py / dist, pz / dist
    alpha = math.asin(min(r / dist, 1.0)) + 0.03
    a = rx * hx + ry * hy + rz * hz
    qx, qy, qz = rx - a * hx, ry - a * hy, rz - a * hz
    rho = math.sqrt(qx * qx + qy * qy + qz * qz)
    if rho > 1e-6:
        inv = 1.0 / max(rho, 1e-9)
        ex, ey, ez = qx * inv, qy * inv, qz * inv
    else:  # vr along ph: turn toward ph x z (or y if ph is vertical)
        sx, sy = hy, -hx
        sn = math.sqrt(sx * sx + sy * sy)
        if sn < 1e-6:
            sx, sy, sn = 0.0, 1.0, 1.0
        ex, ey, ez = sx / sn, sy / sn, 0.0
    s = max(a * math.cos(alpha) + rho * math.sin(alpha), 0.0)
    ca, sa = math.cos(alpha), math.sin(alpha)
    leg = np.array([s * (ca * hx + sa * ex), s * (ca * hy + sa * ey), s * (ca * hz + sa * ez)])
    cx, cy, cz = px / tau, py / tau, pz / tau
    wx, wy, wz = rx - cx, ry - cy, rz - cz
    wn = math.sqrt(wx * wx + wy * wy + wz * wz)
    if wn > 1e-6:
        inv = 1.0 / max(wn, 1e-9)
        wx, wy, wz = wx * inv, wy * inv, wz * inv
    else:
        wx, wy, wz = -hx, -hy, -hz
    k = r / tau * 1.05
    cap = np.array([cx + wx * k, cy + wy * k, cz + wz * k])
    if flat:  # planar obstacles leave the vertical component as it was
        leg[2] += vr_z
        cap[2] += vr_z
    return leg + u, cap + u


def _shield(v_des, rel, ovel, radius, valid, planar, idx, fan, tau, vm):
    """shield.velocity_obstacle_shield for one vehicle: ``(v, corrected)``."""
    inside, _ = _vo(v_des[0], v_des[1], v_des[2], rel, ovel, radius, valid, planar, tau)
    if not inside:
        return v_des.copy(), False
    k = idx.shape[0]
    nc = 4 + fan.shape[0] + 2 * k
    cands = np.empty((nc, 3))
    for i, sc in enumerate((0.75, 0.5, 0.25, 0.0)):
        cands[i] = v_des * sc
    cands[4 : 4 + fan.shape[0]] = fan
    for j in range(k):
        m = idx[j]
        leg, cap = _boundary(v_des, rel[m], ovel[m], radius[m], planar[m], tau)
        cands[4 + fan.shape[0] + j] = leg
        cands[4 + fan.shape[0] + k + j] = cap
    best, best_cost = -1, math.inf
    fallback, fallback_score = 0, -math.inf
    for c in range(nc):
        for a in range(3):
            cands[c, a] = min(max(cands[c, a], -vm), vm)
        dx, dy, dz = cands[c, 0] - v_des[0], cands[c, 1] - v_des[1], cands[c, 2] - v_des[2]
        cost = dx * dx + dy * dy + dz * dz
        ins, ttc = _vo(cands[c, 0], cands[c, 1], cands[c, 2], rel, ovel, radius, valid, planar, tau)
        if not ins and cost < best_cost:
            best, best_cost = c, cost
        score = min(ttc, 1e6) - 1e-3 * cost  # nothing admissible: latest collision, then nearest
        if score > fallback_score:
            fallback, fallback_score = c, score
    return cands[best if best >= 0 else fallback].copy(), True


def _shield_obs(action, lidar, dyn, dirs, upward, fan, k_static, projected, lidar_range, v_max,
                base, mover_base, width0, n_widths, cuboid_height, tau, max_hit):  # fmt: skip
    """shield.shield_action for one vehicle, from its observation: ``(action, corrected)``.

    The obstacle decoding is float32 arithmetic in the batched path's order (so that the same hits
    and distances come out, bit for bit) and the selections are stable sorts, as
    ``shield.nearest``; the VO search is :func:`_shield`."""
    f = np.float32
    inf = np.float32(np.inf)
    big_r, vm, one = f(lidar_range), f(v_max), f(1.0)
    # Static obstacles: the k nearest beam hits (range image value (R - d) / R).
    d = np.empty(lidar.shape[0], np.float32)
    for i in range(lidar.shape[0]):
        r = big_r * (one - lidar[i])
        d[i] = r if r < f(max_hit) else inf
    order = np.argsort(d, kind="mergesort")[:k_static]
    nd = dyn.shape[0]
    use_dyn = False
    for j in range(nd):
        for c in range(dyn.shape[1]):
            if dyn[j, c] != 0:
                use_dyn = True
    m = k_static + (nd if use_dyn else 0)
    rel = np.zeros((m, 3))
    ovel = np.zeros((m, 3))
    radius = np.empty(m)
    valid = np.zeros(m, np.bool_)
    planar = np.zeros(m, np.bool_)
    dist = np.full(m, inf, np.float32)
    for i in range(k_static):
        b = order[i]
        ok = d[b] < inf
        ds = d[b] if ok else f(0.0)
        for a in range(3):
            rel[i, a] = dirs[b, a] * ds
        radius[i] = f(base)
        valid[i], planar[i] = ok, upward[b]
        if ok:
            dist[i] = d[b]
    if use_dyn:  # the tracked moving obstacles, decoded from their features
        cz = f((cuboid_height / 2) ** 2)
        for j in range(nd):
            i = k_static + j
            d2, dz = dyn[j, 3] * big_r, dyn[j, 4] * big_r
            dj = np.sqrt(d2 * d2 + dz * dz)
            for a in range(3):
                rel[i, a] = dyn[j, a] * dj
                ovel[i, a] = dyn[j, 5 + a] * vm
            half = (dyn[j, 8] * f(n_widths - 1) + one) * f(width0) / f(2.0)
            cuboid = dyn[j, 9] > f(0.5)
            r = np.sqrt(f(2.0) * half * half + cz) if cuboid else half
            radius[i] = r + f(mover_base)
            total = f(0.0)
            for c in range(dyn.shape[1]):
                total += abs(dyn[j, c])
            valid[i], planar[i] = total > f(0.0), not cuboid
            if valid[i]:
                dist[i] = dj
    idx = np.argsort(dist, kind="mergesort")[: min(projected, m)]
    v_des = np.empty(3)
    for a in range(3):
        v_des[a] = action[a] * vm
    v, corrected = _shield(v_des, rel, ovel, radius, valid, planar, idx, fan, tau, float(vm))
    out = np.empty(3, np.float32)
    for a in range(3):
        out[a] = min(max(f(v[a]) / vm, f(-1.0)), one)
    return out, corrected


if AVAILABLE:
    insert_depth_kernel = njit(cache=True, nogil=True)(_insert_depth)
    _vo = njit(cache=True, nogil=True)(_vo)
    _boundary = njit(cache=True, nogil=True)(_boundary)
    _shield = njit(cache=True, nogil=True)(_shield)
    shield_kernel = _shield
    shield_obs_kernel = njit(cache=True, nogil=True)(_shield_obs)
else:  # pragma: no cover
    insert_depth_kernel = shield_kernel = shield_obs_kernel = None


__all__ = ["AVAILABLE", "insert_depth_kernel", "shield_kernel", "shield_obs_kernel"]
