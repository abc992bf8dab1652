"""n-step cost targets (``--csac.cost-n-step``): the window's returns against hand-computed values,
the loss, the replay fields, the update using them, and a train + resume run."""

from __future__ import annotations

import pytest
import torch

from safenav.algos.config import CSACConfig
from safenav.algos.csac import CSAC
from safenav.algos.losses import cost_target, n_step_cost_target
from safenav.cli import main
from safenav.common.buffer import Batch, ReplayBuffer
from safenav.common.checkpoint import load_checkpoint
from safenav.common.nstep import NStepWindow

T = torch.tensor


def push(window: NStepWindow, t: int, cost, terminated, truncated):
    """One vector step of 2 envs whose observations carry the step index ``t`` (``s'`` = t + 1)."""
    n = len(cost)
    obs = {"x": torch.full((n, 1), float(t))}
    nxt = {"x": torch.full((n, 1), float(t + 1))}
    released = window.push(Batch(obs, torch.zeros(n, 1), torch.zeros(n), T(cost), nxt, T(terminated)),
                           T(truncated), torch.ones(n, dtype=torch.bool))  # fmt: skip
    return None if released is None else released[0]


def test_window_returns_hand_computed_n_step_costs():
    w = NStepWindow(3, gamma=0.5)
    # env 0 collides at step 2 (cost 1, terminated); env 1 flies on, its time limit at step 1
    assert push(w, 0, [0.0, 0.0], [False, False], [False, False]) is None
    assert push(w, 1, [0.0, 0.0], [False, False], [False, True]) is None
    out = push(w, 2, [1.0, 0.0], [True, False], [False, False])
    # step 0: env 0: 0 + 0.5*0 + 0.25*1 = 0.25, no bootstrap after the collision, s_{t+m} = s_3
    #         env 1: truncated at step 1 -> m = 2: cost 0, bootstrap gamma^2 from s_2 (not s_3)
    torch.testing.assert_close(out.costs_n, T([0.25, 0.0]))
    torch.testing.assert_close(out.discount_n, T([0.0, 0.25]))
    torch.testing.assert_close(out.next_obs_n["x"], T([[3.0], [2.0]]))
    torch.testing.assert_close(out.obs["x"], T([[0.0], [0.0]]))  # the one-step fields of step 0
    torch.testing.assert_close(out.next_obs["x"], T([[1.0], [1.0]]))
    # step 1: env 0: 0.5*1; env 1's episode ended here: m = 1, gamma from s_2
    out = push(w, 3, [0.0, 0.0], [False, False], [False, False])
    torch.testing.assert_close(out.costs_n, T([0.5, 0.0]))
    torch.testing.assert_close(out.discount_n, T([0.0, 0.5]))
    # step 2 for env 1 starts a new episode: a full window, gamma^3 from s_5
    out = push(w, 4, [0.0, 0.0], [False, False], [False, False])
    torch.testing.assert_close(out.costs_n, T([1.0, 0.0]))
    torch.testing.assert_close(out.discount_n, T([0.0, 0.125]))
    torch.testing.assert_close(out.next_obs_n["x"], T([[3.0], [5.0]]))


def test_one_step_window_is_eq6_and_cut_ends_the_episodes():
    w = NStepWindow(1, gamma=0.9)
    out = push(w, 0, [1.0, 0.0], [True, False], [False, False])
    torch.testing.assert_close(out.costs_n, T([1.0, 0.0]))
    torch.testing.assert_close(out.discount_n, T([0.0, 0.9]))  # = gamma (1 - terminated)
    q = T([[0.2, 0.4], [0.6, 0.8]])
    torch.testing.assert_close(n_step_cost_target(out.costs_n, out.discount_n, q),
                               cost_target(out.costs, out.terminated, q, 0.9))  # fmt: skip
    w = NStepWindow(3, gamma=0.5)
    push(w, 0, [0.0, 0.0], [False, False], [False, False])
    w.cut()  # the trainer reset every env: step 0's episodes end there (truncation)
    push(w, 1, [1.0, 1.0], [True, True], [False, False])
    out = push(w, 2, [0.0, 0.0], [False, False], [False, False])
    torch.testing.assert_close(out.costs_n, T([0.0, 0.0]))  # the later collision is not counted
    torch.testing.assert_close(out.discount_n, T([0.5, 0.5]))
    torch.testing.assert_close(out.next_obs_n["x"], T([[1.0], [1.0]]))
    with pytest.raises(ValueError):
        NStepWindow(0, 0.9)


def test_n_step_cost_target_hand_value_and_reductions():
    q = T([[0.2, 0.4], [0.6, 0.8]])  # mean [0.4, 0.6], max [0.6, 0.8]
    c, disc = T([0.25, 0.0]), T([0.0, 0.5])
    torch.testing.assert_close(n_step_cost_target(c, disc, q), T([0.25, 0.3]))
    torch.testing.assert_close(n_step_cost_target(c, disc, q, "max"), T([0.25, 0.4]))
    with pytest.raises(ValueError):
        n_step_cost_target(c, disc, q, "median")


