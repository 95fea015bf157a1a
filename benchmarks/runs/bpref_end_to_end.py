"""End to end against real BPref: 5 vmapped seeds of `hprior train --algo pebble` against 5
processes of BPref's own `train_PEBBLE.py`, at the same settings, back to back.

    python -m benchmarks.runs.bpref_end_to_end --prepare --deps ~/bpref_deps   # once
    python -m benchmarks.runs.bpref_end_to_end --bpref ~/BPref --deps ~/bpref_deps \
        [--task cheetah_run] [--preset reduced] [--steps 20000] [--seeds 5] [--repeats 2]

`--bpref` is a checkout of https://github.com/rll-research/BPref (not part of this project).
BPref pins Python 3.6, torch 1.4, hydra 0.11, gym 0.17 and a dm_control fork; it runs here
under this project's Python, torch (CPU) and dm_control 1.0.50 with:
  * `--prepare`: hydra-core 0.11.3 and what it and BPref import that this project does not
    install (omegaconf 1.4, six, gym 0.17.3, cloudpickle, termcolor, scikit-image, and
    setuptools < 70 for hydra's `pkg_resources`), into `--deps`, never into the venv;
  * a shim put first on the BPref processes' path: numpy's removed `np.int/float/bool`
    aliases (BPref's dmc2gym uses `np.int`); `reward_model.device = "cpu"` after BPref's
    `reward_model.py` sets it to "cuda" (its one hard-coded device); and an empty
    `metaworld.envs.mujoco.env_dict`, which BPref's utils.py imports at the top while only
    its MetaWorld runs use it (metaworld 3 moved that module).
BPref's code and its dmc2gym (`custom_dmc2gym/`) run unchanged; its dm_control fork is not
used (this project's dm_control 1.0.50 is). Each BPref process gets one thread
(OMP_NUM_THREADS / MKL_NUM_THREADS = 1), as the issue's method asks.

Settings: BPref's overrides are read from this project's configuration of (task, pebble,
preset), so both sides run the same schedule (seed, unsupervised and feedback steps), label
budget, query selection, SAC and reward-model sizes and learning rates, and evaluation
(BPref evaluates at its episode ends, every `eval_frequency` steps but not after the last).
Our side is `benchmarks.runs.end_to_end.one_run` (empty compilation cache: a cold start).
Reported per side and repeat: wall seconds from launch to the last process's exit, and
`env_steps_per_s` = seeds x steps / wall (compile and start-up included on both sides).
Writes benchmarks/results/runs/bpref_end_to_end.csv (or --out).
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import tasks  # noqa: F401  (sets XLA_FLAGS before jax is imported)
from benchmarks._timing import write_rows
from benchmarks.runs.end_to_end import SEEDS, one_run
from hprior_jax.presets import train_preset

RESULTS = Path(__file__).resolve().parents[1] / "results" / "runs" / "bpref_end_to_end.csv"
# what BPref's train_PEBBLE.py imports beyond this project's own dependencies (versions that
# ran it on 2026-12-04); --no-deps so nothing in the venv is replaced
BPREF_DEPS = ("hydra-core==0.11.3", "omegaconf==1.4.1", "six==1.17.0", "gym==0.17.3",
              "cloudpickle==3.1.3", "termcolor==3.3.0", "setuptools==69.5.1",
              "scikit-image==0.26.0", "lazy_loader==0.6", "networkx==3.6.1",
              "tifffile==2026.3.3")
FEED_TYPE = {"uniform": 0, "disagreement": 1, "entropy": 2}  # BPref's feed_type numbers

SITECUSTOMIZE = '''\
import importlib.abc
import importlib.machinery
import sys

import numpy as np

for name, value in (("int", int), ("float", float), ("bool", bool)):
    if name not in np.__dict__:
        setattr(np, name, value)


class _RewardModelOnCPU(importlib.abc.MetaPathFinder):
    def find_spec(self, fullname, path, target=None):
        if fullname != "reward_model":
            return None
        spec = importlib.machinery.PathFinder.find_spec(fullname, path)
        run = spec.loader.exec_module

        def exec_module(module):
            run(module)
            module.device = "cpu"
        spec.loader.exec_module = exec_module
        return spec


sys.meta_path.insert(0, _RewardModelOnCPU())
'''


def prepare(deps: Path) -> None:
    """Install BPref's extra imports into `deps` (not into this environment)."""
    subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--target",
                    str(deps), *BPREF_DEPS], check=True)


def write_shim(shim: Path) -> None:
    shim.mkdir(parents=True, exist_ok=True)
    (shim / "sitecustomize.py").write_text(SITECUSTOMIZE)
    env_dict = shim / "metaworld" / "envs" / "mujoco"
    env_dict.mkdir(parents=True, exist_ok=True)
    for pkg in (shim / "metaworld", shim / "metaworld" / "envs", env_dict):
        (pkg / "__init__.py").write_text("")
    (env_dict / "env_dict.py").write_text("ALL_V2_ENVIRONMENTS = {}\nALL_V1_ENVIRONMENTS = {}\n")


