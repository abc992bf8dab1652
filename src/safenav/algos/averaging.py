"""Weight averaging of a run's late policies: ``safenav average``.

Stochastic weight averaging (Izmailov et al., 2018, "Averaging Weights Leads to Wider Optima and
Better Generalization"; for deep RL, Nikishin et al., 2018, "Improving Stability in Deep
Reinforcement Learning with Weight Averaging"): the uniform mean of every floating-point
parameter of several snapshots of one network, taken along one training run. Here the snapshots
are the policies ``safenav train --keep-policies`` keeps at each periodic evaluation
(``policies/step_<N>.pt``), and the network is the deployable actor of each (the shared
extractor with it: the whole module a policy file holds), so the average is again a policy file
that ``safenav eval``, ``export`` and ``fly`` read.

Why: with the constraint active, λ grows and the policy swings between consecutive snapshots by
up to 0.1 in success (docs/csac.md); choosing one snapshot by evaluation picks a noisy maximum.
Over the eight 60-minute CSAC runs, the average of the 3.0-5.0 M-step policies tests above the
snapshot chosen on 512 validation episodes in six (docs/csac.md, "Weight averaging of the late
policies"); when a run's last policies turn cautious, the greedy soup of
:mod:`safenav.experiments.soup` (``safenav average --greedy``) leaves them out. This is beyond
the paper, which deploys the last policy.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import torch

from safenav.common.checkpoint import POLICY_KEYS, load_checkpoint
from safenav.errors import SafenavError


def policy_files(paths: Sequence[str | Path]) -> list[Path]:
    """The ``*.pt`` files of ``paths`` (files as given; directories: their ``*.pt``, sorted)."""
    files: list[Path] = []
    for p in map(Path, paths):
        if p.is_dir():
            files.extend(sorted(p.glob("*.pt")))
        elif p.exists():
            files.append(p)
        else:
            raise SafenavError(f"{p}: no such file or directory")
    if not files:
        raise SafenavError(f"no policy files (*.pt) in {[str(p) for p in paths]}")
    return files


def _description(meta: dict[str, Any]) -> dict[str, Any]:
    """What must agree for two policies to be averaged: everything but the training step."""
    return {k: v for k, v in meta.items() if k not in ("global_step", "averaged_steps")}


def _seed(state: dict[str, Any]) -> Any:
    run = state.get("config", {}).get("run", {})
    return run.get("seed") if isinstance(run, dict) else None


def check_snapshots(states: Sequence[dict[str, Any]]) -> None:
    """``SafenavError`` unless ``states`` (checkpoint dicts) are policies of one network and one
    run, so that their weights may be averaged: when a state holds no policy, when two share a
    step or their runs' seeds differ (snapshots of different runs: their weights lie in unrelated
    basins), or when the policies differ in algorithm, observation layout, network or parameter
    shapes."""
    if not states:
        raise SafenavError("no policies to average")
    for i, st in enumerate(states):
        pol = st.get("policy")
        if not isinstance(pol, dict) or "meta" not in pol or "state_dict" not in pol:
            raise SafenavError(f"policy {i}: the checkpoint holds no policy")
    last = states[-1]
    steps = [int(st["global_step"]) for st in states]
    repeated = sorted({s for s in steps if steps.count(s) > 1})
    if repeated:
        raise SafenavError(f"two policies of step {repeated[0]:,}: snapshots of different runs do "
                           "not average (one run's policies/ directory does)")  # fmt: skip
    seeds = sorted({str(_seed(st)) for st in states})
    if len(seeds) > 1:
        raise SafenavError(f"policies of runs with different seeds ({', '.join(seeds)}): only "
                           "snapshots of one run average")  # fmt: skip
    mine = _description(last["policy"]["meta"])
    ref_sd = last["policy"]["state_dict"]
    for st, step in zip(states, steps, strict=True):
        if st.get("algo") != last.get("algo"):
            raise SafenavError(f"cannot average a {st.get('algo')} policy (step {step}) with "
                               f"{last.get('algo')} ones")  # fmt: skip
        other = _description(st["policy"]["meta"])
        if other != mine:
            diff = sorted(k for k in set(other) | set(mine) if other.get(k) != mine.get(k))
            raise SafenavError(f"the policy of step {step} differs from the others in {diff}: "
                               "only snapshots of one network average")  # fmt: skip
        sd = st["policy"]["state_dict"]
        if set(sd) != set(ref_sd):
            raise SafenavError(f"the policy of step {step} has other parameters than the others")
        for key, value in sd.items():
            if value.shape != ref_sd[key].shape:
                raise SafenavError(f"the policy of step {step}: {key} has shape {tuple(value.shape)}, "
                                   f"the others {tuple(ref_sd[key].shape)}")  # fmt: skip


def average_policy_states(states: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """The policy-only checkpoint state whose actor parameters are the uniform mean of those of
    ``states`` (checkpoint dicts, as :func:`~safenav.common.checkpoint.load_checkpoint` returns;
    ordered by step). Counters, configs and metadata are the last state's; ``averaged_steps``
    lists the steps averaged. Non-float tensors (none in today's actors) must be equal.
    ``SafenavError`` from :func:`check_snapshots` for policies that do not average."""
    check_snapshots(states)
    last = states[-1]
    ref_sd = last["policy"]["state_dict"]
    steps = [int(st["global_step"]) for st in states]
    averaged: dict[str, torch.Tensor] = {}
    for key, ref in ref_sd.items():
        values = [st["policy"]["state_dict"][key] for st in states]
        if ref.is_floating_point():
            # accumulate in float64: the mean of n float32 snapshots, rounded once
            averaged[key] = torch.stack([v.double() for v in values]).mean(0).to(ref.dtype)
        else:
            if any(not torch.equal(v, ref) for v in values):
                raise SafenavError(f"{key}: a non-float tensor differs between the policies")
            averaged[key] = ref.clone()
    meta = dict(last["policy"]["meta"]) | {"averaged_steps": steps}
    out = {k: last[k] for k in POLICY_KEYS if k in last and k != "policy"}
    return out | {"policy": {"meta": meta, "state_dict": averaged}, "policy_only": True,
                  "averaged_steps": steps}  # fmt: skip


def load_policy_states(
    paths: Sequence[str | Path], steps: tuple[int, int] | None = None
) -> list[dict[str, Any]]:
    """The checkpoint dicts of the policy files of ``paths`` (files or directories of them, such
    as a run's ``policies/``), ordered by step; only those with ``lo <= global_step <= hi`` when
    ``steps = (lo, hi)``."""
    files = policy_files(paths)
    states = sorted(
        (load_checkpoint(f) for f in files), key=lambda s: int(s.get("global_step", -1))
    )
    if steps is not None:
        lo, hi = steps
        if lo > hi:
            raise SafenavError(f"--steps {lo} {hi}: the first step must not exceed the second")
        states = between_steps(states, lo, hi)
        if not states:
            raise SafenavError(f"--steps {lo} {hi}: no policy with {lo} <= step <= {hi} in "
                               f"{[str(p) for p in paths]}")  # fmt: skip
    return states


def between_steps(states: Iterable[dict[str, Any]], lo: int, hi: int) -> list[dict[str, Any]]:
    """The states with ``lo <= global_step <= hi``, ordered by step."""
    chosen = (s for s in states if lo <= int(s.get("global_step", -1)) <= hi)
    return sorted(chosen, key=lambda s: int(s["global_step"]))


def average_policies(
    paths: Sequence[str | Path], steps: tuple[int, int] | None = None
) -> dict[str, Any]:
    """The average (:func:`average_policy_states`) of :func:`load_policy_states`."""
    return average_policy_states(load_policy_states(paths, steps))


__all__ = ["average_policies", "average_policy_states", "between_steps", "check_snapshots",
           "load_policy_states", "policy_files"]  # fmt: skip
