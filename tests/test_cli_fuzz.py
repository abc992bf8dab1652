"""CLI fuzz test (issue 23): every verb, every option, malformed values.

The options come from each verb's own ``--help`` (so a new option is fuzzed without touching this
file, and one without a verdict below fails :func:`test_every_option_has_a_verdict`). Every case
appends one option to a command line that is known to be accepted (``BASE``) and runs
``safenav.cli.main`` in-process, with the expensive work (training, evaluation, export, flights,
sweeps, benchmarks) replaced by a stub that exits with :data:`ACCEPTED`. Each case must end with

- exit code 2 for a usage error, 1 for a runtime error (or :data:`ACCEPTED` where the value is
  legitimately accepted: every such value is listed below, on purpose),
- at most two lines on stderr, ``safenav: error: ...``, naming the option, never a traceback and
  never the "this is a bug" line,
- no existing file changed or removed, and for a refused command no new file either.
"""

from __future__ import annotations

import hashlib
import os
import re
import shutil
import socket
from pathlib import Path

import pytest

import safenav.commands  # noqa: F401  (registers the verbs)
from conftest import run_cli
from safenav.cli import VERBS
from safenav.deploy.sim_vehicle import SimVehicle as REAL_SIM_VEHICLE

ROOT = Path(__file__).resolve().parents[1]
ACCEPTED = 99
HUGE_INT, HUGE_FLOAT = "1e18", "1e30"


class Reached(SystemExit):
    """The stubbed work was reached: the command line was accepted."""


def _reached(*args, **kwargs):
    raise Reached(ACCEPTED)


STUBS = [
    ("safenav.training", "train"),
    ("safenav.experiments.evaluate", "evaluate"),
    ("safenav.experiments.flight", "SafeNavVectorEnv"),  # render: after loading the policy
    ("safenav.experiments.reproduce", "run_sweep"),
    ("safenav.experiments.plots", "plot_all"),
    ("safenav.common.checkpoint", "save_checkpoint"),  # average's output
    ("safenav.experiments.soup", "greedy_soup"),
    ("safenav.deploy.export", "export_onnx"),
    ("safenav.algos.policy", "save_policy_only"),
    ("safenav.commands.fly", "fly_policy"),
    ("safenav.deploy.demo", "run_demo"),
    ("safenav.deploy.sim_vehicle", "SimVehicle"),
    ("safenav.bench.env", "bench_env"),
    ("safenav.bench.update", "bench_update"),
    ("safenav.bench.latency", "bench_latency"),
    ("safenav.bench.soak", "bench_soak"),
    ("safenav.bench.gym", "bench_suite"),
    ("safenav.experiments.tune", "tune"),
]


# ------------------------------------------------------------------------------ workspace


@pytest.fixture(scope="module")
def ws(tmp_path_factory) -> Path:
    """Inputs every case may read (and must leave as they are); outputs go to ``scratch/``."""
    ws = tmp_path_factory.mktemp("ws")
    shutil.copy(ROOT / "checkpoints" / "csac-paper.pt", ws / "ckpt.pt")
    (ws / "policy.onnx").write_bytes(b"not checked before the stubbed flight")
    (ws / "afile").write_text("a file, not a directory\n")
    (ws / "garbage.pt").write_bytes(b"not a checkpoint at all")
    (ws / "adir").mkdir()
    os.mkfifo(ws / "fifo")  # what a rename over it would replace, not write into
    (ws / "alink").symlink_to(ws / "afile")
    run = ws / "runs" / "csac" / "seed1"
    run.mkdir(parents=True)
    (run / "config.json").write_text('{"algo": "csac", "run": {"seed": 1}}\n')
    (run / "progress.csv").write_text("global_step,charts/success_rate\n100,0.5\n200,0.6\n")
    (ws / "scratch").mkdir()
    return ws


def unwritable_dir(ws: Path) -> Path | None:
    """A directory this process cannot write in: a read-only one, or (as root, whom file modes
    do not stop) /sys where the kernel refuses; None if there is none."""
    ro = ws / "readonly"
    ro.mkdir(exist_ok=True)
    ro.chmod(0o555)
    for d in (ro, Path("/sys")):
        try:
            (d / ".probe").touch()
            (d / ".probe").unlink()
        except OSError:
            return d
    return None