def shapes():
    return {"image": (1, 4, 6), "state": (3,)}


def fill(buf: ReplayBuffer, n: int, seed: int = 0) -> None:
    g = torch.Generator().manual_seed(seed)
    obs = {k: torch.rand(n, *s, generator=g) for k, s in shapes().items()}
    nxt = {k: torch.rand(n, *s, generator=g) for k, s in shapes().items()}
    far = {k: torch.rand(n, *s, generator=g) for k, s in shapes().items()}
    buf.add(obs, torch.rand(n, 2, generator=g), torch.rand(n, generator=g), torch.zeros(n), nxt,
            torch.zeros(n), torch.ones(n, dtype=torch.bool), torch.rand(n, generator=g), far,
            torch.full((n,), 0.5))  # fmt: skip


def test_buffer_keeps_n_step_fields_and_round_trips():
    buf = ReplayBuffer(32, shapes(), 2, n_step=True)
    fill(buf, 20)
    batch = buf.sample(64)
    assert batch.costs_n.shape == (64,) and batch.next_obs_n["image"].shape == (64, 1, 4, 6)
    assert torch.all(batch.discount_n == 0.5)
    copy = ReplayBuffer(32, shapes(), 2, n_step=True)
    copy.load_state_dict(buf.state_dict())
    torch.testing.assert_close(copy.storage[:20], buf.storage[:20])
    with pytest.raises(ValueError, match="n-step"):  # a buffer saved without the fields
        copy.load_state_dict(ReplayBuffer(32, shapes(), 2).state_dict())
    with pytest.raises(ValueError, match="costs_n"):
        buf.add({k: torch.zeros(1, *s) for k, s in shapes().items()}, torch.zeros(1, 2),
                torch.zeros(1), torch.zeros(1), {k: torch.zeros(1, *s) for k, s in shapes().items()},
                torch.zeros(1))  # fmt: skip
    assert ReplayBuffer(4, shapes(), 2).sample  # one-step buffers: no n-step fields
    assert ReplayBuffer(4, {"x": (2,)}, 1).costs_n is None


def test_update_fits_the_cost_critics_to_the_n_step_target():
    """With the cost-critic learning rate only, the cost critics move towards ``y_C^(n)``: a batch
    whose n-step return is 1 (a collision m steps ahead) raises Q_C; discount 0 stops bootstrap."""
    cfg = CSACConfig(cost_n_step=5, actor_lr=0.0, reward_critic_lr=0.0, alpha_lr=0.0, lambda_lr=0.0,
                     cost_critic_lr=1e-2)  # fmt: skip
    torch.manual_seed(0)
    agent = CSAC({"x": (4,)}, 2, cfg)
    buf = ReplayBuffer(64, {"x": (4,)}, 2, n_step=True)
    x = torch.rand(64, 4)
    buf.add({"x": x}, torch.rand(64, 2) * 2 - 1, torch.zeros(64), torch.zeros(64), {"x": x},
            torch.zeros(64), None, torch.ones(64), {"x": x}, torch.zeros(64))  # fmt: skip
    with torch.no_grad():
        before = agent.qc(x, buf.actions).mean()
    for _ in range(200):
        agent.update(buf.sample(64))
    with torch.no_grad():
        after = agent.qc(x, buf.actions).mean()
    # the one-step target (cost 0 everywhere) would keep Q_C near 0; the n-step one says 1
    assert after == pytest.approx(1.0, abs=0.1) and abs(float(before)) < 0.5


def test_train_with_n_step_costs_and_resume_with_the_buffer(tmp_path):
    from tests.test_train_cli import FAST

    run_dir = tmp_path / "nstep"
    base = ["train", "--algo", "csac", "--preset", "easy", "--run-dir", str(run_dir), *FAST,
            "--csac.cost-n-step", "4", "--save-buffer"]  # fmt: skip
    main([*base, "--total-steps", "200"])
    ckpt = load_checkpoint(run_dir / "checkpoint.pt")
    assert ckpt["config"]["csac"]["cost_n_step"] == 4
    assert "costs_n" in ckpt["buffer"] and len(ckpt["nstep_window"]["steps"]) == 3
    main(["train", "--algo", "csac", "--resume", str(run_dir), "--total-steps", "400",
          "--no-progress"])  # fmt: skip
    assert load_checkpoint(run_dir / "checkpoint.pt")["global_step"] == 400
    with pytest.raises(SystemExit):
        main(["train", "--algo", "csac", "--run-dir", str(tmp_path / "bad"), *FAST,
              "--csac.cost-n-step", "0"])  # fmt: skip
