"""`hprior grid`: every (task, algorithm) with its seeds vmapped in one process, into one
results directory laid out as ROOT/<task>/<algo>/ (each an ordinary `hprior train` run dir).
With more devices than a run's seeds need, several runs train side by side, each on its
own group of devices.

Re-running the same command skips the runs whose last checkpoint reached their budget and
resumes the interrupted ones from their last checkpoint, so a grid can be stopped (Ctrl-C,
a lost machine) and started again at no cost beyond the chunks since that checkpoint."""
from __future__ import annotations

import dataclasses
import json
import time
from dataclasses import dataclass
from pathlib import Path

from hprior_jax import dir_lock, envs, presets
from hprior_jax.config import RunConfig, differing_fields
from hprior_jax.loop import devices as seed_devices
from hprior_jax.loop import host
from hprior_jax.loop.run_files import latest_checkpoint_step
from hprior_jax.methods import registry
from hprior_jax.runs import build
from hprior_jax.runs.run_dir import load_run_config, prepare_run_dir

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
    out = str(Path(root) / task / algo)
    # a physics option applies to the tasks that offer it only (grids mix DMC and MetaWorld)
    overrides = {k: v for k, v in overrides.items()
                 if k not in envs.PHYSICS_OPTIONS or envs.option_applies(k, task, v)}
    return presets.train_preset(task, algo, budget, seeds=tuple(seeds), out=out, **overrides)


def run_status(cfg: RunConfig) -> str:
    """Whether `cfg.out` holds a finished run of `cfg`, an interrupted one, or nothing.

    A directory holding a run of another configuration is an error: mixing budgets or
    seeds in one table would be silent nonsense."""
    run_dir = Path(cfg.out)
    if not run_dir.exists() or not any(run_dir.iterdir()):
        return "new"
    if not (run_dir / "config.json").exists():
        raise FileExistsError(f"{run_dir} is not empty but holds no config.json; move it away "
                              "so the grid can start that run afresh")
    saved = load_run_config(run_dir)
    # videos change nothing that is learned: a rerun may ask for them or not
    differs = [k for k in differing_fields(saved, cfg)
               if k not in ("out", "capture_video", "video_steps")]
    if differs:
        raise ValueError(
            f"{run_dir} was run with a different configuration ({', '.join(differs)}); use "
            "another grid directory (--out) or the grid options that made it")
    latest = latest_checkpoint_step(run_dir)
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
             overrides: dict | None = None, progress: bool = True, train_fn=None,
             devices: int | None = None, estimate: bool = False,
             run_info: dict | None = None) -> list[GridRun]:
    """Runs every (task, algo) of the grid that is not complete; returns the plan.

    The devices (`devices` of them, default all) are cut into groups of as many as split the
    seeds evenly; each group trains one run at a time, the groups side by side (threads:
    the programs run on their own devices and the host loops are light). With `estimate`,
    every run's remaining wall time is first calibrated (`calibrate`) and the runs are
    packed longest first onto the least loaded group; otherwise they keep the plan's order.
    `train_fn(cfg, run_dir, resume)` replaces training (tests pass a recorder). A second
    grid on the same `root` is refused (dir_lock.DirInUse). `run_info` (what produced the
    grid: `hprior_jax.provenance.run_info()`) goes into each new run's config.json."""
    root = Path(root)
    runs = plan(root, tasks, algos, seeds, budget, overrides)
    root.mkdir(parents=True, exist_ok=True)
    with dir_lock.DirLock(root):  # one grid per results directory
        return _run_plan(root, runs, tasks, algos, seeds, budget, overrides, progress,
                         train_fn, devices, estimate, run_info)


