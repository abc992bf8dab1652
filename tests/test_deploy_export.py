"""``safenav export``: the deterministic actor as ONNX; ONNX Runtime equals torch within 1e-5."""

from __future__ import annotations

import dataclasses
import json
import sys
import types
from pathlib import Path

import numpy as np
import pytest
import torch

from safenav.bench.latency import ReferenceActor
from safenav.deploy.export import (
    OnnxPolicy,
    TorchPolicy,
    export_onnx,
    input_names,
    load_actor,
    load_sidecar,
    random_observations,
)
from safenav.deploy.scripted import GoToGoalActor
from safenav.envs import make_config

pytest.importorskip("onnxruntime")


pytestmark = pytest.mark.usefixtures("one_thread")


def real_observations(cfg, steps=10, n=8):
    from safenav.commands.export import env_observations

    return env_observations(cfg, steps=steps, num_envs=n)


def assert_onnx_equals_torch(actor, cfg, path: Path, real) -> np.ndarray:
    """Export ``actor``, run the ONNX file on the observations ``real`` and check it against the
    torch actor (within 1e-5); returns the torch actions."""
    export_onnx(actor, cfg, path, check_observations=real)
    got = OnnxPolicy(path)(*(real[k] for k in input_names(cfg)))
    with torch.no_grad():
        ref = actor(*(torch.as_tensor(real[k]) for k in actor.input_names)).numpy()
    np.testing.assert_allclose(got, ref, atol=1e-5, rtol=0)
    return ref


@pytest.mark.parametrize("make_actor", [ReferenceActor, GoToGoalActor])
def test_onnx_runtime_equals_torch(tmp_path: Path, make_actor) -> None:
    cfg = make_config("easy")
    torch.manual_seed(0)
    actor = make_actor(cfg).eval()
    real = real_observations(cfg)
    meta = export_onnx(actor, cfg, tmp_path / "policy.onnx", check_observations=real)
    assert meta["check"]["max_abs_diff"] <= 1e-5
    ort_policy, torch_policy = OnnxPolicy(tmp_path / "policy.onnx"), TorchPolicy(actor)
    for obs in (real, {k: v.numpy() for k, v in random_observations(cfg, 33, seed=7).items()}):
        got = ort_policy(obs["state"], obs["lidar"], obs["dynamic"])
        ref = torch_policy(obs["state"], obs["lidar"], obs["dynamic"])
        assert got.shape == (len(obs["state"]), 3)
        np.testing.assert_allclose(got, ref, atol=1e-5, rtol=0)
    one = {k: v[:1] for k, v in real.items()}  # batch 1, as on board
    np.testing.assert_allclose(
        ort_policy(*one.values()), torch_policy(*one.values()), atol=1e-5, rtol=0
    )


def test_sidecar_describes_the_conventions(tmp_path: Path) -> None:
    cfg = make_config("medium", v_max=1.5, control_hz=20.0)
    export_onnx(GoToGoalActor(cfg), cfg, tmp_path / "p.onnx", checkpoint="x.pt")
    meta, back = load_sidecar(tmp_path / "p.onnx")
    assert back == cfg
    assert meta["v_max"] == 1.5 and meta["control_hz"] == 20.0 and meta["checkpoint"] == "x.pt"
    obs = meta["observation"]
    assert (
        obs["state"]["shape"] == [8]
        and obs["lidar"]["shape"] == [4, 36]
        and obs["dynamic"]["shape"] == [5, 10]
    )
    assert obs["state"]["scale"] == {"horizontal_distance_to_goal_m": 20.0, "z_distance_to_goal_m": 4.0,
                                     "velocity_m_s": 1.5}  # fmt: skip
    assert obs["lidar"]["rows_elevation_deg"] == [-10.0, 0.0, 10.0, 20.0]
    assert meta["action"]["scale_m_s"] == 1.5 and meta["action"]["frame"] == "goal"
    assert len(meta["sha256"]) == 64
    assert meta["inputs"] == ["state", "lidar", "dynamic"] and "static" not in obs


def test_cli_export_scripted_and_errors(tmp_path: Path, capsys) -> None:
    from safenav.cli import main

    out = tmp_path / "policy.onnx"
    main(["export", "--scripted", "--preset", "easy", "--onnx", str(out)])
    assert (
        out.exists()
        and json.loads(Path(str(out) + ".json").read_text())["format"] == "safenav-policy/1"
    )
    for argv, msg in ((["export", "--onnx", str(out)], "no CHECKPOINT"),
                      (["export", str(tmp_path / "missing.pt")], "not found")):  # fmt: skip
        with pytest.raises(SystemExit) as e:
            main(argv)
        assert e.value.code == 2
        assert msg in capsys.readouterr().err


