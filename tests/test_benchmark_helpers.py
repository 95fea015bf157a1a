"""The bookkeeping of the benchmark scripts (not their speed): how run logs become wall-time
parts and how FLOPs and times become the roofline columns."""
import json

import pytest

import benchmarks._timing as timing
from benchmarks._timing import best_seconds, roofline
from benchmarks.runs.end_to_end import perf_totals


def test_perf_totals_sums_one_seed_and_every_part(tmp_path):
    records = [
        {"step": 20, "seed": 1, "perf/chunk_s": 2.0, "perf/compile_s": 30.0},
        {"step": 20, "seed": 2, "perf/chunk_s": 2.0, "perf/compile_s": 30.0},  # same, other seed
        {"step": 40, "seed": 1, "perf/chunk_s": 1.5, "perf/event_s": 4.0,
         "perf/world_model_s": 3.0, "perf/eval_s": 0.5, "perf/checkpoint_s": 0.25},
        {"step": 40, "seed": 1, "perf/meta_step_s": 0.75},
        {"step": 40, "seed": 1, "train/critic_loss": 9.0},
    ]
    path = tmp_path / "metrics.jsonl"
    path.write_text("\n".join(json.dumps(r) for r in records) + "\n")
    totals = perf_totals(path, first_seed=1)
    assert totals == {"steps": 40, "chunk_s": 3.5, "event_s": 4.0, "world_model_s": 3.0,
                      "meta_step_s": 0.75, "eval_s": 0.5, "checkpoint_s": 0.25,
                      "compile_s": 30.0}


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


def test_write_rows_appends_to_kept_rows_with_new_columns(tmp_path):
    path = tmp_path / "r.csv"
    timing.write_rows([{"size": "a", "ms": 1.5}], path)
    kept = timing.read_rows(path)
    timing.write_rows([{"size": "b", "ms": 2.0, "temp_gib": 0.5}], path, kept)
    assert timing.read_rows(path) == [{"size": "a", "ms": "1.5", "temp_gib": ""},
                                      {"size": "b", "ms": "2.0", "temp_gib": "0.5"}]
    assert timing.read_rows(tmp_path / "missing.csv") == []


def test_op_profile_maps_xla_ops_to_their_jax_source():
    from benchmarks.updates.op_profile import matmul_ops, op_class, op_sources, source_of

    hlo = ('  %fusion.3 = f32[4,8]{1,0} fusion(%p0), kind=kLoop, metadata={op_name='
           '"jit(run)/while/body/closed_call/transpose(jvp(Model))/layers/self_attn/bind,jnd->bnij/transpose" '
           'stack_frame_id=9}\n'
           '  ROOT %rng.1 = u32[8,4]{1,0} fusion(%k), metadata={op_name='
           '"jit(run)/jvp(Model)/layers/Dropout_1/jit(_bernoulli)/jit(_uniform)/rng_bit_generator"}\n'
           '  %copy.2 = f32[4]{0} copy(%x)\n'
           '%fused_computation.7 (p: f32[4,8]) -> f32[4,4] {\n'
           '  %p = f32[4,8]{1,0} parameter(0)\n'
           '  ROOT %dot.1 = f32[4,4]{1,0} dot(%p, %p), metadata={op_name="jit(run)/layers/linear1/dot_general"}\n'
           '}\n'
           '  %ynn_fusion.7 = f32[4,4]{1,0} fusion(%a), kind=kCustom, calls=%fused_computation.7\n')
    sources = op_sources(hlo)
    assert set(sources) == {"fusion.3", "rng.1", "dot.1", "ynn_fusion.7"}
    assert source_of(sources["ynn_fusion.7"]) == ("fwd", "linear1/dot_general")
    assert source_of(sources["fusion.3"]) == ("bwd", "bind,jnd->bnij/transpose")
    assert source_of(sources["rng.1"]) == ("fwd", "rng (dropout bits)")
    assert source_of("jit(run)/jvp(M)/layers/Dropout_0/select_n") == ("fwd", "dropout (apply mask)")
    assert matmul_ops(hlo) == {"ynn_fusion.7", "dot.1"}  # a fusion holding a dot is a matmul
    assert op_class(sources["fusion.3"], False) == "relative position (encodings, shift)"
    assert op_class(sources["rng.1"], False) == "dropout bits"
    assert op_class(sources["fusion.3"], True) == "matmuls"
    assert op_class("jit(run)/vmap()/add", False) == "optimizer and glue"


