"""Shared networks: ensemble layers, the circular CNN, extractors, actor and critics."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch
import torch.nn.functional as F

from safenav.envs.vector import obs_layout
from safenav.errors import SafenavError
from safenav.nn.config import NetConfig
from safenav.nn.extractors import FlattenExtractor, NavExtractor
from safenav.nn.layers import CircularConv1d, EnsembleLinear, EnsembleMLP
from safenav.nn.networks import Actor, DeterministicActor, QEnsemble, make_extractor

NAV = {"state": (8,), "lidar": (4, 36), "dynamic": (5, 10)}


def nav_obs(n=6, seed=0):
    g = torch.Generator().manual_seed(seed)
    return {k: torch.rand(n, *s, generator=g) for k, s in NAV.items()}


@pytest.mark.parametrize(("length", "cin", "cout", "stride", "members"),
                         [(36, 4, 8, 2, 1), (18, 8, 16, 2, 3), (9, 16, 16, 1, 2)])  # fmt: skip
def test_circular_conv_equals_conv1d_on_circularly_padded_input(length, cin, cout, stride, members):
    conv = CircularConv1d(length, cin, cout, kernel=5, stride=stride, ensemble_size=members)
    x = torch.randn(7, cin, length)
    y = conv(x.transpose(1, 2).reshape(7, -1))  # channels-last, flattened
    padded = torch.cat([x[..., -2:], x, x[..., :2]], -1)
    for e in range(members):
        w = conv.weight[e].view(5, cin, cout).permute(2, 1, 0)  # (C_out, C_in, K)
        ref = F.conv1d(padded, w, conv.bias[e, 0], stride=stride)
        torch.testing.assert_close(y[e], ref.transpose(1, 2).reshape(7, -1), atol=1e-5, rtol=1e-4)


def test_circular_conv_is_equivariant_to_azimuth_rotation():
    conv = CircularConv1d(36, 4, 8, kernel=5, stride=1)
    x = torch.randn(3, 4, 36)
    flat = lambda t: t.transpose(1, 2).reshape(3, -1)  # noqa: E731
    y = conv(flat(x))[0].view(3, 36, 8)
    y_rot = conv(flat(torch.roll(x, 5, dims=-1)))[0].view(3, 36, 8)
    torch.testing.assert_close(y_rot, torch.roll(y, 5, dims=1), atol=1e-5, rtol=1e-4)


def test_ensemble_members_are_independent_linears():
    layer = EnsembleLinear(5, 4, ensemble_size=3)
    x = torch.randn(10, 5)
    y = layer(x)  # shared input
    for e in range(3):
        torch.testing.assert_close(y[e], x @ layer.weight[e] + layer.bias[e, 0])
    xs = torch.randn(3, 10, 5)
    ys = layer(xs)
    for e in range(3):
        torch.testing.assert_close(ys[e], xs[e] @ layer.weight[e] + layer.bias[e, 0])
    torch.testing.assert_close(layer(x[None]), y)  # (1, N, in) is shared too
    mlp = EnsembleMLP(5, (8,), 2, ensemble_size=2)
    out = mlp(x)
    out[0].sum().backward()  # member 0's output depends on member 0's weights only
    assert mlp.layers[0].weight.grad[1].abs().sum() == 0
    assert mlp.layers[0].weight.grad[0].abs().sum() > 0


def test_nav_extractor_shapes_and_flatten_extractor():
    ex = make_extractor(NAV, NetConfig(), ensemble_size=2)
    assert isinstance(ex, NavExtractor)
    f = ex(nav_obs())
    assert f.shape == (2, 6, 200) and ex.out_features == 200
    torch.testing.assert_close(f[0, :, -8:], nav_obs()["state"])  # the state passes through
    flat = make_extractor({"obs": (3,)}, NetConfig())
    assert isinstance(flat, FlattenExtractor) and flat.out_features == 3
    assert (
        make_extractor({"a": (2,), "b": (2, 2)}, NetConfig(flatten_hidden=(16,))).out_features == 16
    )
    with pytest.raises(ValueError):
        NavExtractor((4, 30), (5, 10), 8)  # 30 columns do not divide by the strides 2*2*1


def test_obs_layout():
    assert obs_layout(gym.spaces.Box(-1, 1, (3,))) == {"obs": (3,)}
    space = gym.spaces.Dict({k: gym.spaces.Box(-1, 1, s) for k, s in NAV.items()})
    assert obs_layout(space) == NAV
    with pytest.raises(SafenavError):
        obs_layout(gym.spaces.Discrete(3))


def test_actor_sample_critic_ensemble_and_traceable_deterministic_actor():
    torch.manual_seed(0)
    actor = Actor(make_extractor(NAV, NetConfig()), 200, 3, (64, 64))
    a, logp, mean_a = actor.sample(nav_obs())
    assert a.shape == (6, 3) and logp.shape == (6,) and a.abs().max() <= 1
    q = QEnsemble(None, 200, 3, (64, 64), ensemble_size=4)
    feats = make_extractor(NAV, NetConfig())(nav_obs())
    assert q(feats, a).shape == (4, 6) and q(feats[0], a).shape == (4, 6)
    det = DeterministicActor(None, actor, ("state", "lidar", "dynamic"))
    o = nav_obs(3)
    out = det(o["state"], o["lidar"], o["dynamic"])
    torch.testing.assert_close(out, actor.sample(o)[2])
    traced = torch.jit.trace(det, (o["state"], o["lidar"], o["dynamic"]))
    o2 = nav_obs(5, seed=1)
    torch.testing.assert_close(traced(o2["state"], o2["lidar"], o2["dynamic"]),
                               det(o2["state"], o2["lidar"], o2["dynamic"]))  # fmt: skip
    assert np.isfinite(out.detach().numpy()).all()