def test_load_actor_reads_the_trainers_policy(tmp_path: Path, monkeypatch) -> None:
    """The adapter to ``safenav.algos.policy.load_policy`` (``Policy.actor``, env config in
    ``Policy.env_config()`` or ``Policy.meta``)."""
    cfg = make_config("easy")
    actor = GoToGoalActor(cfg)

    class WithMethod:
        def __init__(self):
            self.actor = actor

        def env_config(self):
            return cfg

    class WithMeta:
        actor = GoToGoalActor(cfg)
        meta = {"env_config": dataclasses.asdict(cfg), "algo": "csac"}

    ckpt = tmp_path / "c.pt"
    ckpt.write_bytes(b"x")
    for policy in (WithMethod(), WithMeta()):
        module = types.ModuleType("safenav.algos.policy")
        module.load_policy = lambda path, device="cpu", _p=policy: _p
        monkeypatch.setitem(sys.modules, "safenav.algos.policy", module)
        got_actor, got_cfg = load_actor(ckpt)
        assert got_actor is policy.actor and got_cfg == cfg


def test_the_trainers_actor_exports_with_its_own_input_order(tmp_path: Path) -> None:
    """The trainer's DeterministicActor takes its inputs in ``input_names`` order (for SafeNav:
    state, lidar, dynamic); the export and the runtime feed it by name, whatever the order."""
    from safenav.algos.policy import build_actor
    from safenav.nn.networks import NetConfig

    cfg = make_config("easy")
    torch.manual_seed(0)
    meta = {"net": dataclasses.asdict(NetConfig()), "action_dim": 3,
            "obs_shapes": {"dynamic": [5, 10], "lidar": [4, 36], "state": [8]}}  # fmt: skip
    actor = build_actor(meta).eval()
    assert tuple(actor.input_names) == ("state", "lidar", "dynamic")
    real = real_observations(cfg, steps=5)
    ref = assert_onnx_equals_torch(actor, cfg, tmp_path / "csac.onnx", real)
    np.testing.assert_allclose(
        TorchPolicy(actor)(real["state"], real["lidar"], real["dynamic"]), ref, atol=1e-6
    )


def test_a_policy_with_a_pillar_list_exports_with_a_static_input(tmp_path: Path) -> None:
    """``static_tracked`` K > 0: a fourth ONNX input ``static (N, K, 7)``, in the actor's order,
    ONNX Runtime equal to torch on the env's observations (pillar lists from its map) and random
    ones; the sidecar describes it; the policy refuses to run without it."""
    from safenav.algos.policy import build_actor
    from safenav.nn.networks import NetConfig

    cfg = make_config("easy", static_tracked=4, static_source="map")
    torch.manual_seed(0)
    shapes = {"dynamic": [5, 10], "lidar": [4, 36], "state": [8], "static": [4, 7]}
    meta = {"net": dataclasses.asdict(NetConfig()), "action_dim": 3, "obs_shapes": shapes}
    actor = build_actor(meta).eval()
    assert tuple(actor.input_names) == input_names(cfg) == ("state", "lidar", "dynamic", "static")
    real = real_observations(cfg, steps=5)
    assert real["static"].shape[1:] == (4, 7) and real["static"][..., 6].sum() > 0
    path = tmp_path / "static.onnx"
    ref = assert_onnx_equals_torch(actor, cfg, path, real)
    policy, torch_policy = OnnxPolicy(path), TorchPolicy(actor)
    assert policy.input_names == ("state", "lidar", "dynamic", "static")
    np.testing.assert_allclose(torch_policy(*(real[k] for k in input_names(cfg))), ref, atol=1e-6)
    rand = {k: v.numpy() for k, v in random_observations(cfg, 17, seed=3).items()}
    np.testing.assert_allclose(policy(*rand.values()), torch_policy(*rand.values()), atol=1e-5,
                               rtol=0)  # fmt: skip
    # the list reaches the action
    moved = policy(rand["state"], rand["lidar"], rand["dynamic"], rand["static"] * 0.5)
    assert np.abs(moved - policy(*rand.values())).max() > 1e-4
    sidecar, back = load_sidecar(path)
    assert back == cfg and sidecar["inputs"] == ["state", "lidar", "dynamic", "static"]
    assert sidecar["observation"]["static"]["shape"] == [4, 7]
    with pytest.raises(ValueError, match="static"):
        policy(rand["state"], rand["lidar"], rand["dynamic"])
