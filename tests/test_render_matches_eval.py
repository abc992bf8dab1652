"""``safenav render --episode K`` flies episode K of ``safenav eval``'s batch, bit for bit, behind
the shield too: one vehicle is shielded by the torch path a batch takes, not by the compiled
kernel, whose ~1 ulp of other rounding parts the flights within seconds (validation map 12347,
episode 0, the scripted policy behind the shield: 59.3 s alone with the kernel, 57.8 s in
``safenav eval``'s batch; with the torch path 57.8 s both ways)."""

from __future__ import annotations

import pytest
import torch

from safenav.deploy import kernels
from safenav.deploy import shield as sh
from safenav.envs.config import make_config
from safenav.envs.nav import SafeNavVectorEnv
from safenav.envs.scripted import potential_field
from safenav.experiments import flight
from safenav.experiments.evaluate import evaluate, fixed_test_scenario

SHIELD = dict(memory=1, map_scan=True, mover_margin=0.3, brake=True)


def _first_parting(steps: int) -> int | None:
    """Env 0 of a batch of 4 and the same episode alone, each behind its own shield, stepped
    together: the first step whose shielded actions differ (None if none within ``steps``)."""
    cfg, starts, goals = fixed_test_scenario(make_config("paper"), 12347, 4)
    runs = []
    for n in (1, 4):
        env = SafeNavVectorEnv(n, config=cfg, output="torch", autoreset_mode="Disabled")
        obs, _ = env.reset(seed=12347, options={"starts": starts[:n], "goals": goals[:n]})
        runs.append([env, obs, sh.shield_for_memory(**SHIELD)])
    for t in range(steps):
        out = []
        for run in runs:
            env, obs, shield = run
            action = shield(env, obs, potential_field(obs))
            run[1] = env.step(action)[0]
            out.append(action[0])
        if not torch.equal(out[0], out[1]):
            return t
    return None


@pytest.mark.skipif(not kernels.AVAILABLE, reason="the compiled kernel needs Numba")
def test_one_vehicle_is_shielded_as_in_a_batch_within_batched_arithmetic():
    assert _first_parting(20) is not None  # the kernel's rounding (step 13 when measured)
    with sh.batched_arithmetic():
        assert _first_parting(20) is None
    assert sh._one_vehicle_kernel  # and back


def test_eval_and_render_fly_the_shield_in_batched_arithmetic(monkeypatch):
    seen = []

    def spy(env, obs, action):
        seen.append(sh._one_vehicle_kernel)
        return action

    monkeypatch.setattr(sh, "shield_for_memory", lambda *a, **k: spy)
    evaluate(potential_field, make_config("paper"), env_seed=12347, episodes=1, shield=spy)
    flight.fly_frames(None, "scripted", "paper", 12347, 0, None, 1, True, 0.3, True)
    assert seen and not any(seen)
    assert sh._one_vehicle_kernel


def test_batched_arithmetic_is_restored_after_an_error():
    with pytest.raises(RuntimeError), sh.batched_arithmetic():
        assert not sh._one_vehicle_kernel
        raise RuntimeError("restored even so")
    assert sh._one_vehicle_kernel


def test_a_network_flying_alone_rounds_as_in_the_batch():
    """Torch's CPU matrix products round 1-3 rows differently from a batch (~1e-7 in the actions
    of this committed policy, with its memory image), which parted a rendered validation episode
    from the same episode in ``safenav eval``'s batch (a timeout there, an arrival rendered):
    ``flight.in_batch_rows`` gives the network a batch's rows, and ``fly_frames`` flies
    checkpoints through it."""
    import inspect
    from pathlib import Path

    from safenav.algos.policy import load_policy

    path = Path(__file__).resolve().parents[1] / "results/csac-v1/levers/policies"
    fn = load_policy(path / "shieldml-g995-s1/step_001000192.pt")
    cfg, starts, goals = fixed_test_scenario(fn.env_config(), 12345, 100)
    env = SafeNavVectorEnv(100, config=cfg, output="torch", autoreset_mode="Disabled")
    obs, _ = env.reset(seed=12345, options={"starts": starts, "goals": goals})
    with torch.no_grad():
        batch = fn(obs)
        for n in (1, 2, 3):
            alone = flight.in_batch_rows(fn)({k: v[:n] for k, v in obs.items()})
            assert alone.shape == (n, 3) and torch.equal(alone, batch[:n])
    assert "in_batch_rows(fn)" in inspect.getsource(flight.fly_frames)
