"""`hprior grid`: every (task, algorithm) with its seeds vmapped in one process, into one
results directory laid out as ROOT/<task>/<algo>/ (each an ordinary `hprior train` run dir).

Re-running the same command skips the runs whose last checkpoint reached their budget and
resumes the interrupted ones from their last checkpoint, so a grid can be stopped (Ctrl-C,
a lost machine) and started again at no cost beyond the chunks since that checkpoint."""
from __future__ import annotations

import dataclasses
import json
import time
from dataclasses import dataclass
from pathlib import Path

from hprior_jax.config import RunConfig, differing_fields
from hprior_jax.methods import registry

PAPER_SEEDS = (12345, 23456, 34567, 45678, 56789)  # appendix E


@dataclass(frozen=True)
class GridRun:
    task: str
    algo: str
    cfg: RunConfig
    status: str  # "complete" | "interrupted" | "new"

    @property
    def run_dir(self) -> Path:
        return Path(self.cfg.out)


def run_config(root: Path, task: str, algo: str, seeds, budget: str,
               overrides: dict) -> RunConfig:
    from hprior_jax import envs, presets

    out = str(Path(root) / task / algo)
    # a physics option applies to the tasks of its domain only (grids mix DMC and MetaWorld)
    domain = envs.task_info(task).domain
    overrides = {k: v for k, v in overrides.items()
                 if k not in envs.PHYSICS_OPTIONS or envs.PHYSICS_OPTIONS[k].domain == domain}
    return presets.train_preset(task, algo, budget, seeds=tuple(seeds), out=out, **overrides)


def run_status(cfg: RunConfig) -> str:
    """Whether `cfg.out` holds a finished run of `cfg`, an interrupted one, or nothing.

    A directory holding a run of another configuration is an error: mixing budgets or
    seeds in one table would be silent nonsense."""
    from hprior_jax.checkpoint import Checkpointer
    from hprior_jax.loop.run_dir import load_run_config

    run_dir = Path(cfg.out)
    if not run_dir.exists() or not any(run_dir.iterdir()):
        return "new"
    if not (run_dir / "config.json").exists():
        raise FileExistsError(f"{run_dir} is not empty but holds no config.json; move it away "
                              "so the grid can start that run afresh")
    saved = load_run_config(run_dir)
    differs = [k for k in differing_fields(saved, cfg) if k != "out"]
    if differs:
        raise ValueError(
            f"{run_dir} was run with a different configuration ({', '.join(differs)}); use "
            "another grid directory (--out) or the grid options that made it")
    if not (run_dir / "checkpoints").exists():
        return "interrupted"
    ckpt = Checkpointer(run_dir / "checkpoints")
    try:
        latest = ckpt.latest_step()
    finally:
        ckpt.close()
    return "complete" if latest is not None and latest >= cfg.steps else "interrupted"


def _jsonable(obj):
    return dataclasses.asdict(obj) if dataclasses.is_dataclass(obj) else str(obj)


def plan(root: Path, tasks, algos, seeds, budget: str = "reduced",
         overrides: dict | None = None) -> list[GridRun]:
    """The grid's runs in execution order (the reference first: it normalises every task)."""
    unknown = [a for a in algos if a not in registry.names()]
    if unknown:
        raise ValueError(f"unknown algorithm(s) {unknown}; available: "
                         f"{', '.join(registry.names())}")
    if not tasks or not algos:
        raise ValueError("give at least one --tasks and one --algos")
    algos = sorted(dict.fromkeys(algos),
                   key=lambda a: (a != registry.REFERENCE, list(algos).index(a)))
    runs = []
    for task in dict.fromkeys(tasks):
        for algo in algos:
            cfg = run_config(root, task, algo, seeds, budget, overrides or {})
            runs.append(GridRun(task, algo, cfg, run_status(cfg)))
    return runs


def run_grid(root: Path, tasks, algos, seeds=PAPER_SEEDS, budget: str = "reduced",
             overrides: dict | None = None, progress: bool = True, train_fn=None) -> list[GridRun]:
    """Runs every (task, algo) of the grid that is not complete; returns the plan.

    `train_fn(cfg, run_dir, resume)` defaults to `hprior_jax.loop.host.run` (tests pass a
    recorder)."""
    from hprior_jax.loop import host
    from hprior_jax.loop.run_dir import prepare_run_dir

    root = Path(root)
    runs = plan(root, tasks, algos, seeds, budget, overrides)
    root.mkdir(parents=True, exist_ok=True)
    spec = dict(tasks=list(tasks), algos=list(algos), seeds=list(seeds), budget=budget,
                overrides=overrides or {}, written=time.strftime("%Y-%m-%d %H:%M:%S"))
    (root / "grid.json").write_text(json.dumps(spec, indent=2, default=_jsonable) + "\n")
    if train_fn is None:
        def train_fn(cfg, run_dir, resume):
            host.run(cfg, run_dir, resume=resume, progress=progress)
    for i, r in enumerate(runs, 1):
        head = f"[{i}/{len(runs)}] {r.task} {r.algo} (seeds {', '.join(map(str, seeds))})"
        if r.status == "complete":
            print(f"{head}: complete, skipped ({r.run_dir})", flush=True)
            continue
        print(f"{head}: {'resuming' if r.status == 'interrupted' else 'starting'} "
              f"in {r.run_dir}", flush=True)
        if r.status == "new":
            prepare_run_dir(r.cfg)
        t0 = time.perf_counter()
        train_fn(r.cfg, r.run_dir, r.status == "interrupted")
        print(f"{head}: finished in {time.perf_counter() - t0:.0f} s", flush=True)
    return runs
