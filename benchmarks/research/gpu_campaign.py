"""Issue 57's GPU campaign: α of the paper-size world model, in one command of at most
9 minutes on one H100-class GPU (results/research/gpu_campaign/README.md: how to run it, the
decision rules, what each part costs).

    python -m benchmarks.research.gpu_campaign --dataset PATH --out DIR    # on the GPU (paper)
    python -m benchmarks.research.gpu_campaign --scale tiny --dataset PATH # anywhere, in minutes
    python -m benchmarks.research.gpu_campaign --stage  # here: the dataset into .gpu/campaign/,
                                            # beside benchmarks.tooling.gpu_carry's wheels

Parts, in the order the time goes to them:
1. `world_model`: the lab's world model at the scale's size (paper: TWM's 10 layers x 256,
   4 heads, feed-forward 1024, batch 100, observation model 2 x 512 -> 32) trained on the
   lab dataset, `--seeds` seeds vmapped, with the lab's diagnostics at each checkpoint
   (paper: 1k = the end of the joint pre-training, 2.5k, 5k updates): world_model.csv (a row
   per seed and checkpoint), alpha_profile.csv (the positional profile).
2. `probe`: the critical-event probe (benchmarks/research/lab_probe.py), every-step reveal at
   delay 30 then 15, the same world-model size, 1500 updates each: probe_delay{D}.json, probe.csv.
3. `lab`: the lab's rounds (rules pebble, rvar, prior, prior~shift, positional,
   positional~shift, oracle~shift; 10 seeds; 25 and 100 labels) with part 1's world models
   (lab seed i reads world model i mod --seeds): run_lab's files in lab/.
The checkpoints before the last run before the probes, the last one after them.

It compiles part 1's update, times the first 100 updates, and sizes the rest to the time
left of `--budget-s`: an item whose estimate no longer fits is dropped, with a line saying so
(in the output and in campaign.json). A watchdog ends the process `--grace-s` after the
budget, whatever runs. Every file is written whole under a temporary name and then renamed
(the lab's own report files excepted), and campaign.json is rewritten after every step, so a
run cut short keeps what finished.
"""
from __future__ import annotations

import time

_T0 = time.perf_counter()  # the campaign's clock starts before the heavy imports

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import re  # noqa: E402
import shutil  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
from pathlib import Path  # noqa: E402

import tasks  # noqa: E402,F401  (sets XLA_FLAGS before jax is imported)
from benchmarks.research._gpu_campaign_record import (  # noqa: E402,F401  (tests read them too)
    POSITION_R2_MIN, REVEAL_ERROR_MAX, SKILL_MIN, T_STAR_OVER_UNIFORM_MIN, Campaign, Item,
    mean_over_seeds, plan, probe_row, probe_verdict, world_model_verdict, write_atomic,
    write_csv)

ROOT = Path(__file__).resolve().parents[2]
RESULTS = ROOT / "benchmarks" / "results" / "research" / "gpu_campaign"
STAGE = ROOT / ".gpu" / "campaign"  # git-ignored: carried to the GPU machine
DATASET_NAME = "cheetah_run_sac-reduced_50000steps_seed0.npz"

# appendix C.1 / Table 5 (TWM): PriorConfig's defaults, as FIELD=VALUE over the lab preset's
PAPER_WORLD_MODEL = dict(wm_embed=256, wm_layers=10, wm_heads=4, wm_head_dim=64, wm_ff=1024,
                         wm_obs_hidden=512, wm_obs_depth=2, wm_head_hidden=512,
                         wm_head_depth=4, wm_batch=100)
# the smoke preset's sizes: every code path in seconds on a CPU
TINY_WORLD_MODEL = dict(wm_embed=32, wm_layers=1, wm_heads=2, wm_head_dim=16, wm_ff=64,
                        wm_obs_hidden=64, wm_obs_depth=1, wm_head_hidden=64, wm_head_depth=1,
                        wm_batch=8)
LAB_RULES = ("pebble", "rvar", "prior", "prior~shift", "positional", "positional~shift",
             "oracle~shift")
