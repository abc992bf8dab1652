"""Issue 23, "A newcomer's first hour": each reported case, as the user meets it.

The CLI fuzz test (test_cli_fuzz.py) covers every option with malformed values; these tests check
what each case of the issue now *says and does*: the figures in the messages, the files left as
they were, the JSON that parses, the exit codes.
"""

from __future__ import annotations

import io
import json
import math
import re
import shlex
import shutil
import socket
from collections import deque
from pathlib import Path

import pytest

from conftest import run_cli
from safenav.cli import VERBS, app, main
from safenav.common.checks import parse_count
from safenav.errors import SafenavError

ROOT = Path(__file__).resolve().parents[1]
CKPT = ROOT / "checkpoints" / "csac-paper.pt"
TINY = ["--num-envs", "2", "--log-every", "100", "--eval-every", "0", "--checkpoint-every", "100",
        "--no-progress", "--no-tensorboard", "--torch-threads", "1", "--csac.learning-starts", "50",
        "--csac.batch-size", "16", "--csac.buffer-size", "500", "--csac.net.hidden", "16", "16"]  # fmt: skip


class Reached(SystemExit):
    pass


def run(capsys, argv: list[str]) -> tuple[int, str, str]:
    code, out, err = run_cli(capsys, argv)
    assert "Traceback" not in out + err
    return code, out, err


def one_error(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("safenav: error: "), err
    return lines[0]


@pytest.fixture
def ckpt(tmp_path) -> Path:
    path = tmp_path / "policy.pt"
    shutil.copy(CKPT, path)
    return path


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory) -> Path:
    """A 200-step CSAC run on the easy preset (a few seconds)."""
    run_dir = tmp_path_factory.mktemp("tiny") / "run"
    main(["train", "--preset", "easy", "--total-steps", "200", "--run-dir", str(run_dir), *TINY])
    return run_dir


# ---------------------------------------------------------------------- tracebacks -> one line


def test_eval_negative_episodes_and_a_directory_as_json(capsys, ckpt, tmp_path):
    code, _, err = run(capsys, ["eval", str(ckpt), "--episodes", "-1"])
    assert code == 2 and "--episodes -1" in one_error(err)
    code, _, err = run(capsys, ["eval", str(ckpt), "--json", str(tmp_path)])
    assert code == 2 and f"--json {tmp_path / 'eval.json'}" in one_error(err)  # the fix


@pytest.mark.parametrize(
    ("seed", "role"),
    [(1, "the test scenario"), (4, "a held-out map"), (12346, "a validation map"), (77, "the map")],
)
def test_eval_names_the_role_of_the_map_it_flew(capsys, ckpt, seed, role):
    """The table's title said "fixed test scenario" for any env seed, validation maps included."""
    code, out, _ = run(capsys, ["eval", str(ckpt), "--preset", "easy", "--episodes", "1",
                                "--env-seed", str(seed)])  # fmt: skip
    assert code == 0 and f"{role}: env seed {seed}, 1 episodes" in " ".join(out.split())


def test_render_fps_zero_and_unwritable_out(capsys, ckpt, tmp_path, monkeypatch):
    flown = []
    monkeypatch.setattr("safenav.experiments.flight.render_episode",
                        lambda *a, **k: flown.append(1))  # fmt: skip
    code, _, err = run(capsys, ["render", str(ckpt), "--fps", "0"])
    assert code == 2 and "--fps 0" in one_error(err)
    code, _, err = run(capsys, ["render", str(ckpt), "--out", "/no/such/dir/flight.gif"])
    assert code == 2 and "/no/such/dir does not exist" in one_error(err)
    assert not Path("/no/such/dir").exists()
    # nothing lost: refused before the episode is flown, not when the GIF is written
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    target = ro if not _writable(ro) else Path("/sys")  # root ignores file modes
    if _writable(target):
        pytest.skip("no unwritable directory here")
    code, _, err = run(capsys, ["render", str(ckpt), "--out", str(target / "flight.gif")])
    assert code == 1 and "cannot write" in one_error(err)
    assert not flown


def _writable(d: Path) -> bool:
    try:
        (d / ".probe").touch()
        (d / ".probe").unlink()
        return True
    except OSError:
        return False


