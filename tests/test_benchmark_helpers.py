"""The bookkeeping of the benchmark scripts (not their speed): how run logs become wall-time
parts and how FLOPs and times become the roofline columns."""
import json

import pytest

import benchmarks._timing as timing
from benchmarks._timing import best_seconds, roofline
from benchmarks.end_to_end import perf_totals


def test_perf_totals_sums_one_seed_and_every_part(tmp_path):
    records = [
        {"step": 20, "seed": 1, "perf/chunk_s": 2.0, "perf/compile_s": 30.0},
        {"step": 20, "seed": 2, "perf/chunk_s": 2.0, "perf/compile_s": 30.0},  # same, other seed
        {"step": 40, "seed": 1, "perf/chunk_s": 1.5, "perf/event_s": 4.0,
         "perf/world_model_s": 3.0, "perf/eval_s": 0.5, "perf/checkpoint_s": 0.25},
        {"step": 40, "seed": 1, "train/critic_loss": 9.0},
    ]
    path = tmp_path / "metrics.jsonl"
    path.write_text("\n".join(json.dumps(r) for r in records) + "\n")
    totals = perf_totals(path, first_seed=1)
    assert totals == {"steps": 40, "chunk_s": 3.5, "event_s": 4.0, "world_model_s": 3.0,
                      "eval_s": 0.5, "checkpoint_s": 0.25, "compile_s": 30.0}


def test_roofline_columns():
    row = roofline(gflop=4.0, jax_ms=20.0, torch_ms=40.0, matmul_gflops=250.0)
    assert row == {"gflop_per_update": 4.0, "jax_gflops_s": 200.0, "torch_gflops_s": 100.0,
                   "matmul_gflops_s": 250.0}
    assert roofline(4.0, 20.0, None, 250.0)["torch_gflops_s"] == ""


def test_best_seconds_keeps_the_fastest_and_waits(monkeypatch):
    waited = []
    times = iter([0.0, 5.0, 10.0, 11.0, 20.0, 27.0])  # runs of 5, 1 and 7 s
    monkeypatch.setattr(timing.time, "perf_counter", lambda: next(times))
    assert best_seconds(lambda: "out", 3, waited.append) == pytest.approx(1.0)
    assert waited == ["out"] * 3