def snapshot(ws: Path) -> dict[str, str]:
    files = {}
    for p in sorted(ws.rglob("*")):
        if "scratch" in p.relative_to(ws).parts:
            continue
        if p.is_symlink():
            files[str(p.relative_to(ws))] = f"a link to {os.readlink(p)}"
        elif p.is_fifo():  # never opened: that would block
            files[str(p.relative_to(ws))] = "a FIFO"
        elif p.is_file():
            files[str(p.relative_to(ws))] = hashlib.sha256(p.read_bytes()).hexdigest()
    return files


@pytest.fixture
def stubbed(monkeypatch, ws):
    import importlib

    for module, name in STUBS:
        monkeypatch.setattr(importlib.import_module(module), name, _reached)
    monkeypatch.chdir(ws / "scratch")
    monkeypatch.setenv("COLUMNS", "80")
    return ws


run = run_cli


# --------------------------------------------------------------------------- the options


def base(verb: str, flag: str, ws: Path) -> list[str]:
    """A command line of ``verb`` that is accepted, into which ``flag`` is fuzzed."""
    s = ws / "scratch"
    if verb == "train":
        algo = ["--algo", "ppo"] if flag.startswith("--ppo.") else []
        # no --overwrite: the accepted cases leave a run dir that never trained, which is reused
        return ["train", *algo, "--preset", "easy", "--run-dir", str(s / "run"), "--no-progress"]
    if verb == "fly" and flag in ("--episode", "--gif", "--checkpoint", "--preset", "--scripted"):
        return ["fly", "--demo", "--checkpoint", str(ws / "ckpt.pt"), "--gif", str(s / "f.gif"),
                "--connect", "udpin://127.0.0.1:0"]  # fmt: skip
    return {
        "eval": ["eval", str(ws / "ckpt.pt"), "--preset", "easy"],
        "render": ["render", str(ws / "ckpt.pt"), "--out", str(s / "e.gif")],
        "reproduce": ["reproduce", "--out", str(s / "repro"), "--preset", "easy"],
        "plot": ["plot", str(ws / "runs"), "--out", str(s / "figs")],
        "average": ["average", str(ws / "ckpt.pt"), "--out", str(s / "avg.pt")],
        "export": ["export", str(ws / "ckpt.pt"), "--onnx", str(s / "p.onnx")],
        "convert": ["convert", str(ws / "ckpt.pt"), "--out", str(s / "c.pt")],
        "sim-vehicle": ["sim-vehicle", "--bind", "127.0.0.1:0", "--perception-port", "0"],
        # --connect port 0: no probe of the (maybe busy) default port 14540 of this machine
        "fly": [
            "fly",
            "--policy",
            str(ws / "policy.onnx"),
            "--goal",
            "1",
            "2",
            "1.5",
            "--connect",
            "udpin://127.0.0.1:0",
        ],  # fmt: skip
        "bench": ["bench", "env", "--preset", "easy"],
        "tune": ["tune", "--space", "sac", "--out", str(s / "tune"), "--preset", "easy"],
    }[verb]


def options(verb: str, capsys, monkeypatch) -> dict[str, str]:
    """``{flag: metavar}`` of ``safenav VERB --help`` ("" for a boolean flag)."""
    monkeypatch.setenv("COLUMNS", "80")  # one column of boxes, one option per row
    code, out, _ = run(capsys, [verb, "--help"])
    assert code == 0
    found: dict[str, str] = {}
    for line in out.splitlines():
        # a row of the options box (its border is "│", or " " when stdout is not a terminal)
        m = re.match(
            r"^[│ ] (--[a-z][\w.-]*)(, --no-[\w.-]+)?(?: ((?:\S+ ?)+?))?(?:  |\s*│?$)", line
        )
        if m and m.group(1) != "--help":
            found[m.group(1)] = "" if m.group(2) else (m.group(3) or "").strip()
    assert found, f"no options parsed from safenav {verb} --help:\n{out}"
    return found


def kind(metavar: str) -> tuple[str, int]:
    """``(int|float|str|path|choice|bool, values per use)`` of a metavar (0: a list)."""
    m = metavar.removeprefix("{None}|")
    if m.startswith("{[") and m.endswith("]}"):  # an optional list: {None}|{[STR [STR ...]]}
        m = m[1:-1]
    if not m:
        return "bool", 0
    if m.startswith("{") and "," in m and " " not in m:
        return "choice", 1
    if m.startswith("["):  # a list (n = 0): nargs "*", so no value at all is the empty list
        return m.strip("[").split()[0].lower(), 0
    words = m.strip("{}").split()
    return words[0].lower(), len(words)


