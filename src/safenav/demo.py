"""``make demo``: the main job, end to end, in a few minutes on a laptop CPU.

1. Evaluate the committed policy ``checkpoints/csac.pt`` (the default ``csac`` recipe,
   csac-shielded-memory-pillars with the planner filter, trained on SafeNav-v1, seed 1, its
   policy chosen on validation maps; results/csac/) on the fixed test scenario of the paper
   preset (env seed 1, 200 episodes), behind the shield it was trained with and the planner
   filter it records, and render one of its flights to ``demo/flight.gif``.
   Without a committed policy, the scripted potential-field controller stands in.
2. Start a short CSAC training run of its own (``demo/run``), when the trainer is installed.
"""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

from rich.console import Console

OUT = Path("demo")
CHECKPOINT = Path("checkpoints/csac.pt")


def main() -> None:
    console = Console()
    OUT.mkdir(exist_ok=True)
    have_policy = (
        CHECKPOINT.exists() and importlib.util.find_spec("safenav.algos.policy") is not None
    )
    policy_args = [str(CHECKPOINT)] if have_policy else ["--policy", "scripted"]
    name = str(CHECKPOINT) if have_policy else "the scripted potential-field controller"
    console.rule(f"[bold]1. Evaluate {name} on the fixed test scenario (paper preset)")
    run(["eval", *policy_args, "--json", str(OUT / "eval.json")])
    console.rule("[bold]2. Render one flight")
    run(["render", *policy_args, "--episode", "0", "--out", str(OUT / "flight.gif")])
    if importlib.util.find_spec("safenav.commands.train") is not None:
        console.rule("[bold]3. A short CSAC training run of its own (easy preset)")
        run(["train", "--algo", "csac", "--env", "SafeNav-v1", "--preset", "easy", "--seed", "0",
             "--total-steps", "20000", "--run-dir", str(OUT / "run"), "--overwrite"])  # fmt: skip
    console.print(f"[green]done:[/] {OUT}/eval.json, {OUT}/flight.gif")


def run(args: list[str]) -> None:
    cmd = [sys.executable, "-m", "safenav", *args]
    print("$ safenav " + " ".join(args), flush=True)
    subprocess.run(cmd, check=True)


if __name__ == "__main__":
    main()