def bpref_overrides(task: str, preset: str, steps: int) -> list[str]:
    """BPref's hydra overrides for our PEBBLE configuration of (task, preset), `steps` long."""
    cfg = train_preset(task, "pebble", preset)
    pb, sac = cfg.pebble, cfg.sac
    if pb.reward_hidden != 256 or pb.reward_depth != 3 or pb.reward_batch != 128:
        # BPref's RewardModel fixes these (256 x 3 hidden, 128-pair minibatches)
        raise ValueError("BPref's reward model is 256 x 3 with 128-pair batches only")
    values = {
        "env": task, "device": "cpu", "num_train_steps": steps,
        "num_seed_steps": cfg.num_seed_steps, "num_unsup_steps": pb.num_unsup_steps,
        "num_interact": pb.num_interact, "max_feedback": pb.max_feedback,
        "reward_batch": pb.queries_per_round, "reward_update": pb.reward_epochs,
        "feed_type": FEED_TYPE[pb.feed_type], "segment": pb.segment_len,
        "large_batch": pb.large_batch, "ensemble_size": pb.ensemble_size,
        "reward_lr": pb.reward_lr, "reset_update": pb.reset_update, "topK": pb.knn_k,
        "activation": "tanh", "eval_frequency": cfg.eval_every,
        "num_eval_episodes": cfg.num_eval_episodes, "log_save_tb": "false",
        "agent.params.actor_lr": sac.lr, "agent.params.critic_lr": sac.lr,
        "agent.params.alpha_lr": sac.alpha_lr, "agent.params.batch_size": sac.batch_size,
        "agent.params.init_temperature": sac.init_temperature,
        "agent.params.discount": sac.discount, "agent.params.critic_tau": sac.tau,
        "agent.params.critic_target_update_frequency": sac.target_update_every,
        "agent.params.actor_update_frequency": sac.actor_update_every,
    }
    for net in ("diag_gaussian_actor", "double_q_critic"):
        values[f"{net}.params.hidden_dim"] = sac.hidden_dim
        values[f"{net}.params.hidden_depth"] = sac.hidden_depth
    return [f"{k}={v}" for k, v in values.items()]


def run_bpref(bpref: Path, deps: Path, overrides: list[str], n_seeds: int, work: Path) -> dict:
    """`n_seeds` BPref processes at once, one thread each; wall = launch to the last exit."""
    shim = work / "shim"
    write_shim(shim)
    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", MUJOCO_GL="disable",
               PYTHONPATH=os.pathsep.join(str(p) for p in
                                          (shim, deps, bpref / "custom_dmc2gym", bpref)))
    children = []
    t0 = time.perf_counter()
    for seed in SEEDS[:n_seeds]:
        run_dir = work / f"bpref_{seed}"
        run_dir.mkdir(parents=True, exist_ok=True)  # hydra writes its folders under the cwd
        log = open(run_dir / "log.txt", "w")
        cmd = [sys.executable, str(bpref / "train_PEBBLE.py"), *overrides, f"seed={seed}"]
        children.append((subprocess.Popen(cmd, cwd=run_dir, env=env, stdout=log,
                                          stderr=subprocess.STDOUT), log, run_dir))
    ends = []
    for child, log, run_dir in children:
        code = child.wait()
        ends.append(time.perf_counter() - t0)
        log.close()
        if code != 0:
            raise RuntimeError(f"BPref failed:\n{(run_dir / 'log.txt').read_text()[-4000:]}")
    return {"wall_s": max(ends), "first_exit_s": min(ends)}


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--bpref", type=Path, help="a checkout of rll-research/BPref")
    p.add_argument("--deps", type=Path, required=True,
                   help="folder for BPref's extra packages (--prepare installs them there)")
    p.add_argument("--prepare", action="store_true", help="install BPref's extra packages")
    p.add_argument("--task", default="cheetah_run")
    p.add_argument("--preset", default="reduced", choices=["smoke", "reduced", "paper"])
    p.add_argument("--steps", type=int, default=None, help="override the preset's steps")
    p.add_argument("--seeds", type=int, default=5)
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--out", type=Path, default=RESULTS)
    p.add_argument("--keep", type=Path, default=None,
                   help="run the repeats in this folder and keep it (logs, metrics)")
    args = p.parse_args(argv)
    if args.prepare:
        prepare(args.deps)
        if args.bpref is None:
            return
    if args.bpref is None or not (args.bpref / "train_PEBBLE.py").exists():
        p.error("--bpref must be a BPref checkout (train_PEBBLE.py at its top)")

    steps = args.steps or train_preset(args.task, "pebble", args.preset).steps
    overrides = bpref_overrides(args.task, args.preset, steps)
    rows = []
    with tempfile.TemporaryDirectory(prefix="hprior_bpref_") as tmp:
        tmp = args.keep or tmp
        for repeat in range(1, args.repeats + 1):
            work = Path(tmp) / f"repeat_{repeat}"
            work.mkdir(parents=True)
            ours = one_run(args.task, "pebble", args.seeds, args.preset, steps, work)
            theirs = run_bpref(args.bpref, args.deps, overrides, args.seeds, work)
            for side, r in (("hprior_jax", ours), ("bpref", theirs)):
                rows.append({"repeat": repeat, "side": side, "task": args.task,
                             "preset": args.preset, "steps": steps, "seeds": args.seeds,
                             "wall_s": round(r["wall_s"], 1),
                             "env_steps_per_s": round(args.seeds * steps / r["wall_s"], 1),
                             "compile_s": round(r.get("compile_s", float("nan")), 1),
                             "first_step_s": round(r.get("first_step_s", float("nan")), 1),
                             "first_exit_s": round(r.get("first_exit_s", float("nan")), 1),
                             "peak_rss_gb": round(r.get("peak_rss_gb", float("nan")), 2)})
                print(rows[-1], flush=True)
            print(f"repeat {repeat}: hprior_jax / BPref env steps/s = "
                  f"{theirs['wall_s'] / ours['wall_s']:.2f}", flush=True)
            write_rows(rows, args.out)  # after each repeat: a long run keeps what it measured


if __name__ == "__main__":
    main()