# Per option: the code for -1, 0 and a huge value where it is not 2 (a usage error). Every
# accepted value is a decision: None = no case (the option takes no number).
ANY = {"-1": ACCEPTED, "0": ACCEPTED, "huge": ACCEPTED}
NONNEG = {"0": ACCEPTED, "huge": ACCEPTED}
POSITIVE = {"huge": ACCEPTED}
MEMORY = {"huge": 1}  # too much memory: refused with the estimate, a runtime error
VERDICTS: dict[str, dict[str, int]] = {
    # train
    "train --num-envs": MEMORY, "train --seed": {"0": ACCEPTED}, "train --total-steps": POSITIVE,
    "train --torch-threads": {"0": ACCEPTED}, "train --log-every": POSITIVE,
    "train --eval-every": NONNEG, "train --eval-episodes": MEMORY, "train --report-episodes": {},
    "train --checkpoint-every": POSITIVE, "train --map-refresh-every": NONNEG,
    "train --density.start": {"0": ACCEPTED}, "train --density.end": {"0": ACCEPTED},
    "train --density.ramp-fraction": POSITIVE, "train --density.success-threshold": {"0": ACCEPTED},
    "train --density.increment": {}, "train --density.epoch-steps": POSITIVE,
    "train --density.quantum": {},
    "train --csac.gamma": {}, "train --csac.tau": {}, "train --csac.batch-size": {},
    "train --csac.buffer-size": POSITIVE, "train --csac.learning-starts": {"0": ACCEPTED},
    "train --csac.updates-per-step": {},
    **{f"train --csac.{lr}": NONNEG for lr in ("actor-lr", "reward-critic-lr", "cost-critic-lr",
                                                "alpha-lr", "lambda-lr")},
    "train --csac.init-alpha": POSITIVE, "train --csac.target-entropy": ANY,
    "train --csac.action-noise-beta": {"0": ACCEPTED},  # in [0, 2]
    "train --csac.init-lambda": NONNEG, "train --csac.lambda-max": NONNEG,
    "train --csac.num-critics": MEMORY, "train --csac.num-cost-critics": {"0": ACCEPTED, "huge": 1},
    "train --csac.lambda-every": POSITIVE, "train --csac.episode-lambda-lr": POSITIVE,
    "train --csac.lambda-window": NONNEG, "train --csac.cost-scale-episodes": POSITIVE,
    "train --csac.lambda-warmup-steps": NONNEG,
    **{f"train --csac.pid-{g}": NONNEG for g in ("kp", "ki", "kd")},
    "train --csac.pid-ema": {"0": ACCEPTED}, "train --csac.pid-d-delay": {},  # <= 1e6
    "train --csac.cost-n-step": MEMORY, "train --csac.cost-horizon": NONNEG,
    "train --csac.cost-gamma": {},  # in (0, 1]
    "train --csac.planner-share": {"0": ACCEPTED},  # in [0, 1)
    "train --csac.planner-steps": POSITIVE, "train --csac.planner-envs": {},  # <= planner-steps
    **{f"train --{a}.net.{n}": MEMORY for a in ("csac", "ppo")
       for n in ("hidden", "lidar-kernel", "lidar-embed", "dynamic-hidden", "dynamic-embed",
                 "flatten-hidden")},
    **{f"train --{a}.net.{n}": {} for a in ("csac", "ppo")
       for n in ("lidar-strides", "lidar-channels")},  # one entry per convolution: 3, not 1
    **{f"train --{a}.curriculum.d-init": POSITIVE for a in ("csac", "ppo")},
    **{f"train --{a}.curriculum.d-min": {} for a in ("csac", "ppo")},
    **{f"train --{a}.curriculum.factor": {} for a in ("csac", "ppo")},
    **{f"train --{a}.curriculum.{n}": POSITIVE for a in ("csac", "ppo")
       for n in ("patience", "epoch-steps", "min-episodes")},
    "train --ppo.gamma": {}, "train --ppo.gae-lambda": {"0": ACCEPTED},
    "train --ppo.rollout-steps": MEMORY, "train --ppo.epochs": {},
    "train --ppo.num-minibatches": {}, "train --ppo.clip": POSITIVE,
    "train --ppo.value-clip": NONNEG, "train --ppo.lr": POSITIVE,
    "train --ppo.entropy-coef": NONNEG, "train --ppo.max-grad-norm": POSITIVE,
    "train --ppo.value-norm-beta": {}, "train --ppo.target-kl": POSITIVE,
    "train --ppo.lambda-lr": POSITIVE, "train --ppo.init-lambda": NONNEG,
    "train --ppo.lambda-max": NONNEG,
    "train --ppo.sde-sample-freq": ANY,  # <= 0: once per rollout; read only with --ppo.use-sde
    "train --ppo.log-std-init": {"-1": ACCEPTED, "0": ACCEPTED},  # in [-20, 20]
    # the other verbs
    "eval --env-seed": {"0": ACCEPTED}, "eval --episodes": MEMORY,
    "eval --shield-memory": {"0": ACCEPTED},  # 0-100, and above 1 only with --shield
    "render --shield-memory": {"0": ACCEPTED},
    **{f"{v} --shield-mover-margin": {"0": ACCEPTED} for v in ("train", "eval", "render", "fly")},  # 0-2 m
    "train --shield-memory": {"0": ACCEPTED},
    "train --shield-penalty": {"0": ACCEPTED},  # 0-10 per m/s, above 0 only with --shield
    "fly --shield-memory": {"0": ACCEPTED},
    "render --env-seed": {"0": ACCEPTED}, "render --episode": {"0": ACCEPTED}, "render --fps": {},
    "reproduce --seeds": {}, "reproduce --first-seed": {"0": ACCEPTED},
    "reproduce --cpus-per-trial": {"huge": 1}, "reproduce --gpus-per-trial": {"0": ACCEPTED, "huge": 1},
    "reproduce --num-cpus": {}, "reproduce --eval-episodes": MEMORY,
    "plot --smooth": POSITIVE,
    "average --steps": {}, "average --val-episodes": POSITIVE,  # no policy kept at 0 nor 1e18
    "export --opset": {},
    "sim-vehicle --world-seed": {"0": ACCEPTED}, "sim-vehicle --density": {"0": ACCEPTED},
    "sim-vehicle --episode": {"0": ACCEPTED}, "sim-vehicle --start": {"-1": ACCEPTED, "0": ACCEPTED},
    "sim-vehicle --perception-port": {"-1": ACCEPTED, "0": ACCEPTED}, "sim-vehicle --duration": POSITIVE,
    "fly --goal": {}, "fly --rate": {}, "fly --takeoff-altitude": {},
    "fly --origin": {"-1": ACCEPTED, "0": ACCEPTED}, "fly --link-timeout": {},
    "fly --max-flight-time": POSITIVE, "fly --episode": {"0": ACCEPTED},
    "bench --repeats": {}, "bench --num-envs": MEMORY, "bench --env-steps": POSITIVE,
    "bench --updates": POSITIVE, "bench --seeds": {}, "bench --first-seed": {},
    "bench --steps": NONNEG, "bench --jobs": {}, "bench --cost-limit": NONNEG,
    "bench --max-trials": {"0": ACCEPTED},  # fuzzed on bench env, where N > 0 is refused
    "tune --trials": {}, "tune --total-steps": POSITIVE, "tune --seed": {"0": ACCEPTED},
    "tune --episodes": {}, "tune --jobs": {}, "tune --torch-threads": {},
    "tune --space-seed": {"0": ACCEPTED},
}  # fmt: skip