def test_an_output_over_a_device_fifo_or_link_is_refused(capsys, tmp_path, monkeypatch):
    """Outputs are written beside the target and renamed over it: over /dev/null (as root) that
    would replace the device, over a link the link. Refused before any work."""
    import os
    import stat

    def reached(*args, **kwargs):  # were it accepted: stop before anything is written
        raise Reached(99)

    monkeypatch.setattr("safenav.experiments.evaluate.evaluate", reached)
    fifo, link = tmp_path / "fifo", tmp_path / "link.json"
    os.mkfifo(fifo)
    link.symlink_to(tmp_path / "elsewhere.json")
    for target, says in (("/dev/null", "is not a regular file"), (fifo, "is not a regular file"),
                         (link, "is a symbolic link")):  # fmt: skip
        code, _, err = run(capsys, ["eval", "--policy", "scripted", "--json", str(target)])
        assert code == 2 and f"--json {target} {says}" in one_error(err)
    assert stat.S_ISCHR(os.stat("/dev/null").st_mode) and stat.S_ISFIFO(os.stat(fifo).st_mode)
    assert link.is_symlink() and sorted(p.name for p in tmp_path.iterdir()) == ["fifo", "link.json"]


def test_sim_vehicle_port_in_use_and_fly_port_out_of_range(capsys):
    with socket.socket() as tcp:
        tcp.bind(("127.0.0.1", 0))
        tcp.listen(1)
        port = tcp.getsockname()[1]
        code, _, err = run(
            capsys, ["sim-vehicle", "--preset", "easy", "--perception-port", str(port)]
        )
    assert code == 1 and f"127.0.0.1:{port} is already in use" in one_error(err)
    code, _, err = run(capsys, ["fly", "--perception-port", "70000"])  # fly has --perception
    assert code == 2 and "did you mean --perception?" in one_error(err)
    for argv in (["sim-vehicle", "--perception-port", "70000"],
                 ["fly", "--perception", "127.0.0.1:70000", "--goal", "1", "2", "1.5",
                  "--connect", "udpin://127.0.0.1:0"]):  # fmt: skip
        code, _, err = run(capsys, argv)
        assert code == 2 and "70000" in one_error(err) and "65535" in err


def test_a_fly_process_ends_without_teardown_and_keeps_its_status_and_output():
    """``safenav fly`` as its own process leaves through ``exit_now`` (no interpreter teardown,
    which took ~1 s with torch loaded): its error line and exit status still arrive."""
    import subprocess
    import sys

    from safenav.cli import exit_status

    assert [exit_status(c) for c in (None, 0, 3, 143)] == [0, 0, 3, 143]
    cmd = [sys.executable, "-c", "from safenav.cli import main; main()", "fly", "--rate", "5",
           "--policy", "p.onnx", "--goal", "1", "2", "1.5"]  # fmt: skip
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert done.returncode == 2, done.stderr
    assert done.stderr.count("safenav: error:") == 1 and "--rate" in done.stderr


def test_train_device_and_out_of_memory_refused_with_the_figure(capsys, tmp_path):
    run_dir = tmp_path / "run"
    code, _, err = run(capsys, ["train", "--device", "tpu", "--run-dir", str(run_dir)])
    assert code == 2 and "--device 'tpu'" in one_error(err)
    code, _, err = run(capsys, ["train", "--num-envs", "10000000", "--run-dir", str(run_dir)])
    line = one_error(err)
    assert code == 1 and "10,000,000 envs" in line and "lower --num-envs" in line
    need, have = re.findall(r"([\d.]+) ([KMGTP]B)", line.split("needs about")[1])[:2]
    scale = {"KB": 1e3, "MB": 1e6, "GB": 1e9, "TB": 1e12, "PB": 1e15}
    assert float(need[0]) * scale[need[1]] > float(have[0]) * scale[have[1]]
    assert not run_dir.exists()  # nothing written


# ------------------------------------------------------------------ wrong or misleading answers