PARTS = ("world_model", "probe", "lab")
SCALES = {
    "paper": dict(world_model=PAPER_WORLD_MODEL, tag="paper_wm", seeds=3, chunk=100,
                  pretrain=1000, checkpoints=(1000, 2500, 5000), timing_updates=100,
                  probe_steps=1500, probe_episodes=400, probe_delays=(30, 15),
                  lab_seeds=10, lab_budgets=(25, 100), segments=256,
                  # estimates before anything is measured (README: where they come from)
                  one_seed_ms=25.0, probe_fixed_s=45.0, diagnostics_s=25.0, lab_s=180.0,
                  reserve_s=10.0, grace_s=20.0),
    "tiny": dict(world_model=TINY_WORLD_MODEL, tag="tiny_wm", seeds=2, chunk=50,
                 pretrain=100, checkpoints=(100, 250, 500), timing_updates=100,
                 probe_steps=150, probe_episodes=40, probe_delays=(30, 15),
                 lab_seeds=2, lab_budgets=(10, 20), segments=256,
                 one_seed_ms=5.0, probe_fixed_s=8.0, diagnostics_s=5.0, lab_s=60.0,
                 reserve_s=1.0, grace_s=30.0),
}


def device_name() -> str:
    import jax

    d = jax.devices()[0]
    return f"{d.platform}:{d.device_kind}"


def stage(dataset: Path) -> int:
    """Copies the dataset into .gpu/campaign/ (beside `gpu_carry`'s wheels, carried with
    them) and says what to carry."""
    STAGE.mkdir(parents=True, exist_ok=True)
    target = STAGE / dataset.name
    shutil.copyfile(dataset, target)
    gpu = STAGE.parent
    size = sum(f.stat().st_size for f in gpu.rglob("*") if f.is_file()) / 2**20
    wheels = (gpu / "run.sh").exists()
    print(f"{target}; .gpu holds {size:.1f} MiB (a call carries 64 MiB of ignored paths)"
          + ("" if wheels else
             "; no wheels yet: run `python -m benchmarks.tooling.gpu_carry` first")
          + ". Carry ['.gpu'] and run the command of "
            "benchmarks/results/research/gpu_campaign/README.md")
    return 0


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--scale", default="paper", choices=list(SCALES))
    p.add_argument("--budget-s", type=float, default=540.0,
                   help="seconds of campaign time, start-up included (default 540)")
    p.add_argument("--grace-s", type=float, default=None,
                   help="the watchdog ends the process this long after the budget (0: no "
                        "watchdog; default: the scale's)")
    p.add_argument("--out", type=Path, default=None,
                   help="default benchmarks/results/research/gpu_campaign/<device name>/")
    p.add_argument("--dataset", type=Path, default=None,
                   help=f"a lab dataset .npz (default: the lab cache's {DATASET_NAME})")
    p.add_argument("--parts", nargs="+", default=list(PARTS), choices=PARTS)
    p.add_argument("--seeds", type=int, default=None, help="world models vmapped (part 1)")
    p.add_argument("--checkpoints", type=int, nargs="+", default=None,
                   help="updates at which part 1 reads its diagnostics (the scale's)")
    p.add_argument("--probe-steps", type=int, default=None, help="the scale's: 1500 / 150")
    p.add_argument("--lab-seeds", type=int, default=None, help="the scale's: 10 / 2")
    p.add_argument("--lab-budgets", type=int, nargs="+", default=None,
                   help="label budgets of part 3 (the scale's: 25 100 / 10 20)")
    p.add_argument("--stage", action="store_true",
                   help="copy the dataset into .gpu/campaign/ (to carry) and stop")
    args = p.parse_args(argv)
    if "lab" in args.parts and "world_model" not in args.parts:
        p.error("--parts lab reads part 1's world models: name world_model too")
    return args


def scale_settings(args) -> dict:
    """The scale's settings with the command line's overrides, checked."""
    s = dict(SCALES[args.scale])
    for key in ("seeds", "probe_steps", "lab_seeds", "lab_budgets"):
        if getattr(args, key) is not None:
            s[key] = getattr(args, key)
    if args.checkpoints:
        s["checkpoints"] = tuple(sorted(args.checkpoints))
        s["pretrain"] = min(s["pretrain"], s["checkpoints"][0])
    if any(c % s["chunk"] for c in s["checkpoints"]) or s["pretrain"] % s["chunk"]:
        raise SystemExit(f"checkpoints {s['checkpoints']} must be multiples of the "
                         f"{args.scale} chunk ({s['chunk']} updates)")
    return s


