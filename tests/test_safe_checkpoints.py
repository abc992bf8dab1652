"""Safe checkpoints (issue 24, item 3): every checkpoint loads with ``torch.load(weights_only=True)``
and torch's default allow-list; a crafted pickle fed to ``eval``, ``export``, ``fly``, ``average``,
``render``, ``train --resume`` and ``convert`` is refused in one line and its payload never runs;
an older safenav's checkpoint (NumPy RNG state) is refused with the conversion command, which
rewrites it without running code; every JSON file and checkpoint goes through one atomic, fsynced
writer."""

from __future__ import annotations

import json
import os
import pickle
import random
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from safenav.cli import main
from safenav.common import atomic
from safenav.common.checkpoint import (
    FORMAT,
    FORMAT_VERSION,
    convert_checkpoint,
    load_checkpoint,
    rng_state,
    safe_state,
    save_checkpoint,
    set_rng_state,
)
from safenav.common.jsonout import write_json
from safenav.errors import SafenavError

pytestmark = pytest.mark.usefixtures("one_thread")

ROOT = Path(__file__).resolve().parents[1]
TINY = ["--algo", "csac", "--preset", "easy", "--seed", "3", "--num-envs", "4", "--log-every",
        "100", "--eval-every", "200", "--eval-episodes", "2", "--checkpoint-every", "200",
        "--no-progress", "--no-tensorboard", "--torch-threads", "1", "--csac.learning-starts",
        "100", "--csac.batch-size", "32", "--csac.buffer-size", "2000", "--csac.updates-per-step",
        "0.25", "--csac.net.hidden", "32", "32"]  # fmt: skip


class Payload:
    """Unpickling this runs ``os.system("touch MARKER")``: what a crafted checkpoint does."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch '{self.marker}'",))


def armed_state(marker: Path) -> dict:
    """A checkpoint dict that looks like safenav's and carries the payload."""
    policy = torch.load(ROOT / "checkpoints" / "csac-paper.pt", weights_only=True)
    return {**policy, "format": FORMAT, "format_version": FORMAT_VERSION, "x": Payload(marker)}


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory) -> Path:
    """A 300-step CSAC run with its replay buffer and n-step window in checkpoint.pt."""
    run_dir = tmp_path_factory.mktemp("safe") / "run"
    main(["train", *TINY, "--total-steps", "300", "--keep-policies", "--save-buffer",
          "--csac.cost-n-step", "3", "--run-dir", str(run_dir)])  # fmt: skip
    return run_dir


@pytest.fixture
def crafted(tmp_path) -> dict[str, Path]:
    """The payload as a torch.save zip, a legacy (pre-zip) torch.save and a bare pickle."""
    marker = tmp_path / "PAYLOAD_RAN"
    d = tmp_path / "crafted"
    d.mkdir()
    files = {"zip": d / "evil.pt", "legacy": d / "evil_legacy.pt", "bare": d / "evil_bare.pt"}
    torch.save(armed_state(marker), files["zip"])
    torch.save(armed_state(marker), files["legacy"], _use_new_zipfile_serialization=False)
    files["bare"].write_bytes(pickle.dumps(armed_state(marker)))
    return {**files, "marker": marker, "out": tmp_path / "out"}


def run(capsys, argv: list[str]) -> tuple[int, str, str]:
    capsys.readouterr()
    try:
        main([str(a) for a in argv])
        code = 0
    except SystemExit as err:
        code = err.code if isinstance(err.code, int) else 1
    out, err = capsys.readouterr()
    return code, out, err


def test_the_crafted_files_are_armed(tmp_path):
    """The payload does run when the file is unpickled the old way: the refusals below mean
    something."""
    marker = tmp_path / "ran"
    torch.save(armed_state(marker), tmp_path / "evil.pt")
    torch.load(tmp_path / "evil.pt", weights_only=False)
    assert marker.exists()


