"""The velocity-obstacle safety shield: unchanged when safe, minimal correction otherwise."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch

from safenav.deploy.shield import (
    MemoryShield,
    ShieldConfig,
    _vo_test,
    shield_action,
    velocity_obstacle_shield,
)
from safenav.envs import SafeNavVectorEnv, make_config
from safenav.envs.scripted import go_to_goal

ROOT = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.usefixtures("one_thread")


def scene(points, vels=None, radius=0.4, planar=False):
    rel = torch.tensor([points], dtype=torch.float32)
    vel = torch.zeros_like(rel) if vels is None else torch.tensor([vels], dtype=torch.float32)
    m = rel.shape[1]
    return (
        rel,
        vel,
        torch.full((1, m), radius),
        torch.ones(1, m, dtype=torch.bool),
        torch.full((1, m), planar),
    )


def admissible(v, rel, vel, rad, valid, planar, cfg):
    inside, _ = _vo_test(v[:, None, :], rel, vel, rad, valid, planar, cfg.time_horizon)
    return ~inside[:, 0]


def test_safe_velocity_is_returned_bit_for_bit() -> None:
    cfg = ShieldConfig()
    v = torch.tensor([[1.3, -0.2, 0.1]])
    rel, vel, rad, valid, planar = scene([[0.0, 3.0, 0.0], [-2.0, 0.0, 0.0]])  # beside and behind
    out, corrected = velocity_obstacle_shield(v, rel, vel, rad, valid, planar, cfg)
    assert not bool(corrected[0]) and torch.equal(out, v)


def test_head_on_static_obstacle_is_avoided_with_a_small_change() -> None:
    cfg = ShieldConfig()
    v = torch.tensor([[2.0, 0.0, 0.0]])
    rel, vel, rad, valid, planar = scene([[1.5, 0.05, 0.0]], planar=True)  # a pillar 1.5 m ahead
    out, corrected = velocity_obstacle_shield(v, rel, vel, rad, valid, planar, cfg)
    assert bool(corrected[0])
    assert bool(admissible(out, rel, vel, rad, valid, planar, cfg)[0])
    # The correction is the smallest of its candidates: no admissible fan velocity is closer.
    ang = torch.linspace(0, 2 * math.pi, 721)[:-1]
    for speed in (0.5, 1.0, 1.5, 2.0):
        fan = torch.stack(
            [speed * torch.cos(ang), speed * torch.sin(ang), torch.zeros_like(ang)], -1
        )
        ok = admissible(fan, rel.expand(720, -1, -1), vel.expand(720, -1, -1), rad.expand(720, -1),
                        valid.expand(720, -1), planar.expand(720, -1), cfg)  # fmt: skip
        closest = (fan[ok] - v).norm(dim=-1).min()
        assert (out - v).norm() <= closest + 0.05


def test_approaching_moving_obstacle_makes_the_shield_move_away() -> None:
    cfg = ShieldConfig()
    v = torch.zeros(1, 3)  # hovering ...
    rel, vel, rad, valid, planar = scene(
        [[2.0, 0.0, 0.0]], vels=[[-1.5, 0.0, 0.0]], radius=0.8
    )  # ... it comes
    out, corrected = velocity_obstacle_shield(v, rel, vel, rad, valid, planar, cfg)
    assert bool(corrected[0])
    assert bool(admissible(out, rel, vel, rad, valid, planar, cfg)[0])
    assert out.norm() > 0.1


def test_penetrating_obstacle_only_allows_moving_away() -> None:
    cfg = ShieldConfig()
    rel, vel, rad, valid, planar = scene([[0.2, 0.0, 0.0]])
    out, corrected = velocity_obstacle_shield(
        torch.tensor([[1.0, 0.0, 0.0]]), rel, vel, rad, valid, planar, cfg
    )
    assert bool(corrected[0]) and float(out[0, 0]) <= 0.0


def test_batched_rows_are_independent() -> None:
    cfg = ShieldConfig()
    gen = torch.Generator().manual_seed(0)
    n, m = 12, 7
    v = (torch.rand(n, 3, generator=gen) * 2 - 1) * 2
    rel = (torch.rand(n, m, 3, generator=gen) * 2 - 1) * 3
    vel = torch.rand(n, m, 3, generator=gen) - 0.5
    rad = torch.rand(n, m, generator=gen) * 0.5 + 0.3
    valid = torch.rand(n, m, generator=gen) > 0.3
    planar = torch.rand(n, m, generator=gen) > 0.5
    out, corrected = velocity_obstacle_shield(v, rel, vel, rad, valid, planar, cfg)
    for i in range(n):
        oi, ci = velocity_obstacle_shield(v[i : i + 1], rel[i : i + 1], vel[i : i + 1], rad[i : i + 1],
                                          valid[i : i + 1], planar[i : i + 1], cfg)  # fmt: skip
        assert bool(ci[0]) == bool(corrected[i])
        torch.testing.assert_close(oi[0], out[i])
    assert corrected.any() and (~corrected).any()
    assert bool((out.abs() <= cfg.v_max + 1e-6).all())


def test_the_fallback_for_envs_with_nothing_admissible_is_row_by_row_the_same() -> None:
    """Where no candidate is admissible the shield takes the latest time to collision; those times
    are computed for those envs only, and the batch gives each env, bit for bit, what it alone
    gets from the same (uncompiled) code."""
    cfg = ShieldConfig()
    gen = torch.Generator().manual_seed(1)
    n, m = 10, 26
    v = (torch.rand(n, 3, generator=gen) * 2 - 1) * 2
    rel = (torch.rand(n, m, 3, generator=gen) * 2 - 1) * 1.5  # dense: some need a correction
    vel = torch.rand(n, m, 3, generator=gen) - 0.5
    rad = torch.rand(n, m, generator=gen) * 0.5 + 0.3
    valid = torch.rand(n, m, generator=gen) > 0.3
    planar = torch.zeros(n, m, dtype=torch.bool)
    # envs 2 and 7: closed in by 26 obstacles 1 m away, all converging on the vehicle (env 7's
    # slower the further down the list, so that its latest collision lies elsewhere)
    dirs = torch.tensor([(x, y, z) for x in (-1, 0, 1) for y in (-1, 0, 1) for z in (-1, 0, 1)
                         if (x, y, z) != (0, 0, 0)], dtype=torch.float32)  # fmt: skip
    dirs = dirs / dirs.norm(dim=-1, keepdim=True)
    for i, speed in ((2, torch.full((m, 1), 1.5)), (7, torch.linspace(2.0, 0.8, m)[:, None])):
        rel[i], vel[i], rad[i], valid[i] = dirs, -speed * dirs, 0.6, True
    out, corrected = velocity_obstacle_shield(v, rel, vel, rad, valid, planar, cfg, compiled=False)
    for i in range(n):
        alone = [t[i : i + 1] for t in (v, rel, vel, rad, valid, planar)]
        oi, ci = velocity_obstacle_shield(*alone, cfg, compiled=False)
        assert bool(ci[0]) == bool(corrected[i]) and torch.equal(oi[0], out[i]), i
    ok = admissible(out, rel, vel, rad, valid, planar, cfg)
    assert corrected[[2, 7]].all() and not ok[[2, 7]].any()  # the fallback: nothing admissible
    assert (corrected & ok).any()  # and envs corrected to an admissible velocity beside them


def test_shield_action_on_the_vector_env_cuts_collisions() -> None:
    """The batched API on the env's own tensors: a straight-to-goal policy collides far less."""
    cfg = make_config("easy")
    sc = ShieldConfig.for_env(cfg)
    collisions = {}
    for use in (False, True):
        env = SafeNavVectorEnv(64, config=cfg, output="torch")
        obs, _ = env.reset(seed=0)
        n = 0
        for _ in range(150):
            a = go_to_goal(obs)
            if use:
                safe, corrected = shield_action(obs, a, sc)
                assert torch.equal(safe[~corrected], a[~corrected])  # untouched rows unchanged
                assert bool((safe.abs() <= 1.0).all())
                a = safe
            obs, _, _, _, info = env.step(a)
            n += int(info["collision"].sum())
        collisions[use] = n
    assert collisions[False] > 20
    assert collisions[True] < 0.5 * collisions[False], collisions