def main(argv=None) -> int:
    global _T0
    t0, _T0 = _T0, None  # the first campaign of a process counts its imports; later ones not
    t0 = t0 or time.perf_counter()
    args = parse_args(argv)
    from hprior_jax.lab.dataset import dataset_path

    dataset = args.dataset or (STAGE / DATASET_NAME if (STAGE / DATASET_NAME).exists()
                               else dataset_path("cheetah_run", 0, 50_000, "reduced"))
    if args.stage:
        return stage(dataset)
    s = scale_settings(args)
    device = device_name()
    out = args.out or RESULTS / re.sub(r"[^A-Za-z0-9_.-]+", "_", device)
    settings = [f"{k}={v}" for k, v in s["world_model"].items()]
    run = Campaign(out, args.budget_s, dict(
        device=device, scale=args.scale, budget_s=args.budget_s, parts=args.parts,
        dataset=str(dataset), seeds=s["seeds"], checkpoints=list(s["checkpoints"]),
        world_model_settings=settings, decision_rules=dict(
            world_model=f"position R² >= {POSITION_R2_MIN} at skill >= {SKILL_MIN}: the small "
                        "model is not why α is positional on cheetah",
            probe=f"α on t* > {T_STAR_OVER_UNIFORM_MIN}x uniform with reveal error < "
                  f"{REVEAL_ERROR_MAX} of predicting zero at delay 30: size restores the "
                  "look-back")), t0=t0)
    grace = s["grace_s"] if args.grace_s is None else args.grace_s
    timer = run.watchdog(args.budget_s + grace) if grace > 0 else None
    try:
        _Runner(run, s, args.parts, dataset, settings).run()
    finally:
        if timer is not None:
            timer.cancel()
    run.record["finished"] = True
    run.save()
    run.say(f"finished: {len(run.record['done'])} items done, "
            f"{len(run.record['dropped'])} dropped; files in {out}")
    return 0


