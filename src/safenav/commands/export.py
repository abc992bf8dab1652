"""``safenav export``: the deterministic actor as ONNX plus its JSON sidecar."""

from __future__ import annotations

from pathlib import Path

import tyro

from safenav.cli import app


@app.command(name="export")
def export(
    checkpoint: tyro.conf.Positional[Path | None] = None,
    onnx: Path = Path("policy.onnx"),
    opset: int = 17,
    scripted: bool = False,
    preset: str = "easy",
    policy_only: Path | None = None,
) -> None:
    """Export a checkpoint's deterministic actor to ONNX (``--onnx policy.onnx``) and write the
    sidecar ``policy.onnx.json`` (observation layout and scaling, action scaling, v_max, control
    rate, env config). ONNX Runtime is checked against torch within 1e-5 on random observations
    and on real ones from the checkpoint's env.

    ``--scripted`` exports the scripted go-to-goal actor instead (no checkpoint; env ``--preset``):
    the deployment chain without a trained policy.

    Args:
        checkpoint: Training checkpoint (read with ``safenav.algos.policy.load_policy``).
        onnx: Output ONNX file; the sidecar is written next to it as ``<onnx>.json``.
        opset: ONNX opset of the export: written exactly, or refused (9 or higher for a
            safenav policy).
        scripted: Export the scripted go-to-goal actor instead of a checkpoint.
        preset: With ``--scripted``: the env preset the sidecar describes.
        policy_only: Instead of ONNX, write a small checkpoint holding the policy alone (what
            ``checkpoints/*.pt`` are): ``safenav eval`` reads it, ``--resume`` cannot.
    """
    from safenav.common.checks import check_output_file
    from safenav.errors import SafenavError

    if checkpoint is not None and scripted:
        raise SafenavError("--scripted exports the scripted actor: give no CHECKPOINT with it")
    if policy_only is not None:
        from safenav.algos.policy import save_policy_only

        if checkpoint is None:
            raise SafenavError("--policy-only needs a CHECKPOINT")
        check_output_file(policy_only, "--policy-only", "policy.pt")
        if policy_only.exists() and policy_only.resolve() == Path(checkpoint).resolve():
            raise SafenavError(f"--policy-only {policy_only} is the CHECKPOINT it reads: name "
                               "another file")  # fmt: skip
        out = save_policy_only(checkpoint, policy_only)
        print(f"wrote {out} ({out.stat().st_size / 1e6:.2f} MB)")
        return
    import onnx as onnx_lib

    from safenav.common.checks import in_range
    from safenav.deploy.export import export_onnx, is_torch_file, load_actor
    from safenav.deploy.scripted import GoToGoalActor
    from safenav.envs.config import make_config

    in_range("--opset", opset, 1, onnx_lib.defs.onnx_opset_version(), "ONNX opsets; default 17")
    make_config(preset)  # ValueError for an unknown preset: exit 2
    # --onnx must never land on a checkpoint (or any non-ONNX file): refused before exporting.
    check_output_file(onnx, "--onnx", "policy.onnx")
    if onnx.suffix.lower() != ".onnx" or is_torch_file(onnx):
        raise SafenavError(f"--onnx {onnx}: name the ONNX file *.onnx, e.g. --onnx "
                           f"{onnx.with_suffix('.onnx')} (the sidecar goes next to it)")  # fmt: skip
    if scripted:
        cfg = make_config(preset)
        actor, source = GoToGoalActor(cfg), "scripted:GoToGoalActor"
    else:
        if checkpoint is None:
            raise SafenavError(
                "no CHECKPOINT given: pass one, or --scripted for the scripted go-to-goal actor"
            )
        actor, cfg = load_actor(checkpoint)
        source = str(checkpoint)
    meta = export_onnx(
        actor, cfg, onnx, opset=opset, checkpoint=source, check_observations=env_observations(cfg)
    )
    print(
        f"wrote {onnx} and {onnx}.json (ONNX Runtime vs torch: max |diff| {meta['check']['max_abs_diff']:.1e})"
    )


def env_observations(cfg, steps: int = 20, num_envs: int = 8) -> dict:
    """Real observations of the env ``cfg`` under random actions (for the export check)."""
    import numpy as np

    from safenav.envs.nav import SafeNavVectorEnv

    env = SafeNavVectorEnv(num_envs, config=cfg)
    obs, _ = env.reset(seed=1)
    rng = np.random.default_rng(0)
    batches = [obs]
    for _ in range(steps):
        obs, *_ = env.step(rng.uniform(-1, 1, (num_envs, 3)).astype(np.float32))
        batches.append(obs)
    env.close()
    return {k: np.concatenate([b[k] for b in batches]) for k in batches[0]}