def test_env_shield_in_the_evaluation_protocol() -> None:
    """``safenav eval --shield`` calls ``env_shield(env, obs, action)`` each step."""
    from safenav.deploy.shield import env_shield
    from safenav.experiments.evaluate import evaluate

    cfg = make_config("easy")
    plain = evaluate(go_to_goal, cfg, episodes=24)
    shielded = evaluate(go_to_goal, cfg, episodes=24, shield=env_shield)
    assert shielded["collision_rate"] < plain["collision_rate"]
    assert shielded["success_rate"] >= plain["success_rate"]


def test_memory_shield_of_one_image_is_env_shield() -> None:
    """``MemoryShield(1)`` remembers only the current image: the memoryless shield's actions, to
    rounding, over episodes that end and restart. Its points go to the world frame and back, so a
    near-tie between candidates may fall the other way now and then (measured: 1 of 3,840 rows
    corrected by one and not the other, 7 rows apart by more than 1e-3); a wrong frame or a stale
    memory would move most corrected rows. Every beam hit counts (``max_static`` 144), so that the
    nearest-24 cut does not add ties of its own."""
    from safenav.deploy.shield import MemoryShield

    env = SafeNavVectorEnv(32, config=make_config("easy"), output="torch")
    cfg = ShieldConfig.for_env(env.cfg, max_static=144)
    obs, _ = env.reset(seed=3)
    shield, corrected, flips, apart, rows = MemoryShield(1, cfg), 0, 0, 0, 0
    for _ in range(120):
        a = go_to_goal(obs)
        plain, was = shield_action(obs, a, cfg)
        mem = shield(env, obs, a)
        corrected += int(was.sum())
        flips += int(((mem != a).any(-1) != was).sum())
        apart += int(((mem - plain).abs().amax(-1) > 1e-3).sum())
        rows += len(a)
        obs, *_ = env.step(plain)
    assert corrected > 200  # the comparison covered corrections, not only untouched actions
    assert flips <= 0.005 * rows and apart <= 0.01 * corrected, (flips, apart, corrected, rows)