def verb_lines(files: dict[str, Path], evil: Path, run_dir: Path) -> list[list]:
    """Every command line that reads a checkpoint or policy file, given ``evil``."""
    out = files["out"]
    policies = out / "policies"
    policies.mkdir(parents=True, exist_ok=True)
    shutil.copy(evil, policies / "step_000000100.pt")
    return [
        ["eval", evil, "--preset", "easy", "--episodes", "2"],
        ["export", evil, "--onnx", out / "p.onnx"],
        ["export", evil, "--policy-only", out / "p.pt"],
        [
            "fly",
            "--demo",
            "--checkpoint",
            evil,
            "--gif",
            out / "f.gif",
            "--connect",
            "udpin://127.0.0.1:0",
        ],  # fmt: skip
        ["average", evil, "--out", out / "avg.pt"],
        ["average", policies, "--out", out / "avg.pt"],
        ["render", evil, "--out", out / "e.gif"],
        ["train", "--resume", run_dir, "--no-progress"],
        ["convert", evil, "--out", out / "c.pt"],
    ]


@pytest.mark.parametrize("kind", ["zip", "legacy", "bare"])
def test_a_crafted_pickle_is_refused_by_every_verb_and_never_runs(kind, crafted, capsys, tiny_run,
                                                                   tmp_path):  # fmt: skip
    evil = crafted[kind]
    run_dir = tmp_path / "run"
    shutil.copytree(tiny_run, run_dir)
    shutil.copy(evil, run_dir / "checkpoint.pt")
    for argv in verb_lines(crafted, evil, run_dir):
        code, out, err = run(capsys, argv)
        lines = err.strip().splitlines()
        where = " ".join(map(str, argv))
        assert not crafted["marker"].exists(), f"the payload ran: {where}"
        assert code == 2, (where, err)
        assert len(lines) == 1 and lines[0].startswith("safenav: error: "), (where, err)
        assert "Traceback" not in out + err, where
        named = {evil.name, "checkpoint.pt", "step_000000100.pt"}
        assert any(n in lines[0] for n in named), (where, err)  # names the file
        if kind != "bare":  # a bare pickle is no torch file: "corrupt ... or not a torch file"
            assert "needs pickle" in lines[0] or "no safenav wrote" in lines[0], (where, err)
            assert "safenav convert" in lines[0], (where, err)  # and the way out
    assert not [p for p in crafted["out"].rglob("*") if p.is_file() and "policies" not in p.parts]
    # fly --policy never unpickles a .pt at all (ONNX only): refused before reading
    code, _, err = run(capsys, ["fly", "--policy", evil, "--goal", "1", "2", "1.5", "--connect",
                                "udpin://127.0.0.1:0"])  # fmt: skip
    assert code == 2 and "not an exported ONNX policy" in err and not crafted["marker"].exists()


def test_the_refusal_names_what_the_file_asks_for(crafted):
    with pytest.raises(SafenavError) as err:
        load_checkpoint(crafted["zip"])
    message = str(err.value)
    assert re.search(r"asks for (posix|os|nt)\.system", message), message
    assert f"safenav convert {crafted['zip']}" in message and "\n" not in message
    assert not crafted["marker"].exists()


# ------------------------------------------------------------------ what safenav writes loads


def test_committed_checkpoints_load_without_pickle():
    for path in sorted((ROOT / "checkpoints").glob("*.pt")):
        state = torch.load(path, weights_only=True)  # torch's default allow-list, nothing added
        assert state["format"] == FORMAT and "state_dict" in state["policy"], path


def test_every_file_of_a_training_run_loads_without_pickle(tiny_run):
    files = sorted(tiny_run.rglob("*.pt"))
    assert {"checkpoint.pt", "best.pt"} <= {p.name for p in files} and len(files) >= 3
    for path in files:
        torch.load(path, weights_only=True)
    state = load_checkpoint(tiny_run)
    assert {"buffer", "nstep_window", "rng", "optimizers"} <= set(state)


