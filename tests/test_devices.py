"""Seeds split over several devices and processes (CPU devices forced in subprocesses):
the same numbers as one device, checkpoints that resume on another device count, and a
two-process `jax.distributed` run that writes one run directory."""
import csv
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.device_runs import GRID_SEEDS, GRID_TASKS, STOP_AFTER_CHUNKS, grid_overrides
from tests.ports import free_port
from tests.xla_opt import env_as_runs

ROOT = Path(__file__).resolve().parent.parent


def _env(devices_per_process: int, **extra) -> dict:
    # compiled as runs do: one device and four agree to rounding there (tests/xla_opt.py)
    env = env_as_runs(dict(os.environ, PYTHONPATH=str(ROOT), **extra))
    env["XLA_FLAGS"] = (env.get("XLA_FLAGS", "") +
                        f" --xla_force_host_platform_device_count={devices_per_process}")
    return env


def _run(mode: str, out: Path, devices: int, visible: int = 4):
    done = subprocess.run([sys.executable, "-m", "tests.device_runs", mode, str(out),
                           str(devices)], env=_env(visible), cwd=ROOT, capture_output=True,
                          text=True, timeout=600)
    return done


def _ok(done):
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    return done


def _eval_rows(run_dir: Path):
    return list(csv.DictReader(open(run_dir / "eval.csv", newline="")))


def _records(run_dir: Path):
    """metrics.jsonl less wall-clock timings, ordered by (step, seed)."""
    rows = [{k: v for k, v in json.loads(line).items() if not k.startswith("perf/")}
            for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    rows = [r for r in rows if len(r) > 2]  # rows of timings only are gone
    return sorted(rows, key=lambda r: (r["step"], r["seed"], sorted(r)))


def assert_same_run(a: Path, b: Path):
    rows_a, rows_b = _eval_rows(a), _eval_rows(b)
    assert [(r["step"], r["seed"]) for r in rows_a] == [(r["step"], r["seed"]) for r in rows_b]
    for x, y in zip(rows_a, rows_b):
        np.testing.assert_allclose(float(x["true_return"]), float(y["true_return"]),
                                   rtol=1e-5, atol=1e-5)
    rec_a, rec_b = _records(a), _records(b)
    assert len(rec_a) == len(rec_b)
    for x, y in zip(rec_a, rec_b):
        assert sorted(x) == sorted(y)
        np.testing.assert_allclose([float(x[k]) for k in sorted(x)],
                                   [float(y[k]) for k in sorted(y)], rtol=1e-4, atol=1e-5,
                                   err_msg=f"step {x['step']} seed {x['seed']}")


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    root = tmp_path_factory.mktemp("devices")
    for n in (1, 4):
        _ok(_run("full", root / f"full{n}", n))
    return root


def test_four_seeds_on_four_devices_equal_one_device(runs):
    rows = _eval_rows(runs / "full4")
    assert {r["seed"] for r in rows} == {"1", "2", "3", "4"} and len(rows) == 4 * 3
    assert_same_run(runs / "full4", runs / "full1")
    # the run was split: every checkpointed leaf is stored in four shards of one seed each
    meta = json.loads(next((runs / "full4" / "checkpoints" / "120").rglob("_sharding"))
                      .read_text())
    layouts = [json.loads(v) for v in meta.values()]
    assert layouts and all(m["partition_spec"][0] == "seeds" and len(m["device_mesh"]["mesh"])
                           == 4 for m in layouts)


@pytest.fixture(scope="module")
def cut_on_four(tmp_path_factory):
    """The same run stopped after 3 chunks on 4 devices (step 60: a checkpoint between two
    regular ones, after the first feedback round)."""
    cut = tmp_path_factory.mktemp("cut") / "run"
    _ok(_run("cut", cut, 4))
    assert len(_eval_rows(cut)) == 4 and STOP_AFTER_CHUNKS * 20 == 60  # step 40 only
    return cut


# CI time: resuming on 2 devices (40 s here) is a slow test; on 1 device stays
@pytest.mark.parametrize("devices", [pytest.param(2, marks=pytest.mark.slow), 1])
def test_a_checkpoint_of_four_devices_resumes_on_fewer(runs, cut_on_four, tmp_path, devices):
    run = tmp_path / "run"
    shutil.copytree(cut_on_four, run)
    _ok(_run("resume", run, devices))
    assert_same_run(run, runs / "full4")


def test_a_seed_count_the_devices_cannot_split_is_refused_by_name(tmp_path):
    done = _run("full", tmp_path / "three", 3)
    assert done.returncode == 2 and "--devices 3 does not divide the 4 seeds" in done.stderr
    assert not (tmp_path / "three").exists()  # refused before anything was written
    done = _run("full", tmp_path / "eight", 8)
    assert done.returncode == 2 and "this process sees 4 device(s)" in done.stderr


@pytest.mark.slow  # CI time: 55 s here (two processes, each compiling the run)
def test_two_processes_write_one_run_directory_equal_to_one_process(runs, tmp_path):
    """Two processes of 2 CPU devices each (localhost `jax.distributed`), the command every
    host runs: one run directory, the same numbers as the single-process run."""
    out, port = tmp_path / "two_hosts", free_port()
    procs = [subprocess.Popen(
        [sys.executable, "-m", "tests.device_runs", "full", str(out), "4"],
        env=_env(2, JAX_COORDINATOR_ADDRESS=f"127.0.0.1:{port}", JAX_NUM_PROCESSES="2",
                 JAX_PROCESS_ID=str(i)),
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        for i in range(2)]
    logs = [p.communicate(timeout=600)[0] for p in procs]
    assert [p.returncode for p in procs] == [0, 0], "\n".join(x[-3000:] for x in logs)
    assert sorted(p.name for p in out.iterdir()) == sorted(
        p.name for p in (runs / "full4").iterdir())
    assert sorted(p.name for p in (out / "checkpoints").iterdir()) == ["120", "80"]
    assert_same_run(out, runs / "full4")


@pytest.mark.slow  # CI time: 2 min (a calibration and two grids)
def test_a_grid_trains_runs_side_by_side_on_groups_of_devices(tmp_path):
    """4 devices, 2 seeds a run: two groups of 2 devices train the grid's two runs at once,
    after a calibration that estimates each; each run equals the same run on one device."""
    from hprior_jax.experiments.grid import run_grid

    done = _ok(_run("grid", tmp_path / "side", 4))
    assert "2 run(s) at a time, each over 2 device(s)" in done.stdout
    assert "devices [0, 1]: toy_point/sac ~" in done.stdout
    assert "devices [2, 3]: toy_scaled/sac ~" in done.stdout
    assert "estimated wall time" in done.stdout
    run_grid(tmp_path / "alone", GRID_TASKS, ["sac"], GRID_SEEDS, "smoke", grid_overrides(),
             progress=False)
    for task in GRID_TASKS:
        assert_same_run(tmp_path / "side" / task / "sac", tmp_path / "alone" / task / "sac")