def test_memory_shield_remembers_a_pillar_top_the_image_has_lost() -> None:
    """The lowest beam (-10 deg) sees a pillar's side 2 m ahead, 0.35 m below the UAV; 1.5 m on
    the image is empty (the top has dropped below the beam). Flying on would graze the top: the
    memory shield turns, the memoryless one does not; a new episode forgets the hit."""
    from types import SimpleNamespace

    from safenav.deploy.shield import MemoryShield, env_shield

    cfg = make_config("paper")
    yaw = torch.tensor([0.7])
    heading = torch.tensor([[math.cos(0.7), math.sin(0.7), 0.0]])
    env = SimpleNamespace(cfg=cfg, pos=torch.tensor([[3.0, -2.0, 1.5]]), yaw=yaw,
                          steps=torch.tensor([0]))  # fmt: skip
    empty = {"state": torch.zeros(1, 8), "lidar": torch.zeros(1, 4, 36),
             "dynamic": torch.zeros(1, cfg.num_tracked, 10)}  # fmt: skip
    seen = {**empty, "lidar": empty["lidar"].clone()}
    d = 2.0 / math.cos(math.radians(10.0))  # beam length to the side 2 m ahead
    seen["lidar"][0, 0, 0] = (cfg.lidar_range - d) / cfg.lidar_range  # row 0: -10 deg, column 0
    ahead = torch.tensor([[1.0, 0.0, 0.0]])
    shield = MemoryShield(10)
    shield(env, seen, ahead)
    env.pos, env.steps = env.pos + 1.5 * heading, torch.tensor([1])
    assert torch.equal(env_shield(env, empty, ahead), ahead)  # nothing in view
    turned = shield(env, empty, ahead)
    assert not torch.equal(turned, ahead)
    assert float(turned[0, 0]) < 0.9 or abs(float(turned[0, 1])) > 0.2 or float(turned[0, 2]) > 0.1
    env.steps = torch.tensor([0])  # a new episode in the same place
    assert torch.equal(shield(env, empty, ahead), ahead)