def test_a_run_dir_that_never_trained_does_not_block_the_retry(
    capsys, tmp_path, monkeypatch, tiny_run
):
    import safenav.training as training

    def crash(*args, **kwargs):
        raise SafenavError("the env broke down before the first step")

    def accepted(*args, **kwargs):
        raise Reached(99)

    run_dir = tmp_path / "run"
    monkeypatch.setattr(training, "train", crash)
    code, _, err = run(capsys, ["train", "--preset", "easy", "--run-dir", str(run_dir), *TINY])
    assert code == 2 and (run_dir / "config.json").exists()  # what the failed attempt left
    monkeypatch.setattr(training, "train", accepted)
    code, _, err = run(capsys, ["train", "--preset", "easy", "--run-dir", str(run_dir), *TINY])
    assert code == 99, err  # the retry is accepted
    # a run dir that trained keeps refusing, unless --resume or --overwrite
    trained = tmp_path / "trained"
    shutil.copytree(tiny_run, trained)
    code, _, err = run(capsys, ["train", "--preset", "easy", "--run-dir", str(trained), *TINY])
    assert code == 2 and "already holds a run" in one_error(err) and "--resume" in err
    assert (trained / "checkpoint.pt").exists()
    assert run(capsys, ["train", "--resume", str(trained), "--no-progress"])[0] == 99
    assert run(capsys, ["train", "--preset", "easy", "--run-dir", str(trained), "--overwrite",
                        *TINY])[0] == 99  # fmt: skip


def test_a_refused_run_prints_its_error_alone(capsys, tmp_path, tiny_run):
    """Not the recipe it would have trained with first (stdout), then the refusal."""
    trained = tmp_path / "trained"
    shutil.copytree(tiny_run, trained)
    code, out, err = run(capsys, ["train", "--preset", "easy", "--run-dir", str(trained), *TINY])
    assert code == 2 and out == "" and "already holds a run" in one_error(err)


def test_fly_never_suggests_overwriting_a_checkpoint(capsys, ckpt):
    before = ckpt.read_bytes()
    code, _, err = run(capsys, ["fly", "--policy", str(ckpt), "--goal", "1", "2", "1.5"])
    line = one_error(err)
    assert code == 2 and f"--onnx {ckpt.with_suffix('.onnx')}" in line
    assert f"--onnx {ckpt} " not in line + " "
    missing = ckpt.with_name("nope.pt")
    code, _, err = run(capsys, ["fly", "--policy", str(missing), "--goal", "1", "2", "1.5"])
    assert code == 2 and f"--onnx {missing.with_suffix('.onnx')}" in one_error(err)
    # and export refuses to write ONNX over it, whatever the hint
    code, _, err = run(capsys, ["export", str(ckpt), "--onnx", str(ckpt)])
    assert code == 2 and ckpt.read_bytes() == before


def test_a_cuda_saved_checkpoint_loads_on_a_cpu_machine(capsys, tmp_path, monkeypatch, tiny_run):
    """``torch.save`` on a GPU tags every tensor ``cuda:0``; faked here by the tag alone."""
    import torch.serialization

    from safenav.algos.policy import load_policy
    from safenav.common.checkpoint import load_checkpoint, save_checkpoint

    run_dir = tmp_path / "cuda-run"
    shutil.copytree(tiny_run, run_dir)
    state = load_checkpoint(run_dir)
    monkeypatch.setattr(torch.serialization, "location_tag", lambda storage: "cuda:0")
    save_checkpoint(
        run_dir / "checkpoint.pt", {k: v for k, v in state.items() if "format" not in k}
    )
    monkeypatch.undo()
    if not torch.cuda.is_available():
        with pytest.raises(RuntimeError, match="CUDA"):  # what torch does without map_location
            torch.load(run_dir / "checkpoint.pt", weights_only=False)
    assert load_policy(run_dir).meta["algo"] == "csac"  # loaded, not "corrupt"
    config = json.loads((run_dir / "config.json").read_text())
    config["run"]["device"] = "cuda"  # the run was trained on a GPU
    (run_dir / "config.json").write_text(json.dumps(config))
    if not torch.cuda.is_available():
        code, _, err = run(capsys, ["train", "--resume", str(run_dir), "--no-progress"])
        assert code == 1 and "use --device cpu" in one_error(err) and "corrupt" not in err
    resumed = [
        "train",
        "--resume",
        str(run_dir),
        "--device",
        "cpu",
        "--total-steps",
        "300",
        "--no-progress",
    ]
    code, _, err = run(capsys, resumed)
    assert code == 0, err
    assert load_checkpoint(run_dir)["global_step"] == 300


def test_ppo_errors_do_not_speak_of_the_sac_family(capsys, tmp_path):
    code, _, err = run(capsys, ["train", "--algo", "ppo", "--env", "CartPole-v1", "--run-dir",
                                str(tmp_path / "run"), "--ppo.num-minibatches", "100000"])  # fmt: skip
    line = one_error(err)
    assert code == 2 and "SAC-family" not in line and "--ppo.num-minibatches 100000" in line
    assert "256 transitions" in line  # the classic-ppo recipe's CartPole-v1 rollout: 8 envs x 32
    assert not (tmp_path / "run").exists()