def test_safe_state_converts_numpy_and_refuses_objects(tmp_path):
    state = {"a": np.float64(0.5), "b": np.int32(3), "c": np.arange(4, dtype=np.uint32),
             "d": (np.bool_(True), [np.float32(2.0)]), "e": {"f": np.zeros((2, 2))}}  # fmt: skip
    save_checkpoint(tmp_path / "c.pt", state)
    back = torch.load(tmp_path / "c.pt", weights_only=True)
    assert back["a"] == 0.5 and type(back["a"]) is float and type(back["b"]) is int
    assert back["c"].dtype == torch.int64 and back["c"].tolist() == [0, 1, 2, 3]
    assert back["d"] == (True, [2.0]) and back["e"]["f"].shape == (2, 2)
    with pytest.raises(TypeError, match=r"state\['x'\]\['p'\]: a pathlib"):
        save_checkpoint(tmp_path / "bad.pt", {"x": {"p": Path("somewhere")}})
    assert not (tmp_path / "bad.pt").exists() and not list(tmp_path.glob(".*.tmp"))
    with pytest.raises(TypeError):
        safe_state({"o": np.array([1, "x"], dtype=object)})


def test_rng_state_round_trips_through_a_safe_checkpoint(tmp_path):
    random.seed(1)
    np.random.seed(2)  # noqa: NPY002
    torch.manual_seed(3)
    save_checkpoint(tmp_path / "c.pt", {"rng": rng_state()})
    draws = (random.random(), np.random.random(3).tolist(), torch.rand(3).tolist())  # noqa: NPY002
    set_rng_state(torch.load(tmp_path / "c.pt", weights_only=True)["rng"])
    assert (random.random(), np.random.random(3).tolist(), torch.rand(3).tolist()) == draws  # noqa: NPY002


def test_cuda_rng_states_loaded_onto_the_gpu_are_restored_as_cpu_tensors(monkeypatch):
    """A run on --device cuda loads its checkpoint with map_location=cuda, which moves the CUDA
    generators' states there too; torch.cuda.set_rng_state_all takes CPU byte tensors only (a
    resume on an H200 stopped with "RNG state must be a torch.ByteTensor")."""
    given = []
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "set_rng_state_all", given.extend)

    class OnGpu:  # a tensor that map_location put on the GPU: only .cpu() brings it back
        def cpu(self):
            return torch.zeros(16, dtype=torch.uint8)

    set_rng_state({**rng_state(), "cuda": [OnGpu(), OnGpu()]})
    assert len(given) == 2 and all(isinstance(s, torch.Tensor) and s.device.type == "cpu"
                                   for s in given)  # fmt: skip


# -------------------------------------------------------------- older checkpoints: convert


def old_style(state: dict) -> dict:
    """``state`` as an older safenav wrote it: NumPy's RNG state a tuple holding an array."""
    name, key, *rest = state["rng"]["numpy"]
    return {**state, "rng": {**state["rng"], "numpy": (name, key.numpy().astype(np.uint32), *rest)}}


def test_an_older_checkpoint_is_refused_then_converted_and_resumes(tiny_run, tmp_path, capsys):
    run_dir = tmp_path / "run"
    shutil.copytree(tiny_run, run_dir)
    new = load_checkpoint(run_dir)
    torch.save(old_style(new), run_dir / "checkpoint.pt")  # what safenav wrote before
    code, _, err = run(capsys, ["train", "--resume", run_dir, "--no-progress"])
    assert code == 2 and len(err.strip().splitlines()) == 1
    assert "numpy" in err and f"safenav convert {run_dir / 'checkpoint.pt'}" in err
    code, out, err = run(capsys, ["convert", run_dir])  # in place
    assert code == 0 and "NumPy arrays as tensors" in out, err
    converted = torch.load(run_dir / "checkpoint.pt", weights_only=True)
    for a, b in zip(converted["rng"]["numpy"], new["rng"]["numpy"], strict=True):
        assert torch.equal(a, b) if isinstance(a, torch.Tensor) else a == b
    assert torch.equal(converted["buffer"]["obs"]["lidar"], new["buffer"]["obs"]["lidar"])
    # the older form still restores the same NumPy stream (what convert keeps)
    set_rng_state(old_style(new)["rng"])
    old_draws = np.random.random(4)  # noqa: NPY002
    set_rng_state(converted["rng"])
    assert np.array_equal(np.random.random(4), old_draws)  # noqa: NPY002
    code, out, _ = run(capsys, ["convert", run_dir])
    assert code == 0 and "nothing to convert" in out
    code, _, err = run(capsys, ["train", "--resume", run_dir, "--total-steps", "400",
                                "--no-progress"])  # fmt: skip
    assert code == 0, err
    assert load_checkpoint(run_dir)["global_step"] == 400


