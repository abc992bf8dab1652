"""``bench_latency``: the figures ``safenav bench latency`` writes (a short run)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

pytest.importorskip("onnxruntime")


def test_bench_latency_reports_every_backend_and_the_pipeline(tmp_path: Path) -> None:
    from safenav.bench.latency import bench_latency

    threads = torch.get_num_threads()
    out = tmp_path / "latency.json"
    res = bench_latency(
        out, iterations=30, warmup=5, frames=3, checkpoint=None, quiet=True, repeats=2
    )
    assert torch.get_num_threads() == threads  # restored
    assert json.loads(out.read_text()) == res
    for name in ("torch", "torchscript", "onnx", "pipeline", "pipeline_one_camera", "map_update", "control_step",
                 "observation", "policy", "shield"):  # fmt: skip
        p50, p99 = res[f"{name}_p50_ms"], res[f"{name}_p99_ms"]
        assert 0 < p50 <= p99 < 1000
    assert res["threads"] == 1 and res["target_pipeline_p99_ms"] == 2.0
    assert len(res["pipeline_p99_ms_per_repeat"]) == res["repeats"] == 2
    assert res["pipeline"]["cameras"] == 4 and res["actor"].startswith("reference")