def test_export_writes_the_opset_asked_for_or_refuses(capsys, tmp_path):
    import onnx

    out = tmp_path / "policy.onnx"
    out.write_bytes(b"an earlier export")
    code, _, err = run(capsys, ["export", "--scripted", "--preset", "easy", "--onnx", str(out),
                                "--opset", "3"])  # fmt: skip
    assert code == 2 and "--opset 3" in one_error(err)
    assert out.read_bytes() == b"an earlier export"  # nothing silently replaced
    assert run(capsys, ["export", "--scripted", "--preset", "easy", "--onnx", str(out),
                        "--opset", "11"])[0] == 0  # fmt: skip
    opsets = {o.domain: o.version for o in onnx.load(str(out)).opset_import}
    assert opsets.get("", opsets.get("ai.onnx")) == 11
    assert json.loads(Path(f"{out}.json").read_text())["opset"] == 11


def _reproduce_help() -> str:
    """``safenav reproduce --help`` as it prints."""
    import contextlib
    import io

    buf = io.StringIO()
    with contextlib.redirect_stdout(buf), contextlib.suppress(SystemExit):
        main(["reproduce", "--help"])
    return buf.getvalue()


def _reproduce_examples() -> list[str]:
    """The ``safenav reproduce`` command lines of its --help, each a printed line (what a reader
    copies), and of docs/reproduce.md."""
    examples = [line.removeprefix("Example: ") for line in _reproduce_help().splitlines()
                if line.startswith("Example: ")]  # fmt: skip
    text = (ROOT / "docs" / "reproduce.md").read_text().replace("\\\n", " ")
    examples += [
        line.strip()
        for line in text.splitlines()
        if line.strip().startswith("safenav reproduce --")
    ]
    return examples


def test_reproduce_help_prints_each_example_on_one_line():
    """tyro starts a new line at a docstring line that does not start with a letter: an example
    wrapped there would print as two lines, and the first alone would run something else."""
    from safenav.commands.reproduce import reproduce

    lines = _reproduce_help().splitlines()
    starts = [i for i, line in enumerate(lines) if line.startswith("Example: ")]
    assert len(starts) == reproduce.__doc__.count("Example: ") >= 2
    for i in starts:  # each example is a paragraph of one line
        assert lines[i + 1].strip() == "", lines[i : i + 2]
        assert shlex.split(lines[i], comments=True)[1:3] == ["safenav", "reproduce"]


@pytest.mark.parametrize("example", _reproduce_examples())
def test_reproduce_examples_run_as_written(example, capsys, tmp_path, monkeypatch):
    seen = []
    monkeypatch.setattr("safenav.experiments.reproduce.run_sweep", seen.append)
    monkeypatch.chdir(tmp_path)
    # the docs' commands run in the repository root, where the tuned recipes they name lie
    (tmp_path / "results").mkdir()
    (tmp_path / "results" / "tuning").symlink_to(ROOT / "results" / "tuning")
    argv = shlex.split(example, comments=True)
    assert argv[:2] == ["safenav", "reproduce"]
    code, _, err = run(capsys, argv[1:])
    assert code == 0 and len(seen) == 1, err
    code, _, err = run(capsys, ["reproduce", "--out", "x", "--variants", "a=csac --no-curriculum"])
    assert code == 2 and "--variants a" in one_error(err)  # an option train lacks, before Ray


def test_reproduce_refuses_what_its_trials_would_refuse_before_ray(capsys, tmp_path, monkeypatch):
    """A budget within the warm-up, or a trial too big for memory, fails every trial once Ray has
    started them: refused before, in the words train uses, naming the trials."""
    seen = []
    monkeypatch.setattr("safenav.experiments.reproduce.run_sweep", seen.append)
    out = tmp_path / "repro"
    code, _, err = run(capsys, ["reproduce", "--out", str(out), "--algos", "csac", "ppo",
                                "--total-steps", "1000", "ppo=1M"])  # fmt: skip
    line = one_error(err)
    assert code == 2 and "the csac trials: --total-steps 1,000" in line
    assert "--csac.learning-starts" in line
    code, _, err = run(capsys, ["reproduce", "--out", str(out), "--algos", "sac",
                                "--train-args=--num-envs 1e7"])  # fmt: skip
    line = one_error(err)
    assert code == 1 and "the sac trials: training 10,000,000 envs" in line
    assert "lower --num-envs" in line
    assert not seen and not out.exists()
    # within the budget: accepted
    code, _, err = run(capsys, ["reproduce", "--out", str(out), "--algos", "csac", "--total-steps",
                                "2000", "--train-args=--csac.learning-starts 500"])  # fmt: skip
    assert code == 0 and len(seen) == 1, err