class _Runner:
    """The items of one campaign (module docstring), planned and run in order."""

    def __init__(self, run: Campaign, s: dict, parts, dataset: Path, settings: list[str]):
        from hprior_jax.lab.dataset import Dataset
        from hprior_jax.lab.sweep import lab_config

        self.campaign, self.s, self.parts, self.settings = run, s, parts, settings
        self.data = data = Dataset.load(dataset)
        preset = data.info.get("preset", "reduced")
        cfg = lab_config(data, preset, LAB_RULES, seeds=s["lab_seeds"],
                         budgets=s["lab_budgets"], prior_settings=settings, tag=s["tag"])
        # the positional profile from as many training segments as part 1's (the lab's: 256)
        self.lab_cfg = dataclasses.replace(cfg, profile_segments=s["segments"])
        self.wcfg = wcfg = self.lab_cfg.world_model
        run.record |= dict(dataset_info=data.info, lab_preset=preset,
                           world_model_config=dataclasses.asdict(wcfg))
        run.say(f"device {run.record['device']}, budget {run.budget_s:.0f} s; world model "
                f"{wcfg.num_layers} x {wcfg.embed_dim}, batch {wcfg.batch_size}; dataset "
                f"{data.task} {data.train_obs.shape}")
        self.models, self.per_update = None, None
        self.one_seed = s["one_seed_ms"] / 1000  # s per update of one seed, until measured
        self.estimates = dict(diagnostics=s["diagnostics_s"], lab=s["lab_s"])
        self.probe_s = None
        self.wm_rows, self.profile_rows, self.profiles, self.probe_rows = [], [], None, []

    # -- the plan ---------------------------------------------------------------------
    def items(self) -> list[tuple[str, int | None, str | None]]:
        """(name, argument, the item it needs) in the order they get the time."""
        ckpts, order, prev = self.s["checkpoints"], [], None
        early, late = (ckpts[:-1], ckpts[-1:]) if len(ckpts) > 1 else (ckpts, ())
        checkpoint_items = []
        for c in ckpts if self.models is not None else ():
            checkpoint_items.append((f"world_model@{c}", c, prev))
            prev = f"world_model@{c}"
        order += checkpoint_items[:len(early)]
        if "probe" in self.parts:
            order += [(f"probe@{d}", d, None) for d in self.s["probe_delays"]]
        order += checkpoint_items[len(early):len(early) + len(late)]
        if "lab" in self.parts:
            order.append(("lab", None, f"world_model@{ckpts[0]}"))
        return order

    def estimate(self, name: str, arg, reached: int) -> float:
        if name.startswith("world_model"):
            return max(arg - reached, 0) * self.per_update + self.estimates["diagnostics"]
        if name.startswith("probe"):
            return self.probe_s or self.s["probe_steps"] * self.one_seed + self.s["probe_fixed_s"]
        return self.estimates["lab"]

    def reached(self) -> int:
        return self.models.updates if self.models is not None else 0

    # -- running ----------------------------------------------------------------------
    def run(self) -> None:
        run = self.campaign
        if "world_model" in self.parts:
            self.time_world_model()
        order, reached, items = self.items(), self.reached(), []
        for name, arg, needs in order:
            items.append(Item(name, self.estimate(name, arg, reached), needs))
            reached = arg if name.startswith("world_model") else reached
        run.record["plan"] = plan(items, run.left() - self.s["reserve_s"])
        run.say("plan: " + "; ".join(
            f"{p['item']} ~{p['estimate_s']:.0f} s" + ("" if p["admitted"] else " (dropped)")
            for p in run.record["plan"]))
        run.save()
        done = set()
        for name, arg, needs in order:
            if needs is not None and needs not in done:
                run.drop(name, f"needs {needs}, which did not run")
                continue
            if not run.fits(name, self.estimate(name, arg, self.reached()),
                            self.s["reserve_s"]):
                continue
            run.running, t0 = name, time.perf_counter()
            kind = name.split("@")[0]
            if getattr(self, kind)(arg) is False:
                continue
            done.add(name)
            run.done(name, time.perf_counter() - t0)
        run.running = "the end"

    def time_world_model(self) -> None:
        """Part 1's program compiled and its first updates timed."""
        from benchmarks.research._gpu_campaign_world_model import WorldModels

        run, s = self.campaign, self.s
        run.running = "world_model compile"
        self.models = WorldModels(self.data, self.wcfg, tuple(range(s["seeds"])),
                                  pretrain_steps=s["pretrain"], chunk=s["chunk"],
                                  query=self.lab_cfg.attention_query,
                                  profile_segments=s["segments"],
                                  diagnostic_segments=s["segments"])
        compile_s = self.models.compile()
        run.running = "world_model timing"
        timed = self.models.train(min(s["timing_updates"], s["checkpoints"][0]))
        self.per_update = timed["seconds"] / timed["updates"]
        # one seed alone costs at least 1/S of S vmapped (H200: 18 ms alone, 68 ms for 5)
        self.one_seed = self.per_update * min(1.0, 1.5 / s["seeds"])
        run.record["timing"] = dict(
            compile_s=round(compile_s, 1), updates=timed["updates"],
            ms_per_update=round(1000 * self.per_update, 2),
            ms_per_update_per_seed=round(1000 * self.per_update / s["seeds"], 2))
        run.say(f"part 1 update compiled in {compile_s:.1f} s; {timed['updates']} updates of "
                f"{s['seeds']} seeds: {1000 * self.per_update:.1f} ms each")
        run.done("world_model timing", compile_s + timed["seconds"])

    def world_model(self, checkpoint: int):
        """Trains on to `checkpoint` updates and reads the diagnostics there."""
        run, models, t0 = self.campaign, self.models, time.perf_counter()
        trained = models.train(checkpoint - models.updates, stop=lambda: run.left() <= 0)
        if models.updates < checkpoint:
            run.drop(f"world_model@{checkpoint}",
                     f"cut at {models.updates} updates: past the budget")
            return False
        if trained["updates"]:
            self.per_update = trained["seconds"] / trained["updates"]
        rows, self.profiles, self.estimates["diagnostics"] = models.diagnose()
        self.wm_rows += rows
        self.profile_rows += [dict(updates=checkpoint, seed=seed, position=t, alpha=float(a))
                              for seed, prof in zip(models.seeds, self.profiles)
                              for t, a in enumerate(prof)]
        write_csv(self.wm_rows, run.out / "world_model.csv")
        write_csv(self.profile_rows, run.out / "alpha_profile.csv")
        mean = mean_over_seeds(rows)
        verdict = world_model_verdict(mean)
        run.record.setdefault("world_model", {})[str(checkpoint)] = dict(
            mean=mean, seconds=round(time.perf_counter() - t0, 1), verdict=verdict)
        run.record["world_model_verdict"] = f"at {checkpoint} updates: {verdict}"
        run.say(f"world_model@{checkpoint}: {verdict}; residual vs |Δr| "
                f"{mean['alpha/residual_abs_dr_corr']:+.3f}, shuffle TV position "
                f"{mean['alpha/shuffle_tv_position']:.3f} content "
                f"{mean['alpha/shuffle_tv_content']:.3f}")

    def probe(self, delay: int):
        """The critical-event probe, every-step reveal at `delay`, this world model's size."""
        from benchmarks.research.lab_probe import ProbeConfig, run_probe

        run, t0 = self.campaign, time.perf_counter()
        cfg = ProbeConfig(episodes=self.s["probe_episodes"], steps=self.s["probe_steps"],
                          delay=delay, reveal="every_step", settings=tuple(self.settings))
        result = run_probe(cfg, seed=0)
        write_atomic(run.out / f"probe_delay{delay}.json", json.dumps(result, indent=2))
        row = probe_row(delay, result)
        self.probe_rows.append(row)
        write_csv(self.probe_rows, run.out / "probe.csv")
        self.probe_s = time.perf_counter() - t0  # the next probe's estimate
        run.record.setdefault("probe", {})[str(delay)] = dict(row, verdict=probe_verdict(row))
        if delay == 30:
            run.record["probe_verdict"] = "delay 30: " + probe_verdict(row)
        run.say(f"probe@{delay}: {probe_verdict(row)}")

    def lab(self, _=None):
        """run_lab with part 1's world models, handed to it through its world-model cache (a
        temporary folder): the lab config says the schedule they trained on."""
        from hprior_jax.lab import world_model_cache
        from hprior_jax.lab.contrasts import Contrast
        from hprior_jax.lab.sweep import run_lab

        run, models, tag = self.campaign, self.models, self.s["tag"]
        pre = min(self.s["pretrain"], models.updates)
        cfg = dataclasses.replace(self.lab_cfg, wm_pretrain_steps=pre,
                                  wm_steps=models.updates - pre, wm_order="joint")
        contrasts = [Contrast.parse(c) for c in (
            "oracle~shift:rvar",
            f"prior~shift[{tag}]:positional~shift[{tag}]@oracle~shift:rvar/2",
            f"prior~shift[{tag}]:prior[{tag}]", f"prior[{tag}]:positional[{tag}]")]
        run.record["lab"] = dict(
            seeds=len(cfg.seeds), budgets=list(cfg.budgets), rules=list(cfg.rules),
            world_model_updates=models.updates,
            world_models=f"lab seed i reads world model i mod {len(models.seeds)}")
        run.save()

        def progress(line: str) -> None:
            run.say("lab: " + line)
            if run.left() <= 0:
                raise _OutOfTime(line)

        previous = os.environ.get("HPRIOR_LAB_CACHE")
        with tempfile.TemporaryDirectory() as cache:
            os.environ["HPRIOR_LAB_CACHE"] = cache
            try:
                world_model_cache.save(world_model_cache.cache_path(cfg, self.data),
                                      models.seed_contexts(len(cfg.seeds), self.profiles))
                info = run_lab(self.data, cfg, run.out / "lab", progress=progress,
                               contrasts=contrasts)
                run.record["lab"] |= dict(
                    wall_seconds=info["wall_seconds"], compile_seconds=info["compile_seconds"],
                    world_models_loaded=info["world_model_cache"]["loaded"])
            except _OutOfTime as e:
                run.record["lab"]["cut"] = f"past the budget after: {e}"
                run.say(f"lab cut after: {e}")
            finally:
                if previous is None:
                    os.environ.pop("HPRIOR_LAB_CACHE", None)
                else:
                    os.environ["HPRIOR_LAB_CACHE"] = previous


class _OutOfTime(Exception):
    pass


if __name__ == "__main__":
    sys.exit(main())