def path_cases(ws: Path) -> dict[str, list[tuple[str, int]]]:
    """Per PATH option: (value, code). ``{W}`` is a directory this process cannot write in."""
    missing, afile, adir = str(ws / "missing"), str(ws / "afile"), str(ws / "adir")
    runs_dir, ckpt, garbage = (
        str(ws / "runs" / "csac" / "seed1"),
        str(ws / "ckpt.pt"),
        str(ws / "garbage.pt"),
    )

    def out_file(name: str) -> list[tuple[str, int]]:
        return [(adir, 2), (f"{missing}/sub/{name}", 2), (f"{afile}/{name}", 2),
                ("{W}/" + name, 1), (str(ws / "fifo"), 2), (str(ws / "alink"), 2)]  # fmt: skip

    def out_dir(name: str) -> list[tuple[str, int]]:
        return [(afile, 2), (f"{afile}/{name}", 2), ("{W}/" + name, 1)]

    return {
        "train --run-dir": [*out_dir("run"), (runs_dir, 2)],  # the last: holds a trained run
        "train --resume": [(missing, 2), (afile, 2), (adir, 2)],
        "eval CHECKPOINT": [(missing, 2), (adir, 2), (garbage, 2), (afile, 2)],
        "eval --json": out_file("eval.json"),
        "render CHECKPOINT": [(missing, 2), (adir, 2), (garbage, 2)],
        "render --out": [*out_file("e.gif"), (str(ws / "scratch" / "e.png"), 2)],
        "render --record": [*out_file("e.mcap"), (str(ws / "scratch" / "e.gif"), 2)],
        "reproduce --out": out_dir("repro"),
        "plot DIRS": [(missing, 2), (adir, 2), (afile, 2)],
        "plot --out": out_dir("figs"),
        "average POLICIES": [(missing, 2), (adir, 2), (garbage, 2)],
        "average --out": [*out_file("avg.pt"), (ckpt, 2)],  # the last: one of its inputs
        "export CHECKPOINT": [(missing, 2), (garbage, 2)],
        "export --onnx": [*out_file("p.onnx"), (ckpt, 2), (afile, 2)],  # never onto a checkpoint
        "export --policy-only": [*out_file("p.pt"), (ckpt, 2)],  # the checkpoint it reads
        "convert CHECKPOINT": [(missing, 2), (adir, 2), (garbage, 2), (afile, 2)],
        "convert --out": out_file("c.pt"),
        "fly --policy": [(missing, 2), (adir, 2), (ckpt, 2), (garbage, 2)],
        "fly --json": out_file("flight.json"),
        "fly --checkpoint": [(missing, 2), (adir, 2)],
        "fly --gif": [*out_file("f.gif"), (str(ws / "scratch" / "f.png"), 2)],
        "fly --record": [*out_file("flight.mcap"), (str(ws / "scratch" / "f.gif"), 2)],
        "bench --json": out_file("env.json"),
        "bench --out": out_dir("results"),
        "tune --out": out_dir("tune"),
    }


