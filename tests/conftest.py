"""Shared test fixtures, and the order of the suite under pytest-xdist."""

from __future__ import annotations

import os

import gymnasium as gym
import numpy as np
import pytest
import torch

if os.environ.get("PYTEST_XDIST_WORKER"):
    # `make test` runs two workers on a 2-core machine: two torch thread pools of two threads each
    # would oversubscribe it (see one_thread below).
    torch.set_num_threads(1)


def pytest_collection_modifyitems(config, items):
    """The tests marked ``long`` (15 s or more each) first, so that under xdist the two workers
    share them and finish together on the short ones, instead of one long test running alone at
    the end."""
    items.sort(key=lambda item: item.get_closest_marker("long") is None)  # stable sort


@pytest.fixture
def one_thread():
    """One torch thread: on a loaded 2-core machine OpenMP oversubscription costs 50x.

    Modules opt in with ``pytestmark = pytest.mark.usefixtures("one_thread")``.
    """
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


class CounterEnv(gym.Env):
    """obs = [t]; the episode ends at t = 3, terminated (``terminal``) or truncated; cost 1 at t = 3
    (reported in the step's info, as Safety-Gymnasium does); success = terminated. The truncation
    and final-observation tests of CSAC and PPO (``from conftest import CounterEnv``)."""

    observation_space = gym.spaces.Box(-np.inf, np.inf, (1,), np.float32)
    action_space = gym.spaces.Box(-2.0, 2.0, (1,), np.float32)

    def __init__(self, terminal: bool) -> None:
        self.terminal, self.t = terminal, 0

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t = 0
        return np.zeros(1, np.float32), {}

    def step(self, action):
        self.t += 1
        end = self.t >= 3
        info = {"cost": 1.0 if end else 0.0, "success": self.terminal and end}
        return (
            np.full(1, self.t, np.float32),
            1.0,
            self.terminal and end,
            (not self.terminal) and end,
            info,
        )


@pytest.fixture
def world_seeds(monkeypatch) -> list[int]:
    """Every world seed drawn while the fixture is active (generate_world is the one door)."""
    import safenav.envs.nav as nav
    import safenav.envs.world as world

    seen: list[int] = []
    original = world.generate_world

    def recording(cfg, seed):
        seen.append(int(seed))
        return original(cfg, seed)

    monkeypatch.setattr(world, "generate_world", recording)
    monkeypatch.setattr(nav, "generate_world", recording)
    return seen


def run_cli(capsys, argv: list[str]) -> tuple[int, str, str]:
    """``safenav ARGV`` in-process: ``(exit code, stdout, stderr)`` (``from conftest import run_cli``)."""
    from safenav.cli import main

    capsys.readouterr()
    try:
        main(argv)
        code = 0
    except SystemExit as err:
        code = err.code if isinstance(err.code, int) else 1
    out, err = capsys.readouterr()
    return code, out, err


#: Train options for the paper's observation without the shield: the recipe the default csac
#: recipe is built on, before its shield, memory image and pillar list. The tests that load a
#: policy with the paper's three inputs, or need random flights to crash, train this.
PAPER_OBSERVATION = ("--config", "csac-maxcost-crashloss")


def train_tiny_csac(run_dir, *env_kwargs: str):
    """A 200-step CSAC run on the easy preset (4 envs, 32x32 networks, one torch thread) with
    ``--env-kwargs ENV_KWARGS...``: a checkpoint of that observation layout, for the tests of
    training, evaluating and deploying it (``from conftest import train_tiny_csac``). Returns
    ``run_dir``."""
    from safenav.cli import main

    main(["train", *PAPER_OBSERVATION, "--preset", "easy", "--seed", "1", "--num-envs", "4",
          "--total-steps", "200", "--env-kwargs", *env_kwargs,
          "--csac.learning-starts", "64", "--csac.batch-size", "16", "--csac.net.hidden", "32", "32",
          "--eval-every", "0", "--no-progress", "--no-tensorboard", "--torch-threads", "1",
          "--run-dir", str(run_dir)])  # fmt: skip
    return run_dir