def test_memory_shield_refuses_a_bad_memory() -> None:
    from safenav.deploy.shield import MemoryShield

    for bad in (0, -1, 101):
        with pytest.raises(ValueError, match="memory"):
            MemoryShield(bad)


def test_eval_and_render_take_the_shield_memory(capsys, tmp_path, monkeypatch):
    """``--shield-memory N`` (N > 1) needs ``--shield``: one line, exit 2, nothing flown; with it,
    ``safenav eval`` flies behind a MemoryShield and its JSON says how much it remembered, and
    ``safenav render`` hands the memory to the flight."""
    import json

    from conftest import run_cli

    ckpt = str(ROOT / "checkpoints" / "csac-paper.pt")
    code, _, err = run_cli(capsys, ["eval", ckpt, "--shield-memory", "5"])
    assert (
        code == 2
        and "--shield-memory 5 needs --shield" in err
        and len(err.strip().splitlines()) == 1
    )
    code, _, err = run_cli(capsys, ["render", ckpt, "--shield-memory", "101", "--shield"])
    assert code == 2 and "--shield-memory 101" in err
    code, _, err = run_cli(capsys, ["eval", ckpt, "--shield-map"])
    assert code == 2 and "--shield-map needs --shield" in err
    out = tmp_path / "eval.json"
    code, _, _ = run_cli(capsys, ["eval", "--policy", "straight", "--preset", "easy", "--episodes",
                                  "4", "--shield", "--shield-memory", "5", "--json", str(out)])  # fmt: skip
    assert code == 0 and json.loads(out.read_text())["shield_memory"] == 5
    code, _, _ = run_cli(capsys, ["eval", "--policy", "straight", "--preset", "easy", "--episodes",
                                  "4", "--shield", "--shield-map", "--json", str(out)])  # fmt: skip
    assert code == 0 and json.loads(out.read_text())["shield_map"] is True
    code, _, err = run_cli(capsys, ["eval", ckpt, "--shield-brake"])
    assert code == 2 and "--shield-brake needs --shield" in err
    code, _, _ = run_cli(capsys, ["eval", "--policy", "straight", "--preset", "easy", "--episodes",
                                  "4", "--shield", "--shield-brake", "--json", str(out)])  # fmt: skip
    assert code == 0 and json.loads(out.read_text())["shield_brake"] is True
    flown = []
    monkeypatch.setattr("safenav.experiments.flight.render_episode",
                        lambda *a, **k: flown.append((k["shield_memory"], k["shield_map"],
                                                      k["shield_brake"])) or {})  # fmt: skip
    for argv in (
        ["--shield", "--shield-memory", "8"],
        ["--shield"],
        [],
        ["--shield", "--shield-map"],
        ["--shield", "--shield-brake"],
    ):
        code, _, _ = run_cli(capsys, ["render", ckpt, "--out", str(tmp_path / "e.gif"), *argv])
        assert code == 0
    assert flown == [(8, False, False), (1, False, False), (0, False, False), (1, True, False),
                     (1, False, True)]  # fmt: skip


def test_shield_for_memory_names_the_three_settings() -> None:
    from safenav.deploy.shield import MemoryShield, env_shield, shield_for_memory

    assert shield_for_memory(0) is None and shield_for_memory(1) is env_shield
    five = shield_for_memory(5)
    assert isinstance(five, MemoryShield) and five.memory == 5
    assert shield_for_memory(5) is not five  # a fresh memory for each flight
    for memory in (0, 1, 5):
        scan = shield_for_memory(memory, map_scan=True)
        assert isinstance(scan, MemoryShield) and scan.map_scan and scan.memory == max(memory, 1)