STR_CASES: dict[str, list[tuple[str, int]]] = {
    "train --env": [("NoSuchEnv-v0", 2), ("", 2), ("CartPole-v1", 2)],
    "train --preset": [("hard", 2)],
    "train --device": [("tpu", 2), ("cuda:99", 1)],
    "eval --preset": [("hard", 2)],
    "eval --device": [("tpu", 2), ("cuda:99", 1)],
    "render --preset": [("hard", 2)],
    "reproduce --algos": [("foo", 2)],
    "reproduce --seeds": [(v, 2) for v in ("0", "-1", "5-1", "1,1", "a-b", "1e18", "1001", "")],
    "reproduce --total-steps": [("lots", 2), ("0", 2), ("1.5", 2), ("foo=1M", 2)],
    "reproduce --preset": [("hard", 2)],
    "reproduce --device": [("tpu", 2), ("cuda:99", 1)],
    "reproduce --train-args": [("--nope 1", 2), ("--csac.gamma 2", 2), ("--num-envs -1", 2)],
    "reproduce --variants": [("bad", 2), ("x=foo", 2), ("x=csac --nope", 2)],
    "reproduce --address": [],  # free text: Ray's own address forms, checked by Ray
    "export --preset": [("hard", 2)],
    "sim-vehicle --preset": [("hard", 2)],
    "sim-vehicle --connect": [("nohost", 2), ("127.0.0.1:70000", 2)],
    "sim-vehicle --bind": [("127.0.0.1:70000", 2), ("x:y", 2)],
    "sim-vehicle --param": [("FOO=1", 2), ("COM_OF_LOSS_T=x", 2), ("COM_OF_LOSS_T=nan", 2)],
    "fly --connect": [("bogus", 2), ("udpin://127.0.0.1:70000", 2), ("ftp://x:1", 2)],
    "fly --perception": [("x", 2), ("127.0.0.1:70000", 2)],
    "fly --preset": [("hard", 2)],
    "bench --preset": [("hard", 2)],
    "bench --tasks": [("NoSuchEnv-v0", 2)],
    "bench --algos": [("foo", 2)],
    "bench --sb3": [("NoSuchEnv-v0", 2)],
    "bench --train-args": [("--nope 1", 2)],
    "tune --space": [("nope", 2), ("missing.toml", 2)],
    "tune --preset": [("hard", 2)],
    "tune --train-args": [("--nope 1", 2), ("--csac.gamma 2", 2), ("--num-envs -1", 2), ("'", 2)],
    "train --cost-fn": [("nomodule:cost", 2), ("math", 2), ("math:nosuch", 2), ("math:sqrt", 2)],
    "train --ppo.net.trunk": [("gelu", 2), ("", 2)],
    "train --csac.net.trunk": [("gelu", 2), ("relu", 2)],  # the SAC family's MLPs are ReLU
    "train --env-kwargs": [("nonesuch", 2)],  # a name without its value
}
SWITCH_CASES: dict[str, int] = {
    # the switch alone on the base command line, which trains SafeNav: refused, naming it
    "train --normalize-obs": 2, "train --normalize-reward": 2,
}  # fmt: skip