def _gpu_suite_tiny(out, parts, extra=()):
    """`python -m benchmarks.runs.gpu_suite --scale tiny --parts ... [extra]` in a child (the suite
    sets PyTorch's default device) -> {part: rows}."""
    import csv
    import os
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parent.parent
    done = subprocess.run([sys.executable, "-m", "benchmarks.runs.gpu_suite", "--scale", "tiny",
                           "--parts", *parts, "--out", str(out), *extra], cwd=root, capture_output=True,
                          text=True, env=dict(os.environ, PYTHONPATH=str(root)), timeout=900)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-3000:]
    read = lambda name: list(csv.DictReader(open(out / f"{name}.csv", newline="")))
    assert [r["part"] for r in read("suite")] == list(parts)
    rows = {part: read(part) for part in parts}
    for part, part_rows in rows.items():
        assert part_rows and all(r["device"].startswith("cpu:") for r in part_rows), part
    return rows


@pytest.mark.slow  # 65-95 s: a benchmark script's check, run before a benchmark
def test_gpu_suite_measures_env_throughput_at_tiny_sizes_on_cpu(tmp_path):
    """The GPU suite's driver and its env part on a CPU (its other parts: the slow tests),
    with and without the port's contact cap."""
    rows = _gpu_suite_tiny(tmp_path, ("env",), ("--env-caps", "task", "none"))["env"]
    assert [r["contact_cap"] for r in rows] == ["8", ""]  # cheetah's cap, then none
    assert all(float(r["env_steps_per_s"]) > 0 for r in rows)


@pytest.mark.slow  # 65-95 s: a benchmark script's check, run before a benchmark
def test_mjx_warp_benchmark_steps_like_c_mujoco(tmp_path):
    """benchmarks.ports.mjx_warp on the JAX side alone (warp-lang is not a dependency): the port's
    model under `mjx.step` follows C MuJoCo's `mj_step` from the same states and controls."""
    import csv

    from benchmarks.ports import mjx_warp

    out = tmp_path / "mjx_warp.csv"
    mjx_warp.main(["--tasks", "cheetah_run", "--batch", "2", "--steps", "2", "--repeats", "1",
                   "--impls", "jax", "--parity", "2", "--out", str(out)])
    (row,) = list(csv.DictReader(open(out, newline="")))
    assert row["impl"] == "jax" and float(row["substeps_per_s"]) > 0
    # float32 MJX against float64 C: 2e-7 after one control step, 5e-7 after ten (measured)
    assert float(row["jax_qpos_err_1"]) < 1e-5 and float(row["jax_qpos_err_10"]) < 1e-4


@pytest.mark.slow  # CI time: 4 min here (the appendix-size updates and their references)
def test_gpu_suite_measures_updates_at_tiny_sizes_on_cpu(tmp_path):
    rows = _gpu_suite_tiny(tmp_path, ("sac", "reward", "world_model"))
    assert all(float(r["jax_ms"]) > 0 for part in ("sac", "reward", "world_model")
               for r in rows[part])


@pytest.mark.slow  # CI time: the child run compiles cheetah_run's programs (~2 min)
def test_gpu_suite_end_to_end_part_at_tiny_sizes_on_cpu(tmp_path):
    e2e = _gpu_suite_tiny(tmp_path, ("end_to_end",))["end_to_end"][0]
    assert int(e2e["steps"]) == 20 and float(e2e["env_steps_per_s"]) > 0


def test_gpu_carry_keeps_what_the_dm_control_tasks_load(tmp_path):
    """The slim dm_control still builds the ported DM Control models (the GPU machine's
    copy); the wheels it asks for are the locked versions."""
    import os
    import subprocess
    import sys

    from benchmarks.tooling import gpu_carry

    assert gpu_carry.locked_version("mujoco") == gpu_carry.locked_version("mujoco-mjx")
    assert all(gpu_carry.locked_version(name) for name in gpu_carry.WHEELS)
    gpu_carry.slim_dm_control(tmp_path)
    assert not (tmp_path / "dm_control" / "locomotion").exists()
    code = ("import dm_control, sys; assert dm_control.__file__.startswith(sys.argv[1]); "
            "from tasks.dm_control.common import load_suite_model; "
            "from tasks.dm_control.quadruped import load_quadruped_model; "
            "[load_suite_model(d) for d in ('cheetah', 'walker')]; load_quadruped_model(10)")
    env = dict(os.environ, PYTHONPATH=f"{tmp_path}:{gpu_carry.ROOT}", MUJOCO_GL="disable")
    subprocess.run([sys.executable, "-c", code, str(tmp_path)], env=env, check=True)