def test_fly_takes_the_shield_memory_in_env_steps(capsys, tmp_path, monkeypatch) -> None:
    """``safenav fly --shield --shield-memory N`` hands N range images to the flight, which keeps
    N env steps' worth (N x 0.1 s) of setpoints: 2 s is 40 setpoints at 20 Hz; more than 100
    setpoints is one line, exit 2. Without --shield, N > 1 is refused before anything flies."""
    from conftest import run_cli
    from safenav.deploy.runtime import RuntimeConfig
    from safenav.errors import SafenavError

    cfg = make_config("paper")
    assert RuntimeConfig.for_flight(cfg, 0, 20.0).shield is None
    one = RuntimeConfig.for_flight(cfg, 1, 20.0)
    assert one.shield is not None and one.shield_memory == 1
    assert RuntimeConfig.for_flight(cfg, 20, 20.0).shield_memory == 40
    assert RuntimeConfig.for_flight(cfg, 20, 10.0).shield_memory == 20
    assert RuntimeConfig.for_flight(cfg, 1, 20.0, shield_map=True).shield_map
    assert RuntimeConfig.for_flight(cfg, 1, 20.0, mover_margin=0.3).shield.mover_margin == 0.3
    assert RuntimeConfig.for_flight(cfg, 1, 20.0).shield.brake_time == 0.0
    assert RuntimeConfig.for_flight(cfg, 1, 20.0, brake=True).shield.brake_time == 0.4
    with pytest.raises(SafenavError, match="more than 100"):
        RuntimeConfig.for_flight(cfg, 20, 60.0)

    demo = ["fly", "--demo", "--checkpoint", str(ROOT / "checkpoints" / "csac.pt"),
            "--gif", str(tmp_path / "f.gif"), "--connect", "udpin://127.0.0.1:0"]  # fmt: skip
    code, _, err = run_cli(capsys, [*demo, "--shield-memory", "20"])
    assert code == 2 and "--shield-memory 20 needs --shield" in err

    flown = []

    def fake_demo(**kw):
        flown.append(
            (
                kw["shield"],
                kw["shield_memory"],
                kw["shield_map"],
                kw["shield_mover_margin"],
                kw["shield_brake"],
            )
        )
        raise SystemExit(0)

    monkeypatch.setattr("safenav.deploy.demo.run_demo", fake_demo)
    for argv in (
        ["--shield", "--shield-memory", "20"],
        ["--shield"],
        [],
        ["--shield", "--shield-map"],
        ["--shield", "--shield-mover-margin", "0.3"],
        ["--shield", "--shield-brake"],
    ):
        assert run_cli(capsys, [*demo, *argv])[0] == 0
    assert flown == [(True, 20, False, 0.0, False), (True, 1, False, 0.0, False),
                     (False, 0, False, 0.0, False), (True, 1, True, 0.0, False),
                     (True, 1, False, 0.3, False), (True, 1, False, 0.0, True)]  # fmt: skip
    code, _, err = run_cli(capsys, [*demo, "--shield-mover-margin", "0.3"])
    assert code == 2 and "--shield-mover-margin needs --shield" in err


def test_the_response_aware_shield_tests_candidates_from_where_the_vehicle_drifts():
    """``ShieldConfig.response_time``: a first-order tracker (0.4 s, 3 m/s^2) flying 2 m/s keeps
    going 0.91 m when told to hover; 1 m short of a pillar that hover is a collision."""
    from safenav.deploy.shield import response_offset

    cfg = ShieldConfig(response_time=0.4, max_acceleration=3.0)
    v0 = torch.tensor([[2.0, 0.0, 0.0]])
    hover, slower = torch.zeros(1, 1, 3), torch.tensor([[[1.0, 0.0, 0.0]]])
    # |dv| = 2 > a T = 1.2: (4 - 1.44) / 6 + 1.2 * 0.4; |dv| = 1: dv T
    assert response_offset(v0, hover, cfg)[0, 0, 0].item() == pytest.approx(2.56 / 6 + 0.48)
    assert response_offset(v0, slower, cfg)[0, 0, 0].item() == pytest.approx(0.4)
    assert response_offset(v0, hover, ShieldConfig(response_time=0.4))[
        0, 0, 0
    ].item() == pytest.approx(0.8)
    rel, vel = torch.tensor([[[1.0, 0.0, 0.0]]]), torch.zeros(1, 1, 3)
    radius, valid = torch.tensor([[0.5]]), torch.tensor([[True]])
    _, naive = velocity_obstacle_shield(torch.zeros(1, 3), rel, vel, radius, valid, v_now=v0)
    _, aware = velocity_obstacle_shield(
        torch.zeros(1, 3), rel, vel, radius, valid, cfg=cfg, v_now=v0
    )
    assert not naive.item() and aware.item()
    # at rest, far from the pillar, the same command passes either way
    _, calm = velocity_obstacle_shield(torch.zeros(1, 3), rel * 3, vel, radius, valid, cfg=cfg,
                                       v_now=torch.zeros(1, 3))  # fmt: skip
    assert not calm.item()
    # already inside it: leaving is admissible, as without the model
    _, leaving = velocity_obstacle_shield(torch.tensor([[-1.0, 0.0, 0.0]]), rel * 0.4, vel, radius,
                                          valid, cfg=cfg, v_now=torch.zeros(1, 3))  # fmt: skip
    assert not leaving.item()
    with pytest.raises(ValueError, match="v_now"):
        velocity_obstacle_shield(torch.zeros(1, 3), rel, vel, radius, valid, cfg=cfg)