def test_convert_refuses_what_no_safenav_wrote_unless_trusted(crafted, tmp_path):
    with pytest.raises(SafenavError, match=r"no safenav wrote.*--trust-pickle") as err:
        convert_checkpoint(crafted["zip"], tmp_path / "c.pt")
    assert "\n" not in str(err.value) and not crafted["marker"].exists()
    # --trust-pickle unpickles in full (the payload would run: not tried here); an object
    # safenav cannot store without pickle is still refused before writing
    odd = tmp_path / "odd.pt"
    torch.save({"format": FORMAT, "format_version": FORMAT_VERSION, "p": Path("x")}, odd)
    with pytest.raises(SafenavError, match="cannot store without pickle"):
        convert_checkpoint(odd, tmp_path / "c.pt", trust_pickle=True)
    assert not (tmp_path / "c.pt").exists()


def test_corrupt_files_are_still_reported_as_corrupt(tmp_path):
    (tmp_path / "garbage.pt").write_bytes(b"not a checkpoint at all")
    ckpt = (ROOT / "checkpoints" / "csac-paper.pt").read_bytes()
    (tmp_path / "half.pt").write_bytes(ckpt[: len(ckpt) // 2])
    (tmp_path / "text").write_text("a file, not a directory\n")  # the unpickler: IndexError
    for name in ("garbage.pt", "half.pt", "text"):
        with pytest.raises(SafenavError, match="corrupt or truncated, or not a torch file"):
            load_checkpoint(tmp_path / name)


# -------------------------------------------------------------- one atomic, fsynced writer


def test_write_json_and_save_checkpoint_fsync_file_and_directory(tmp_path, monkeypatch):
    synced: list[str] = []
    real_fsync = os.fsync

    def fsync(fd):
        synced.append(os.readlink(f"/proc/self/fd/{fd}") if Path("/proc/self/fd").exists() else "?")
        return real_fsync(fd)

    monkeypatch.setattr(os, "fsync", fsync)
    write_json(tmp_path / "a.json", {"x": float("nan"), "y": (1, 2)})
    assert json.loads((tmp_path / "a.json").read_text()) == {"x": None, "y": [1, 2]}
    save_checkpoint(tmp_path / "c.pt", {"w": torch.ones(3)})
    if synced[0] != "?":
        tmp = [s for s in synced if s.endswith(".tmp")]
        assert len(tmp) == 2 and synced.count(str(tmp_path)) == 2, synced  # each: file, then dir
    assert not list(tmp_path.glob(".*.tmp"))
    write_json(tmp_path / "new" / "dir" / "b.json", [1])  # --json into a folder not yet made
    assert json.loads((tmp_path / "new" / "dir" / "b.json").read_text()) == [1]


def test_a_failed_write_keeps_the_old_file(tmp_path):
    write_json(tmp_path / "a.json", {"v": 1})
    with pytest.raises(ZeroDivisionError), atomic.atomic_write(tmp_path / "a.json", "w") as f:
        f.write('{"v": 2')
        _ = 1 / 0
    assert json.loads((tmp_path / "a.json").read_text()) == {"v": 1}
    assert not list(tmp_path.glob(".*.tmp"))


def test_every_json_file_in_src_goes_through_write_json():
    """No JSON written around the one writer, in the package or the research scripts
    (``events.jsonl`` appends a line per event and is no JSON document; the perception link
    writes to a socket)."""
    bypass = re.compile(r"json\.dump\(|write_text\(\s*json\.dumps|\.write\(json\.dumps")
    found = []
    scripts = [*(ROOT / "src" / "safenav").rglob("*.py"), *(ROOT / "experiments").rglob("*.py")]
    for path in sorted(scripts):
        for n, line in enumerate(path.read_text().splitlines(), 1):
            if bypass.search(line) and "events" not in line:
                found.append(f"{path.relative_to(ROOT)}:{n}: {line.strip()}")
    assert not found, found
    loads = [p for p in (ROOT / "src").rglob("*.py") if "torch.load(" in p.read_text()]
    assert [p.name for p in loads] == ["checkpoint.py"]  # the one reader: weights only