def _run_plan(root: Path, runs, tasks, algos, seeds, budget, overrides, progress, train_fn,
              devices, estimate, run_info) -> list[GridRun]:
    import jax

    spec = dict(tasks=list(tasks), algos=list(algos), seeds=list(seeds), budget=budget,
                overrides=overrides or {}, written=time.strftime("%Y-%m-%d %H:%M:%S"))
    (root / "grid.json").write_text(json.dumps(spec, indent=2, default=_jsonable) + "\n")
    for r in runs:
        if r.status == "complete":
            print(f"{r.task} {r.algo}: complete, skipped ({r.run_dir})", flush=True)
    todo = [r for r in runs if r.status != "complete"]
    available = jax.local_devices()
    n = seed_devices.checked_count(devices or len(available), available)
    per_run = seed_devices.devices_per_run(len(seeds), n)
    groups = [available[i * per_run:(i + 1) * per_run] for i in range(n // per_run)]
    seconds = {}
    if estimate and todo:
        print(f"calibrating {len(todo)} run(s): one chunk per phase, the first events and an "
              "evaluation each (what compiles now is cached for the runs)", flush=True)
        seconds = {r: calibrate(r.cfg, groups[0]) for r in todo}
    lanes, loads = pack(todo, seconds, len(groups))
    print(f"{n} device(s): {len(groups)} run(s) at a time, each over {per_run} device(s) "
          f"({len(seeds)} seeds)", flush=True)
    for group, lane, load in zip(groups, lanes, loads):
        if lane:
            names = ", ".join(f"{r.task}/{r.algo}" + (f" ~{seconds[r] / 60:.0f} min"
                                                      if r in seconds else "") for r in lane)
            cost = f" = ~{load / 60:.0f} min" if seconds else ""
            print(f"  devices {[d.id for d in group]}: {names}{cost}", flush=True)
    if seconds:
        print(f"estimated wall time: ~{max(loads) / 3600:.1f} h", flush=True)

    side_by_side = sum(1 for lane in lanes if lane) > 1
    stop = host.StopRequest() if side_by_side else None

    def run_lane(lane, group):
        train = train_fn or (lambda cfg, run_dir, resume: build.train(
            cfg, run_dir, resume=resume, progress=progress and not side_by_side,
            engine=build.build_engine(cfg, group), interrupt=stop))
        for r in lane:
            _train_one(r, runs, seeds, train, run_info)

    try:
        if not side_by_side:
            for lane, group in zip(lanes, groups):
                run_lane(lane, group)
            return runs
        from concurrent.futures import ThreadPoolExecutor

        with ThreadPoolExecutor(len(groups)) as pool:
            futures = [pool.submit(run_lane, lane, group) for lane, group in zip(lanes, groups)]
        stopped = [f.exception() for f in futures if f.exception() is not None]
        for e in stopped:  # an error other than Ctrl-C is the one to report
            if not isinstance(e, host.Interrupted):
                raise e
        if stopped:
            raise host.Interrupted(root, min(e.step for e in stopped))
    finally:
        if stop is not None:
            stop.restore()
    return runs


def _train_one(r: GridRun, runs, seeds, train, run_info) -> None:
    head = (f"[{runs.index(r) + 1}/{len(runs)}] {r.task} {r.algo} "
            f"(seeds {', '.join(map(str, seeds))})")
    print(f"{head}: {'resuming' if r.status == 'interrupted' else 'starting'} "
          f"in {r.run_dir}", flush=True)
    if r.status == "new":
        prepare_run_dir(r.cfg, run_info)
    t0 = time.perf_counter()
    train(r.cfg, r.run_dir, r.status == "interrupted")
    print(f"{head}: finished in {time.perf_counter() - t0:.0f} s", flush=True)


def pack(runs: list[GridRun], seconds: dict, lanes: int):
    """`runs` onto `lanes` device groups: longest first onto the least loaded group (with
    estimates), else in turn; each group keeps the plan's order (the reference first)."""
    out, loads = [[] for _ in range(lanes)], [0.0] * lanes
    order = sorted(runs, key=lambda r: -seconds[r]) if seconds else runs
    for i, r in enumerate(order):
        lane = loads.index(min(loads)) if seconds else i % lanes
        out[lane].append(r)
        loads[lane] += seconds.get(r, 0.0)
    return [sorted(lane, key=runs.index) for lane in out], loads


def calibrate(cfg: RunConfig, devices) -> float:
    """Estimated wall seconds of what remains of `cfg`'s run on `devices`: one chunk of
    each phase, the first two events and one evaluation, each timed on a fresh state after
    a first call that compiles it, scaled to the run's counts and to the steps left after
    its last checkpoint. Compile time is not counted (the programs compiled here are in the
    persistent cache when the run starts)."""
    import jax

    engine = build.build_engine(cfg, devices)
    seeds = list(cfg.seeds)

    def seconds(program) -> float:
        jax.block_until_ready(program(engine.init_seeds(seeds)))  # compile, warm up
        rs = engine.init_seeds(seeds)
        t0 = time.perf_counter()
        jax.block_until_ready(program(rs))
        return time.perf_counter() - t0

    total = 0.0
    starts = [p.start for p in engine.phases] + [cfg.steps]
    for start, end in zip(starts, starts[1:]):
        if start < min(end, cfg.steps):
            end = min(end, cfg.steps)
            length = min(cfg.chunk_steps, end - start)
            total += (end - start) / length * seconds(
                lambda rs: engine.run_chunk(rs, start, length))
    events = engine.event_steps()
    if events:
        each = [seconds(lambda rs: engine.run_event(rs, s)) for s in events[:2]]
        total += each[0] + (len(events) - 1) * each[-1]
    evaluations = -(-cfg.steps // cfg.eval_every)
    total += evaluations * seconds(lambda rs: engine.run_eval(rs, seeds, cfg.eval_every))
    done = latest_checkpoint_step(cfg.out) or 0
    return total * (cfg.steps - done) / cfg.steps