def generic_values(kind_: str, n: int) -> list[list[str]]:
    """Malformed whatever the option means: wrong type, NaN, infinity, too few values."""
    if kind_ == "int":
        bad = [["abc"], ["1.5"], ["nan"], ["1e-3"], [""]]
    elif kind_ == "float":
        bad = [["abc"], ["nan"], ["inf"], ["1e400"]]
    elif kind_ == "choice":
        bad = [["bogus"]]
    else:
        return [[]] if kind_ != "bool" and n else []  # only "missing value" below
    if n > 1:
        bad = [v * n for v in bad] + [["1"] * (n - 1)]  # and one value too few
    return [*bad, []] if n else bad  # [] = no value at all (for a list: the empty list)


def cases(verb: str, opts: dict[str, str], ws: Path) -> list[tuple[list[str], int, str]]:
    """(argv, expected code, word the error must name) for every option of ``verb``."""
    out = []
    paths = path_cases(ws)
    for flag, metavar in opts.items():
        key = f"{verb} {flag}"
        k, n = kind(metavar)
        name = flag.split(".")[-1].lstrip("-")
        for values in generic_values(k, n):
            out.append(([*base(verb, flag, ws), flag, *values], 2, name))
        if k == "bool":  # a switch given a value
            out.append(([*base(verb, flag, ws), f"{flag}=maybe"], 2, name))
        if key in SWITCH_CASES:
            out.append(([*base(verb, flag, ws), flag], SWITCH_CASES[key], name))
        if k in ("int", "float") and key in VERDICTS:
            for label, value in (("-1", "-1"), ("0", "0"),
                                 ("huge", HUGE_INT if k == "int" else HUGE_FLOAT)):  # fmt: skip
                code = VERDICTS[key].get(label, 2)
                out.append(([*base(verb, flag, ws), flag, *[value] * max(n, 1)], code, name))
        for value, code in paths.get(key, []):
            out.append(([*base(verb, flag, ws), flag, value], code, name))
        for value, code in STR_CASES.get(key, []):
            args = [f"{flag}={value}"] if value.startswith("-") else [flag, value]
            out.append(([*base(verb, flag, ws), *args], code, ""))
    # positionals: replace the base's first argument
    for key, values in paths.items():
        v, _, what = key.partition(" ")
        if v == verb and what.isupper():
            for value, code in values:
                out.append(([verb, value, *base(verb, "", ws)[2:]], code, ""))
    return out


def words(text: str) -> set[str]:
    """The words of ``text``, options without their dashes (``--csac.gamma``: csac, gamma)."""
    return {w.strip("-") for w in re.split(r"[^\w-]+", text)}


def check(capsys, ws: Path, argv: list[str], expected: int, name: str, writable: Path | None):
    """The failures of one case, as strings (empty: it held)."""
    if any("{W}" in a for a in argv):
        if writable is None:
            return []
        argv = [a.replace("{W}", str(writable)) for a in argv]
    before = snapshot(ws)
    code, out, err = run(capsys, argv)
    after = snapshot(ws)
    problems = []
    lines = err.strip().splitlines()
    if code != expected:
        problems.append(f"exit {code}, expected {expected}")
    if "Traceback" in err + out or "this is a bug" in err:
        problems.append("a traceback / a bug")
    if "__tyro" in err:
        problems.append("the error names tyro's internals, not the option")
    if len(lines) > 2:
        problems.append(f"{len(lines)} lines on stderr")
    if code in (1, 2):
        if not lines or not lines[0].startswith("safenav: error: "):
            problems.append("no 'safenav: error:' line")
        elif code == 2 and name and not {name, name.replace("-", "_")} & words(err):
            problems.append(f"the error does not name {name!r}")  # a usage error names the option
    changed = {k for k in before if after.get(k) != before[k]}
    if changed:
        problems.append(f"changed or removed {sorted(changed)}")
    if code in (1, 2) and set(after) - set(before):
        problems.append(f"created {sorted(set(after) - set(before))}")
    return [f"{' '.join(argv)}: {'; '.join(problems)} | {err.strip()[:300]}"] if problems else []