def test_braking_speed_is_the_speed_the_vehicle_can_stop_from():
    """``c T + c^2 / (2 a) = d``: with T = 0.4 s and a = 2 m/s^2, 1 m of room allows 1.35 m/s."""
    from safenav.deploy.shield import braking_speed

    cfg = ShieldConfig(brake_time=0.4, brake_acceleration=2.0)
    c = braking_speed(torch.tensor([0.0, -0.3, 1.0, 3.0]), cfg)
    assert c[0].item() == 0.0 and c[1].item() == 0.0  # no room: no approach at all
    for ci, d in zip(c[2:].tolist(), (1.0, 3.0), strict=True):
        assert ci * 0.4 + ci * ci / 4.0 == pytest.approx(d, rel=1e-5)
    assert c[2].item() == pytest.approx(2 * (math.sqrt(1.16) - 0.4), abs=1e-5)


def test_the_braking_cap_slows_the_approach_only_and_stays_admissible():
    from safenav.deploy.shield import braking_cap

    cfg = ShieldConfig(brake_time=0.4, brake_acceleration=2.0)
    # a pillar 1.5 m ahead (combined radius 0.4: 1.1 m of room), one 1 m behind
    rel, vel, rad, valid, planar = scene([[1.5, 0.0, 0.0], [-1.0, 0.0, 0.0]], planar=True)
    v = torch.tensor([[2.0, 0.0, 0.0], [-2.0, 0.0, 0.0], [0.0, 2.0, 0.0]])
    n = v.shape[0]
    rel, valid, planar, rad = (t.expand(n, *t.shape[1:]) for t in (rel, valid, planar, rad))
    out, capped = braking_cap(v, rel, valid, planar, rad, cfg)
    assert capped.tolist() == [True, True, False]  # towards each pillar: slowed; beside: not
    c = out[0, 0].item()
    assert c * 0.4 + c * c / 4.0 == pytest.approx(1.1, rel=1e-4)
    assert out[1, 0].item() < 0 and torch.equal(out[2], v[2])
    assert torch.allclose(out / out.norm(dim=-1, keepdim=True), v / v.norm(dim=-1, keepdim=True))
    # scaling down never enters a static velocity obstacle that the fast velocity avoided
    gen = torch.Generator().manual_seed(0)
    pts = torch.rand(64, 6, 3, generator=gen) * 6 - 3
    pts[..., 2] = 0.0
    v = torch.rand(64, 3, generator=gen) * 4 - 2
    ok = torch.ones(64, 6, dtype=torch.bool)
    r = torch.full((64, 6), 0.4)
    flat = torch.ones(64, 6, dtype=torch.bool)
    zero = torch.zeros(64, 6, 3)
    before = admissible(v, pts, zero, r, ok, flat, cfg)
    slow, _ = braking_cap(v, pts, ok, flat, r, cfg)
    after = admissible(slow, pts, zero, r, ok, flat, cfg)
    assert before.any() and bool((after | ~before).all())