def test_fly_reports_a_mistake_in_the_command_line_before_a_busy_port(capsys, tmp_path):
    """A usage error (exit 2) is what to fix first; the port probe (exit 1) comes last."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as udp:
        udp.bind(("127.0.0.1", 0))
        port = udp.getsockname()[1]
        connect = ["--connect", f"udpin://127.0.0.1:{port}"]
        missing = tmp_path / "policy.onnx"
        code, _, err = run(capsys, ["fly", "--policy", str(missing), "--goal", "1", "2", "1.5",
                                    *connect])  # fmt: skip
        assert code == 2 and f"--policy {missing} not found" in one_error(err)
        code, _, err = run(capsys, ["fly", "--policy", str(missing), "--goal", "1", "2", "0",
                                    *connect])  # fmt: skip
        assert code == 2 and "--goal" in one_error(err)
        missing.write_bytes(b"stands in for an export")
        code, _, err = run(capsys, ["fly", "--policy", str(missing), "--goal", "1", "2", "1.5",
                                    *connect])  # fmt: skip
        assert code == 1 and f"port {port} is already in use" in one_error(err)


@pytest.mark.parametrize("argv", [["--overwrite=yes"], ["--no-progress", "yes"],
                                  ["--seed", "1", "--overwrite", "1"]])  # fmt: skip
def test_a_switch_given_a_value_is_named(argv, capsys, tmp_path):
    code, _, err = run(capsys, ["train", "--run-dir", str(tmp_path / "run"), *argv])
    switch = next(a for a in reversed(argv) if a.startswith("--")).split("=")[0]
    assert code == 2 and f"{switch} takes no value" in one_error(err)
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("form", ["1000000", "1e6", "1_000_000", "1M", "1m", "1000k"])
def test_step_counts_take_the_same_forms_everywhere(form, capsys, tmp_path, monkeypatch):
    from safenav.experiments.reproduce import parse_steps

    seen = {}

    def stub(algo, run_cfg, *args, **kwargs):
        seen["total_steps"] = run_cfg.total_steps
        raise Reached(99)

    monkeypatch.setattr("safenav.training.train", stub)
    code, _, err = run(capsys, ["train", "--preset", "easy", "--total-steps", form, "--run-dir",
                                str(tmp_path / "run"), "--no-progress"])  # fmt: skip
    assert code == 99 and seen["total_steps"] == 1_000_000, err
    assert parse_steps(form) == parse_count(form) == 1_000_000


def test_parse_count_refuses_what_is_not_a_whole_number():
    assert parse_count("2.5k") == 2500 and parse_count("-3") == -3 and parse_count("1B") == 10**9
    assert parse_count("123456789012345678901") == 123456789012345678901  # exact
    for bad in ("1.5", "1e-3", "nan", "inf", "1e400", "", "abc", "1x", "0x10"):
        with pytest.raises(ValueError):
            parse_count(bad)


def test_eval_json_writes_null_for_nan(capsys, tmp_path, monkeypatch):
    def evaluate(*args, **kwargs):
        rates = dict.fromkeys(("success_rate", "collision_rate", "timeout_rate",
                               "collision_static_rate", "collision_dynamic_rate",
                               "collision_bounds_rate", "collision_border_rate",
                               "border_time_fraction", "outside_time_fraction",
                               "mean_path_length", "min_clearance", "mean_speed"), 0.5)  # fmt: skip
        return {**rates, "mean_time_to_goal": math.nan, "detour_ratio": math.nan,
                "per_episode": {"time": [1.0, math.inf]}}  # fmt: skip

    monkeypatch.setattr("safenav.experiments.evaluate.evaluate", evaluate)
    out = tmp_path / "eval.json"
    code, _, err = run(
        capsys, ["eval", "--policy", "scripted", "--preset", "easy", "--json", str(out)]
    )
    assert code == 0, err

    def no_constants(name):
        raise AssertionError(f"{name} is not JSON")

    data = json.loads(out.read_text(), parse_constant=no_constants)
    assert data["mean_time_to_goal"] is None and data["per_episode"]["time"] == [1.0, None]


@pytest.mark.parametrize("collisions", [4, 0])
def test_fly_reports_collisions_and_exits_nonzero_when_the_flight_collided(
    collisions, capsys, tmp_path, monkeypatch
):
    summary = {"reached_goal": True, "collisions": collisions, "min_clearance_m": -0.3 if collisions else 0.4,
               "flight_time_s": 39.8}  # fmt: skip
    monkeypatch.setattr("safenav.deploy.demo.run_demo", lambda **kwargs: dict(summary))
    out = tmp_path / "flight.json"
    code, stdout, err = run(capsys, ["fly", "--demo", "--scripted", "--preset", "easy", "--json",
                                     str(out), "--gif", str(tmp_path / "f.gif")])  # fmt: skip
    data = json.loads(out.read_text())
    assert (
        data["collisions"] == collisions and data["min_clearance_m"] == summary["min_clearance_m"]
    )
    assert json.loads(stdout) == data
    last = err.strip().splitlines()[-1]
    assert f"{collisions} collision" in last and "min clearance" in last
    if collisions:
        assert code == 4 and data["outcome"] == "collided" and "collided" in last
    else:
        assert code == 0 and data["outcome"] == "reached_goal"


def test_an_aborted_flight_reports_its_collisions_too(capsys, tmp_path, monkeypatch):
    from safenav.deploy.fly import FlightAborted

    def run_demo(**kwargs):
        err = FlightAborted("goal not reached within 120 s")
        err.summary = {"reached_goal": False, "collisions": 7, "min_clearance_m": -0.3}
        raise err

    monkeypatch.setattr("safenav.deploy.demo.run_demo", run_demo)
    out = tmp_path / "flight.json"
    code, _, err = run(capsys, ["fly", "--demo", "--scripted", "--json", str(out), "--gif",
                                str(tmp_path / "f.gif")])  # fmt: skip
    assert code == 3 and "7 collisions, min clearance -0.3 m" in err.strip().splitlines()[-1]
    assert json.loads(out.read_text())["outcome"] == "aborted"


def test_the_flight_log_summary_carries_the_simulator_truth():
    from safenav.deploy.fly import FlightLog

    log = FlightLog(reached_goal=True)
    assert log.summary()["collisions"] is None  # real sensors: unknown, not 0
    log.truth = {"collisions": 4, "min_clearance": -0.31234}
    assert log.summary()["collisions"] == 4 and log.summary()["min_clearance_m"] == -0.312


# ---------------------------------------------------------------------------------------- output


def test_version_and_a_one_screen_help(capsys):
    from safenav import __version__

    code, out, _ = run(capsys, ["--version"])
    assert code == 0 and out.strip() == f"safenav {__version__}"
    code, out, _ = run(capsys, ["--help"])
    assert code == 0 and len(out.splitlines()) <= 40 and max(map(len, out.splitlines())) <= 200
    for verb in VERBS:
        assert re.search(rf"^  {verb} ", out, re.M), verb
    assert set(VERBS) == set(app._subcommands)  # every registered verb is listed
    code, out, _ = run(capsys, ["eval", "--help"])  # the detail is in the verb's own help
    assert code == 0 and "--episodes" in out and "--json" in out


@pytest.mark.parametrize("argv, says", [
    (["convert"], "missing CHECKPOINT:"),
    (["bench"], "missing WHICH (one of env, update, latency, soak"),
    (["bench", "nope"], "WHICH 'nope': choose one of env"),
    (["average", "--out", "x.pt"], "no POLICIES given"),
    (["plot"], "no directories given"),
    (["eval"], "no checkpoint given"),
])  # fmt: skip
def test_a_missing_argument_is_named_as_the_help_names_it(argv, says, capsys, tmp_path,
                                                          monkeypatch):  # fmt: skip
    monkeypatch.chdir(tmp_path)
    code, _, err = run(capsys, argv)
    line = one_error(err)
    assert code == 2 and says in line and "tyro" not in line
    assert not list(tmp_path.iterdir())


def test_help_as_a_verb(capsys):
    """``safenav help`` and ``safenav help VERB``, as git and pip take them."""
    assert run(capsys, ["help"])[1] == run(capsys, ["--help"])[1]
    code, out, _ = run(capsys, ["help", "eval"])
    assert code == 0 and out == run(capsys, ["eval", "--help"])[1] and "--episodes" in out
    code, _, err = run(capsys, ["help", "evl"])
    assert code == 2 and "did you mean 'eval'?" in one_error(err)


def test_help_keeps_sentences_whole(capsys, monkeypatch):
    """A docstring line that starts with a number, ``code`` or a --flag continues its sentence
    in --help (tyro alone starts a new line there); blank lines and list items still break."""
    from safenav.cli import unwrap_help

    text = "Steps: 1000000, 1e6,\n    1_000_000 or 1M; see\n    ``--x``.\n\n    - one\n    - two"
    assert unwrap_help(text) == "Steps: 1000000, 1e6, 1_000_000 or 1M; see ``--x``.\n\n- one\n- two"
    from tyro import _docstrings

    from safenav.common.config import RunConfig

    # an option's help (an attribute docstring, its lines indented) and a verb's description
    doc = _docstrings.get_field_docstring(RunConfig, "cost_fn", ())
    assert doc is not None and 'reports no ``info["cost"]``' in doc and "\n" not in doc
    monkeypatch.setenv("COLUMNS", "80")
    code, out, _ = run(capsys, ["bench", "--help"])
    assert code == 0 and "soak: ``--env-steps`` env steps and ``--updates`` CSAC updates" in out


def test_progress_line_fits_80_and_100_columns(monkeypatch):
    from rich.console import Console

    from safenav.common.progress import ProgressDisplay

    display = ProgressDisplay(5_000_000, 0, enabled=True, title="csac SafeNav-v1",
                              console=Console(file=io.StringIO()))  # fmt: skip
    assert display.live is None  # not a terminal
    display.metrics(1_234_567, {"constraint/lambda": 1.2345, "charts/alpha": 0.05},
                    {"success": deque([1.0, 1.0, 0.0, 1.0]), "collision": deque([0.0, 0.2]),
                     "return": deque([3.0])}, 0.5)  # fmt: skip
    display._samples = deque([(display.t0, 0), (display.t0 + 100, 1_000_000)])  # 10k steps/s
    for width in (80, 100):
        line = display.line(width)
        assert len(line) <= width and "\n" not in line
        for part in ("1.23M/5M", "ETA 0:06:16", "10k steps/s", "succ 0.75", "coll 0.10",
                     "λ 1.23", "d 0.5"):  # fmt: skip
            assert part in line, (width, part, line)
    # as a terminal of COLUMNS=80 draws it: one line
    monkeypatch.setenv("COLUMNS", "80")
    buf = io.StringIO()
    console = Console(file=buf, force_terminal=True)
    assert console.width == 80
    console.print(display)
    drawn = re.sub(r"\x1b\[[0-9;?]*[A-Za-z]", "", buf.getvalue())
    assert drawn.count("\n") == 1 and len(drawn.rstrip("\n")) <= 80 and "steps/s" in drawn
    display.close()


def test_the_exit_codes_are_documented_and_the_readme_links_them():
    assert "docs/reliability.md#exit-codes" in (ROOT / "README.md").read_text()
    text = (ROOT / "docs" / "reliability.md").read_text()
    section = text.split("\n## Exit codes")[1].split("\n## ")[0]
    for code, word in (("0", "success"), ("1", "runtime"), ("2", "usage"), ("3", "aborted"),
                       ("4", "collided"), ("130", "Ctrl-C"), ("143", "SIGTERM")):  # fmt: skip
        assert re.search(rf"^\| {code} \|.*{word}", section, re.M | re.I), code


def test_render_reads_a_safenav_checkpoint_once(capsys, tiny_run, tmp_path, monkeypatch):
    """A training checkpoint holds the replay buffer: ``render`` read it three times (the
    Gymnasium check, the shield settings, the flight)."""
    import safenav.algos.policy as policy_module
    import safenav.common.checkpoint as checkpoint_module

    reads = []

    def counting(path, *a, real=checkpoint_module.load_checkpoint, **k):
        reads.append(path)
        return real(path, *a, **k)

    monkeypatch.setattr(checkpoint_module, "load_checkpoint", counting)
    monkeypatch.setattr(policy_module, "load_checkpoint", counting)
    gif = tmp_path / "flight.gif"
    code, out, err = run(capsys, ["render", str(tiny_run), "--preset", "easy", "--out", str(gif)])
    assert code == 0 and gif.stat().st_size > 0 and "wrote" in out, err
    assert len(reads) == 1, reads
