"""``safenav bench soak`` runs end to end at a tiny size and reports its memory figures."""

from __future__ import annotations

import json
import math
import mmap
import time

import pytest

from safenav.bench.soak import RssSampler, bench_soak, rss_mb

pytestmark = pytest.mark.usefixtures("one_thread")


def test_rss_sampler_sees_an_allocation() -> None:
    # An anonymous mapping, not a bytes object: malloc may hand back heap pages that earlier
    # tests in this worker freed but that are still resident, and then RSS does not move (CI
    # saw +0.008 MiB that way). Fresh mapped pages become resident only when written.
    size = 64 * 2**20
    before = rss_mb()
    with RssSampler(period=0.01) as rss, mmap.mmap(-1, size) as block:
        for _ in range(size // 2**20):
            block.write(b"x" * 2**20)
        time.sleep(0.05)
    assert max(r for _, r in rss.samples) - before > 32


@pytest.mark.long
def test_tiny_soak_writes_its_figures(tmp_path) -> None:
    out = bench_soak(tmp_path / "soak.json", env_steps=4096, updates=200, num_envs=64,
                     preset="easy", buffer_size=600)  # fmt: skip
    saved = json.loads((tmp_path / "soak.json").read_text())
    assert saved["env_steps"] == 4096 and saved["updates"] == 200
    for key in ("env_rss_start_mb", "env_rss_end_mb", "env_growth_after_warmup_mb",
                "train_rss_start_mb", "train_rss_after_buffer_full_mb", "train_rss_last_10pct_mb",
                "train_growth_after_buffer_full_mb", "buffer_mb"):  # fmt: skip
        assert math.isfinite(saved[key]), key
    assert out == saved | {"machine": out["machine"]}
