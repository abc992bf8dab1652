"""SafeNav-v1 under Gymnasium 1.x's conventions.

The single env passes ``gymnasium.utils.env_checker.check_env`` (tests/test_env.py). Gymnasium
ships no checker for vector envs, so :func:`check_vector_env` does for SafeNavVectorEnv what
``check_env`` does for a single env (spaces, dtypes, shapes, determinism, fresh data per call)
and checks the autoreset mode the env declares in ``metadata["autoreset_mode"]``, the way
Gymnasium's own ``SyncVectorEnv`` behaves in it: ``SAME_STEP`` (the returned observation of a
finished env is the first of its next episode, ``final_obs`` / ``final_info`` hold the last step,
every step counts toward an episode) and ``DISABLED`` (nothing resets by itself; ``reset`` with
``options["reset_mask"]`` restarts the chosen envs). Then the wrappers that read these keys:
``RecordEpisodeStatistics`` (vector and single) and ``DictInfoToList``.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import data_equivalence
from gymnasium.vector import AutoresetMode
from gymnasium.wrappers import RecordEpisodeStatistics
from gymnasium.wrappers.vector import DictInfoToList
from gymnasium.wrappers.vector import RecordEpisodeStatistics as VecRecordEpisodeStatistics
from packaging.version import Version

import safenav  # noqa: F401  (registers SafeNav-v1)
from safenav.envs.nav import SafeNavVectorEnv

gym_version = Version(gym.__version__)
# Older Gymnasium wrappers (the floor is 1.1, `make test-floors`): the vector
# RecordEpisodeStatistics drops the first step of every SAME_STEP episode before 1.4 (it assumed
# NEXT_STEP), and DictInfoToList needs a "_key" mask for every key, nested ones too, before 1.2.2.
OLD_RECORD = pytest.mark.skipif(gym_version < Version("1.4"), reason="SAME_STEP from gymnasium 1.4")
OLD_DICT_INFO = pytest.mark.skipif(gym_version < Version("1.2.2"), reason="gymnasium >= 1.2.2")

# Short episodes (2 s = 20 steps) in a sparse map: many episodes end, by timeout and collision.
FAST = dict(preset="easy", max_episode_seconds=2.0, num_static=40, num_dynamic=8)


def numpy_tree(x):
    """Tensors (output="torch") as NumPy arrays, dicts recursively; anything else unchanged."""
    if isinstance(x, dict):
        return {k: numpy_tree(v) for k, v in x.items()}
    return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else x


def shares_memory(a, b) -> bool:
    """Whether two returned structures share an array (a caller keeping one would see the other
    change), dicts recursively."""
    if isinstance(a, dict) and isinstance(b, dict):
        return any(shares_memory(a[k], b[k]) for k in a.keys() & b.keys())
    if isinstance(a, np.ndarray) and isinstance(b, np.ndarray):
        return np.shares_memory(a, b)
    return False


def check_info(info: dict, n: int) -> None:
    """Gymnasium's vector info layout: every leaf is an array of ``n`` rows and every ``_key``
    is a boolean ``(n,)`` mask of a present ``key``."""
    for key, value in info.items():
        if isinstance(value, dict):
            check_info(value, n)
            continue
        assert isinstance(value, np.ndarray) and value.shape[:1] == (n,), key
        if key.startswith("_"):
            assert value.dtype == np.bool_ and value.shape == (n,), key
            assert key[1:] in info, f"mask {key} without its key"


def check_vector_env(envs, steps: int = 60, seed: int = 5) -> dict:
    """The vector-env counterpart of ``check_env``, and the declared autoreset mode's behaviour.

    Returns counts of what was exercised (finished episodes, masked resets) so that callers can
    assert the checks ran on real episode ends.
    """
    env = envs.unwrapped
    n = envs.num_envs
    mode = envs.metadata["autoreset_mode"]
    assert isinstance(mode, AutoresetMode) and mode in (AutoresetMode.SAME_STEP,
                                                        AutoresetMode.DISABLED)  # fmt: skip
    assert mode == env.autoreset_mode
    space, single = envs.observation_space, envs.single_observation_space
    assert space == gym.vector.utils.batch_space(single, n)
    assert envs.action_space == gym.vector.utils.batch_space(envs.single_action_space, n)

    # reset: in the space, deterministic for a seed, fresh data on every call
    obs, info = (numpy_tree(x) for x in envs.reset(seed=seed))
    assert space.contains(obs) and isinstance(info, dict)
    check_info(info, n)
    obs2, info2 = (numpy_tree(x) for x in envs.reset(seed=seed))
    assert data_equivalence(obs, obs2, exact=True) and data_equivalence(info, info2, exact=True)
    assert not shares_memory(obs, obs2)

    rng = np.random.default_rng(seed)
    actions = rng.uniform(-1, 1, (steps, n, 3)).astype(np.float32)
    as_env = (lambda a: torch.as_tensor(a)) if env.output == "torch" else (lambda a: a)  # noqa: E731
    counts = {"episodes": 0, "masked_resets": 0}
    length = np.zeros(n, dtype=np.int64)  # steps of the running episode, as the caller sees it
    trace, previous = [], None
    for t in range(steps):
        obs, reward, term, trunc, info = (numpy_tree(x) for x in envs.step(as_env(actions[t])))
        trace.append((obs, reward, term, trunc))
        assert space.contains(obs), f"step {t}: observation outside the observation space"
        assert reward.shape == (n,) and np.issubdtype(reward.dtype, np.floating)
        assert term.shape == trunc.shape == (n,) and term.dtype == trunc.dtype == np.bool_
        assert not (term & trunc).any()
        check_info(info, n)
        if previous is not None:
            assert not shares_memory(previous[0], obs), f"step {t} reused an observation array"
            assert not shares_memory(previous[1], info), f"step {t} reused an info array"
        previous = (obs, info)
        length += 1
        done = term | trunc
        if not done.any():
            assert "episode" not in info and "final_obs" not in info
            continue
        counts["episodes"] += int(done.sum())
        # Episode statistics: Gymnasium's r / l / t beside SafeNav's own keys, 0 where not done
        ep = info["episode"]
        np.testing.assert_array_equal(info["_episode"], done)
        np.testing.assert_array_equal(ep["l"], np.where(done, length, 0))
        np.testing.assert_array_equal(ep["l"][done], ep["length"][done])
        np.testing.assert_array_equal(ep["r"], np.where(done, ep["return"], 0.0))
        assert (ep["t"][done] >= 0).all() and (ep["t"][~done] == 0).all()
        # a new episode starts hovering: velocity (state[5:8]) is zero in its first observation
        fresh = np.abs(obs["state"][:, 5:8]).max(-1) == 0
        if mode == AutoresetMode.SAME_STEP:
            np.testing.assert_array_equal(info["_final_obs"], done)
            np.testing.assert_array_equal(info["_final_info"], done)
            final = {k: v[done] for k, v in info["final_obs"].items()}
            assert all(single.contains({k: v[j] for k, v in final.items()})
                       for j in range(int(done.sum())))  # fmt: skip
            # the last observation is not the returned one: that is the next episode's first
            assert fresh[done].all() and not np.array_equal(final["state"], obs["state"][done])
            fi = info["final_info"]
            for key in ("cost", "success", "collision", "clearance"):
                np.testing.assert_array_equal(fi[key], info[key])
                np.testing.assert_array_equal(fi[f"_{key}"], done)
            np.testing.assert_array_equal(fi["_episode"], done)
            np.testing.assert_array_equal(fi["episode"]["l"], ep["l"])
            length[done] = 0  # SAME_STEP: the next step is already the new episode's first
        else:
            # nothing resets by itself: a finished env's observation is still its last one
            assert "final_obs" not in info and "final_info" not in info
            assert not fresh[done].any()
            before = env.episode_counter.cpu().numpy().copy()
            obs_r, info_r = (numpy_tree(x) for x in envs.reset(options={"reset_mask": done}))
            counts["masked_resets"] += 1
            assert space.contains(obs_r)
            np.testing.assert_array_equal(info_r["_episode_id"], done)
            np.testing.assert_array_equal(info_r["episode_id"], before + done)
            assert (np.abs(obs_r["state"][done, 5:8]) == 0).all()
            for k in obs:  # the others fly on: their observation is unchanged
                np.testing.assert_array_equal(obs_r[k][~done], obs[k][~done])
            length[done] = 0

    # step determinism: the same seed and actions give the same transitions
    envs.reset(seed=seed)
    for t in range(steps):
        obs, reward, term, trunc, info = (numpy_tree(x) for x in envs.step(as_env(actions[t])))
        assert data_equivalence((obs, reward, term, trunc), trace[t], exact=True), f"step {t}"
        if mode == AutoresetMode.DISABLED and (term | trunc).any():
            envs.reset(options={"reset_mask": term | trunc})
    return counts


@pytest.mark.parametrize("output", ["numpy", "torch"])
def test_vector_env_passes_the_checks_with_same_step_autoreset(output):
    envs = gym.make_vec("SafeNav-v1", num_envs=6, output=output, **FAST)
    assert envs.metadata["autoreset_mode"] == AutoresetMode.SAME_STEP  # the default
    counts = check_vector_env(envs)
    assert counts["episodes"] >= 6


def test_vector_env_passes_the_checks_with_autoreset_disabled():
    envs = gym.make_vec("SafeNav-v1", num_envs=6, autoreset_mode="Disabled",
                        **FAST)  # fmt: skip
    assert envs.metadata["autoreset_mode"] == AutoresetMode.DISABLED
    counts = check_vector_env(envs)
    assert counts["episodes"] >= 6 and counts["masked_resets"] >= 2


def test_next_step_autoreset_is_refused_and_the_class_declares_same_step():
    assert SafeNavVectorEnv.metadata["autoreset_mode"] == AutoresetMode.SAME_STEP
    with pytest.raises(ValueError, match="NEXT_STEP is not supported"):
        SafeNavVectorEnv(2, autoreset_mode=AutoresetMode.NEXT_STEP)


def test_bad_reset_masks_are_clear_errors():
    env = SafeNavVectorEnv(3, **FAST)
    with pytest.raises(ValueError, match="first reset"):
        env.reset(options={"reset_mask": np.ones(3, bool)})
    env.reset(seed=0)
    for bad in (np.ones(2, bool), np.ones(3, int), np.zeros(3, bool)):
        with pytest.raises(ValueError, match="reset_mask"):
            env.reset(options={"reset_mask": bad})
    with pytest.raises(ValueError, match="seed"):
        env.reset(seed=1, options={"reset_mask": np.ones(3, bool)})
    # a masked reset with pinned episodes takes the masked rows of starts and goals
    starts = np.array([[0.0, 0.0, 1.0], [1.0, 2.0, 1.5], [2.0, 0.0, 1.0]], np.float32)
    goals = starts + np.float32(5.0)
    env.reset(options={"reset_mask": np.array([False, True, False]), "starts": starts,
                       "goals": goals})  # fmt: skip
    np.testing.assert_array_equal(env.start[1].numpy(), starts[1])
    assert not np.array_equal(env.start[0].numpy(), starts[0])


@pytest.mark.parametrize("mode", [pytest.param("SameStep", marks=OLD_RECORD), "Disabled"])
def test_record_episode_statistics_agrees_with_the_envs_own_r_l(mode):
    """The wrapper needs another ``stats_key``: SafeNav already writes ``info["episode"]`` (with
    its ``r`` / ``l`` / ``t``), and the wrapper refuses to overwrite it."""
    envs = gym.make_vec("SafeNav-v1", num_envs=4, autoreset_mode=mode, **FAST)
    with pytest.raises(ValueError, match="already exists"):
        wrapped = VecRecordEpisodeStatistics(envs)
        wrapped.reset(seed=0)
        for _ in range(40):
            wrapped.step(wrapped.action_space.sample())
    envs = VecRecordEpisodeStatistics(
        gym.make_vec("SafeNav-v1", num_envs=4, autoreset_mode=mode, **FAST),
        stats_key="gym_episode",
    )
    envs.reset(seed=0)
    envs.action_space.seed(0)
    ended = 0
    for _ in range(80):
        _, _, term, trunc, info = envs.step(envs.action_space.sample())
        done = term | trunc
        if not done.any():
            continue
        ended += int(done.sum())
        ours, theirs = info["episode"], info["gym_episode"]
        np.testing.assert_array_equal(info["_gym_episode"], info["_episode"])
        np.testing.assert_array_equal(ours["l"], theirs["l"])
        np.testing.assert_allclose(ours["r"], theirs["r"], rtol=1e-5, atol=1e-4)
        assert (np.abs(ours["t"] - theirs["t"]) < 0.5).all()  # two clocks, read a moment apart
        if mode == "Disabled":
            envs.reset(options={"reset_mask": done})
    assert ended >= 4


def test_single_env_record_episode_statistics_agrees_with_r_l():
    env = RecordEpisodeStatistics(gym.make("SafeNav-v1", **FAST), stats_key="gym_episode")
    env.reset(seed=2)
    env.action_space.seed(2)
    ended = 0
    for _ in range(60):
        _, _, term, trunc, info = env.step(env.action_space.sample())
        if term or trunc:
            ended += 1
            ep = info["episode"]
            assert ep["l"] == info["gym_episode"]["l"] == ep["length"]
            assert ep["r"] == pytest.approx(info["gym_episode"]["r"], rel=1e-5, abs=1e-4)
            assert 0 <= ep["t"] < 60
            env.reset()
    assert ended >= 2


@OLD_DICT_INFO
def test_dict_info_to_list_gives_per_env_final_obs_and_final_info():
    """With Gymnasium's DictInfoToList the batched ``final_obs`` becomes what a SyncVectorEnv
    gives: each finished env's own last observation, and its last step's info."""
    envs = DictInfoToList(gym.make_vec("SafeNav-v1", num_envs=4, **FAST))
    envs.reset(seed=3)
    envs.action_space.seed(3)
    seen = 0
    for _ in range(60):
        obs, _, term, trunc, infos = envs.step(envs.action_space.sample())
        assert len(infos) == 4
        for i, info in enumerate(infos):
            if not (term[i] or trunc[i]):
                assert "final_obs" not in info and "final_info" not in info
                continue
            seen += 1
            assert envs.single_observation_space.contains(info["final_obs"])
            assert not np.array_equal(info["final_obs"]["state"], obs["state"][i])
            fi = info["final_info"]
            assert fi["cost"] == info["cost"] and fi["episode"]["l"] == info["episode"]["l"] > 0
    assert seen >= 4