def test_the_sliding_cap_keeps_the_velocity_along_the_pillar():
    """``brake_slide``: head-on into a pillar it has no room left for, the scaled cap stops the
    vehicle and the sliding one keeps its sideways component; on random scenes every closing
    speed ends within its braking speed, as the scaled cap's do."""
    from safenav.deploy.shield import (
        _shield_static_and_tracked,
        braking_cap,
        braking_slide,
        braking_speed,
    )

    cfg = ShieldConfig(brake_time=0.4, brake_acceleration=2.0)
    rel, _, rad, valid, planar = scene([[0.45, 0.0, 0.0]], planar=True)  # 0.05 m of room
    v = torch.tensor([[1.5, 1.0, 0.0]])
    out, changed = braking_slide(v, rel, valid, planar, rad, cfg)
    assert changed.item() and out[0, 1].item() == pytest.approx(1.0)
    assert out[0, 0].item() == pytest.approx(
        braking_speed(torch.tensor(0.05), cfg).item(), abs=1e-5
    )
    gen = torch.Generator().manual_seed(1)
    pts = torch.rand(64, 6, 3, generator=gen) * 6 - 3
    pts[..., 2] = 0.0
    v = torch.rand(64, 3, generator=gen) * 4 - 2
    ok, flat = torch.ones(64, 6, dtype=torch.bool), torch.ones(64, 6, dtype=torch.bool)
    r = torch.full((64, 6), 0.4)
    slid, changed = braking_slide(v, pts, ok, flat, r, cfg)
    dist = pts.norm(dim=-1)
    closing = (pts * slid[:, None, :]).sum(-1) / dist
    assert changed.any() and bool((closing <= braking_speed(dist - r, cfg) + 1e-5).all())
    # the passes, not the final scaling, do the work: the slid velocities keep more speed
    scaled, capped = braking_cap(v, pts, ok, flat, r, cfg)
    assert torch.equal(changed, capped)
    assert slid[changed].norm(dim=-1).mean() > 1.2 * scaled[changed].norm(dim=-1).mean()
    assert torch.equal(braking_slide(v, pts, ok, flat, r, cfg, passes=0)[0], scaled)
    # in the shield, off by default; on, it slides where the scaled cap stops
    d = rel.norm(dim=-1)
    act = torch.tensor([[0.75, 0.5, 0.0]])
    scaled, _ = _shield_static_and_tracked(rel, valid, planar, d, torch.zeros(1, 5, 10), act, cfg)
    slide = ShieldConfig(brake_time=0.4, brake_acceleration=2.0, brake_slide=True)
    slid, c = _shield_static_and_tracked(rel, valid, planar, d, torch.zeros(1, 5, 10), act, slide)
    assert c.item() and slid[0, 1].item() > 2 * scaled[0, 1].abs().item()


