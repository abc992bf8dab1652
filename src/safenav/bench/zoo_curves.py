"""The published SB3 zoo agents' own learning curves: references at the same step count.

rl-baselines3-zoo's ``benchmark.md`` (``safenav.bench.suites``) gives one trained agent's return
at the end of its training, e.g. 1M steps for SAC on Hopper, while ``safenav bench gym`` trains
SAC for 300k there. The same agents are published in DLR-RM/rl-trained-agents with the log of
the zoo's ``EvalCallback`` (``ALGO/ENV_1/evaluations.npz``: deterministic episodes every 10k or
25k env steps during that training). Its evaluation at our budget is the published return at the
same step count, which the issue's comparison asks for; the table and ``within_10pct`` use it
wherever the benchmark.md figure was measured at another budget.

``zoo_curves.json`` (beside this file) holds those curves, written by

    python -m safenav.bench.zoo_curves PATH   # a clone (or bare mirror) of rl-trained-agents

which reads ``evaluations.npz`` of each agent below through ``git show`` at the clone's HEAD and
records the commit. The curves are one agent (one seed) each: read a single point as such.
"""

from __future__ import annotations

import functools
import io
import json
import subprocess
import sys
from pathlib import Path
from typing import Any

from safenav.bench.suites import Reference
from safenav.common.jsonout import write_json
from safenav.errors import SafenavError

PATH = Path(__file__).with_name("zoo_curves.json")
REPOSITORY = "DLR-RM/rl-trained-agents"
AGENTS = {
    ("Pendulum-v1", "sac"): "sac/Pendulum-v1_1",
    ("Pendulum-v1", "ppo"): "ppo/Pendulum-v1_1",
    ("MountainCarContinuous-v0", "sac"): "sac/MountainCarContinuous-v0_1",
    ("MountainCarContinuous-v0", "ppo"): "ppo/MountainCarContinuous-v0_1",
    ("LunarLanderContinuous-v3", "sac"): "sac/LunarLanderContinuous-v2_1",
    ("LunarLanderContinuous-v3", "ppo"): "ppo/LunarLanderContinuous-v2_1",
    ("Hopper-v5", "sac"): "sac/Hopper-v3_1",
    ("Hopper-v5", "ppo"): "ppo/Hopper-v3_1",
    ("HalfCheetah-v5", "sac"): "sac/HalfCheetah-v3_1",
    ("HalfCheetah-v5", "ppo"): "ppo/HalfCheetah-v3_1",
}
"""Our task id and algorithm -> the zoo agent's folder (the zoo trained on the v2/v3 ids)."""
SOURCE = "SB3 zoo agent's evaluations.npz"


def _git(clone: Path, *args: str) -> bytes:
    """``git -C clone ARGS``'s output; a failure is one SafenavError line."""
    try:
        return subprocess.run(["git", "-C", str(clone), *args], check=True,
                              capture_output=True).stdout  # fmt: skip
    except (OSError, subprocess.CalledProcessError) as e:
        detail = getattr(e, "stderr", b"") or b""
        raise SafenavError(f"cannot read {args[-1]} in {clone}: "
                           f"{detail.decode().strip() or e}") from e  # fmt: skip


def extract(clone: Path) -> dict[str, Any]:
    """The curves of :data:`AGENTS` from a clone of rl-trained-agents, at its HEAD."""
    import numpy as np

    commit = _git(clone, "rev-parse", "HEAD").decode().strip()
    curves = {}
    for (env, algo), folder in AGENTS.items():
        data = np.load(io.BytesIO(_git(clone, "show", f"HEAD:{folder}/evaluations.npz")))
        steps = np.asarray(data["timesteps"]).reshape(-1)
        # (evaluations, episodes); some agents' logs keep a trailing axis of length 1
        results = np.asarray(data["results"], dtype=float).reshape(len(steps), -1)
        curves[f"{env}/{algo}"] = {
            "path": f"{folder}/evaluations.npz",
            "episodes": int(results.shape[1]),
            "steps": [int(s) for s in steps],
            "mean": [round(float(v), 3) for v in results.mean(axis=1)],
            "std": [round(float(v), 3) for v in results.std(axis=1)],
        }
    return {"repository": REPOSITORY, "commit": commit, "curves": curves}


@functools.cache
def load() -> dict[str, Any]:
    """The shipped ``zoo_curves.json``."""
    return json.loads(PATH.read_text())


def curve(env: str, algo: str) -> dict[str, Any] | None:
    """The zoo agent's evaluation curve for a task and algorithm, or None."""
    return load()["curves"].get(f"{env}/{algo}")


def at(env: str, algo: str, steps: int) -> Reference | None:
    """The zoo agent's evaluation at exactly ``steps`` env steps, or None (no such agent, or no
    evaluation at that step)."""
    c = curve(env, algo)
    if c is None or steps not in c["steps"]:
        return None
    i = c["steps"].index(steps)
    return Reference(c["mean"][i], c["std"][i], steps, f"{SOURCE}, {c['episodes']} episodes")


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 1:
        print(
            "usage: python -m safenav.bench.zoo_curves PATH_TO_RL_TRAINED_AGENTS", file=sys.stderr
        )
        return 2
    data = extract(Path(args[0]))
    write_json(PATH, data)
    load.cache_clear()
    print(f"{PATH}: {len(data['curves'])} curves of {REPOSITORY} at {data['commit'][:12]}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

__all__ = ["AGENTS", "at", "curve", "extract", "load"]