def test_gpu_carry_packs_a_wheel_in_two_halves_that_unpack_whole(tmp_path):
    """`gpu_carry --warp`'s packing: a wheel's files less the dropped folders, in two halves
    that, concatenated, unpack to the same bytes."""
    import io
    import zipfile

    from benchmarks.tooling import gpu_carry

    wheel = tmp_path / "pkg-1.0-py3-none-any.whl"
    files = {"pkg/__init__.py": b"x = 1\n", "pkg/bin/lib.so": bytes(range(256)) * 400,
             "pkg/tests/test_x.py": b"", "pkg-1.0.dist-info/METADATA": b"Name: pkg\n"}
    with zipfile.ZipFile(wheel, "w") as z:
        for name, data in files.items():
            z.writestr(name, data)
    gpu_carry.pack_wheel(wheel, tmp_path / "carry", drop=("pkg/tests",))
    halves = [(tmp_path / "carry" / h / "part").read_bytes() for h in ("a", "b")]
    assert all(halves) and abs(len(halves[0]) - len(halves[1])) <= 1
    gpu_carry.unpack_warp(tmp_path / "site", io.BytesIO(b"".join(halves)))
    for name, data in files.items():
        path = tmp_path / "site" / name
        assert (path.read_bytes() == data) if "tests" not in name else not path.exists()


def test_bpref_runner_shims_what_bpref_needs_and_maps_our_settings(tmp_path):
    """A stand-in for BPref's train_PEBBLE.py records what the runner gives each process:
    numpy's old aliases, the reward model moved off "cuda", metaworld's old module, one
    thread, its own seed and our preset's settings as hydra overrides."""
    from benchmarks.runs.bpref_end_to_end import bpref_overrides, run_bpref

    bpref = tmp_path / "bpref"
    (bpref / "custom_dmc2gym").mkdir(parents=True)
    (bpref / "reward_model.py").write_text("device = 'cuda'\n")
    (bpref / "train_PEBBLE.py").write_text(
        "import json, os, sys\n"
        "import numpy as np\n"
        "import reward_model\n"
        "import metaworld.envs.mujoco.env_dict as d\n"
        "args = dict(a.split('=', 1) for a in sys.argv[1:])\n"
        "json.dump({'device': reward_model.device, 'np_int': np.int is int,\n"
        "           'env_dict': d.ALL_V2_ENVIRONMENTS, 'omp': os.environ['OMP_NUM_THREADS'],\n"
        "           'args': args}, open('seen.json', 'w'))\n")
    overrides = bpref_overrides("cheetah_run", "reduced", 20_000)
    out = run_bpref(bpref, tmp_path / "deps", overrides, 2, tmp_path / "work")
    assert out["wall_s"] >= out["first_exit_s"] > 0
    seen = [json.loads(p.read_text())
            for p in sorted((tmp_path / "work").glob("bpref_*/seen.json"))]
    assert len(seen) == 2 and seen[0]["args"]["seed"] != seen[1]["args"]["seed"]
    for s in seen:
        assert s["device"] == "cpu" and s["np_int"] and s["env_dict"] == {} and s["omp"] == "1"
        args = s["args"]
        # the reduced PEBBLE preset on cheetah_run (hprior_jax.methods.pebble.pebble_preset)
        assert args["num_train_steps"] == "20000" and args["num_interact"] == "4000"
        assert args["reward_batch"] == "10" and args["max_feedback"] == "100"
        assert args["feed_type"] == "1" and args["reward_update"] == "50"
        assert args["agent.params.actor_lr"] == "0.0005"
        assert args["agent.params.batch_size"] == "256"
        assert args["double_q_critic.params.hidden_dim"] == "256"