def test_the_braking_cap_spares_moving_obstacles_and_keeps_the_altitude_band():
    """In the shield: off by default (bit for bit); on, it slows the vehicle near a pillar,
    leaves the velocity where slowing down would stay in a mover's path, and limits the descent
    near the ground when the altitude is known."""
    from safenav.deploy.shield import _shield_static_and_tracked

    cfg = ShieldConfig(brake_time=0.4, brake_acceleration=2.0)
    rel = torch.tensor([[[1.2, 0.6, 0.0]]])  # a pillar ahead and to the left: the VO is clear
    valid, planar, dist = torch.tensor([[True]]), torch.tensor([[True]]), rel.norm(dim=-1)
    dyn = torch.zeros(1, 5, 10)
    act = torch.tensor([[1.0, 0.0, 0.0]])
    off, c0 = _shield_static_and_tracked(rel, valid, planar, dist, dyn, act, ShieldConfig())
    assert torch.equal(off, act) and not c0.item()
    on, c1 = _shield_static_and_tracked(rel, valid, planar, dist, dyn, act, cfg)
    assert c1.item() and 0 < on[0, 0].item() < 1.0 and on[0, 1].item() == 0.0
    # a mover closing head-on from 2.5 m at 1.6 m/s: stopping would wait in its path
    dyn[0, 0, :3] = torch.tensor([1.0, 0.0, 0.0])
    dyn[0, 0, 3] = 2.5 / cfg.lidar_range
    dyn[0, 0, 5] = -1.6 / cfg.v_max
    dyn[0, 0, 8] = 0.0  # the narrowest cylinder
    away = torch.tensor([[0.0, -1.0, 0.0]])  # sideways, out of the mover's way
    mv, _ = _shield_static_and_tracked(rel, valid, planar, dist, dyn, away, cfg)
    assert mv[0, 1].item() < 0 and mv.norm().item() > 0.4
    # near the ground (z = 0.5, 0.2 m of room above z_min + margin): descent slowed, climb kept
    far = torch.tensor([[[4.5, 0.0, 0.0]]])
    down = torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.0, 1.0]])
    two = lambda t: t.expand(2, *t.shape[1:])  # noqa: E731
    out, c2 = _shield_static_and_tracked(two(far), two(valid) & False, two(planar), two(dist),
                                         torch.zeros(2, 5, 10), down, cfg, None,
                                         torch.tensor([0.5, 0.5]))  # fmt: skip
    assert c2.tolist() == [True, False]
    assert out[0, 2].item() * cfg.v_max == pytest.approx(-2 * (math.sqrt(0.36) - 0.4), abs=1e-5)
    assert torch.equal(out[1], down[1])


@pytest.mark.slow
def test_the_braking_shield_cuts_collisions_on_a_validation_map():
    """The memory shield with the map scan, with and without the braking cap, flying a scripted
    policy straight at the goal on validation map 12345 (64 episodes): the cap collides less."""
    from safenav.deploy.shield import shield_for_memory
    from safenav.experiments.evaluate import evaluate

    cfg = make_config("paper")
    rates = []
    for brake in (False, True):
        shield = shield_for_memory(1, True, 0.3, brake=brake)
        result = evaluate(go_to_goal, cfg, env_seed=12345, episodes=64, shield=shield)
        rates.append(result["collision_rate"])
    assert rates[1] < rates[0]


def test_keep_moving_takes_a_way_round_where_the_nearest_velocity_stalls() -> None:
    """ShieldConfig.keep_moving: before a row of pillars the nearest admissible velocity to a
    goal-ward one is (nearly) a hover; the choice that keeps moving slides along the row at no
    less than the fraction of the policy's speed, admissible, and does not turn back."""
    v = torch.tensor([[2.0, 0.0, 0.0]])
    rel, vel, rad, valid, planar = scene([[1.0, -0.6, 0.0], [1.0, 0.0, 0.0], [1.0, 0.6, 0.0]],
                                         planar=True)  # fmt: skip
    nearest_out, _ = velocity_obstacle_shield(v, rel, vel, rad, valid, planar, ShieldConfig())
    assert float(nearest_out[0, :2].norm()) < 1.0  # the premise: it stalls
    cfg = ShieldConfig(keep_moving=0.5)
    out, corrected = velocity_obstacle_shield(v, rel, vel, rad, valid, planar, cfg)
    assert bool(corrected[0]) and bool(admissible(out, rel, vel, rad, valid, planar, cfg)[0])
    assert float(out[0, :2].norm()) >= 1.0 and float(out[0, 0]) >= 0.0
    # Where the nearest admissible velocity is fast enough, the choice is NavRL's.
    one = scene([[1.5, 0.05, 0.0]], planar=True)
    a, _ = velocity_obstacle_shield(v, *one, ShieldConfig(), compiled=False)
    b, _ = velocity_obstacle_shield(v, *one, cfg, compiled=False)
    assert torch.equal(a, b)
    # One vehicle on the CPU: the same choice as the batch (the kernel does not model it).
    one_out, _ = velocity_obstacle_shield(v, rel, vel, rad, valid, planar, cfg, compiled=True)
    torch.testing.assert_close(one_out, out)
    with pytest.raises(ValueError, match="keep_moving"):
        MemoryShield(1, keep_moving=1.5)