# ---------------------------------------------------------------------------------- tests


@pytest.mark.parametrize("verb", list(VERBS))
def test_base_command_line_is_accepted(verb, stubbed, capsys):
    code, out, err = run(capsys, base(verb, "", stubbed))
    assert code == ACCEPTED, err


@pytest.mark.long
@pytest.mark.parametrize("verb", list(VERBS))
def test_fuzz_every_option(verb, stubbed, capsys, monkeypatch):
    ws = stubbed
    writable = unwritable_dir(ws)
    opts = options(verb, capsys, monkeypatch)
    assert opts, f"no options parsed from safenav {verb} --help"
    failures = []
    for argv, expected, name in cases(verb, opts, ws):
        failures += check(capsys, ws, argv, expected, name, writable)
    assert not failures, f"{len(failures)} failing cases:\n" + "\n".join(failures)


def test_every_option_has_a_verdict(capsys, monkeypatch, ws):
    """Every numeric option of every verb has -1/0/huge verdicts, every PATH and STR option its
    cases: a new option cannot slip past the fuzz test."""
    missing = []
    paths = path_cases(ws)
    for verb in VERBS:
        for flag, metavar in options(verb, capsys, monkeypatch).items():
            k, _ = kind(metavar)
            key = f"{verb} {flag}"
            table = {"int": VERDICTS, "float": VERDICTS, "path": paths, "str": STR_CASES}.get(k)
            if table is not None and key not in table:
                missing.append(f"{key} ({metavar})")
    assert not missing, missing


def test_unknown_verbs_options_and_missing_values(stubbed, capsys):
    for argv in (["evl"], ["eval", "--nope", "1"], ["train", "--csac.nope", "1"], ["bench"],
                 ["bench", "nope"], ["reproduce", "--algos"], ["fly", "--goal", "1", "2"], []):  # fmt: skip
        code, out, err = run(capsys, argv)
        assert code == 2 and len(err.strip().splitlines()) == 1, (argv, err)
        assert err.startswith("safenav: error: ") and "Traceback" not in err + out
        assert "__tyro" not in err, err


def test_ports_in_use(stubbed, capsys, monkeypatch):
    """sim-vehicle binds a UDP (MAVLink) and a TCP (perception) port; fly listens on its
    --connect port. Each taken: one line, exit 1, named."""
    import safenav.deploy.sim_vehicle

    monkeypatch.setattr(safenav.deploy.sim_vehicle, "SimVehicle", REAL_SIM_VEHICLE)  # binds
    tcp, udp = socket.socket(), socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    with tcp, udp:
        tcp.bind(("127.0.0.1", 0))
        tcp.listen(1)
        udp.bind(("127.0.0.1", 0))
        taken_tcp, taken_udp = tcp.getsockname()[1], udp.getsockname()[1]
        for argv, flag in (
            (["sim-vehicle", "--preset", "easy", "--perception-port", str(taken_tcp)], "--perception-port"),
            (["sim-vehicle", "--preset", "easy", "--bind", f"127.0.0.1:{taken_udp}"], "--bind"),
            (["fly", "--policy", str(stubbed / "policy.onnx"), "--goal", "1", "2", "1.5",
              "--connect", f"udpin://127.0.0.1:{taken_udp}"], "--connect"),
        ):  # fmt: skip
            code, out, err = run(capsys, argv)
            assert code == 1, err
            assert err.count("\n") == 1 and flag in err and "in use" in err, err


def test_fuzz_covers_the_issue_kinds(ws):
    """The fuzz table holds every kind of malformed value the issue names."""
    text = repr(VERDICTS) + repr(path_cases(ws)) + repr(STR_CASES)
    for word in ("missing", "afile", "adir", "{W}", "70000"):
        assert word in text, word
    assert ["nan"] in generic_values("float", 1) and ["abc"] in generic_values("int", 1)
