"""``safenav bench update`` measures (a smoke run: the figures themselves are in docs/csac.md)."""

from __future__ import annotations

import json

import pytest

from safenav.bench.update import bench_update


@pytest.mark.long
def test_bench_update_smoke(tmp_path):
    out = tmp_path / "update.json"
    result = bench_update(out, repeats=1, updates=2, threads=1)
    saved = json.loads(out.read_text())
    for key in ("csac_updates_per_s", "sac_updates_per_s", "sb3_sac_updates_per_s",
                "csac_bf16_updates_per_s", "sac_cpu_ms_per_update", "sac_vs_sb3"):  # fmt: skip
        assert saved[key] > 0 and result[key] == saved[key]
