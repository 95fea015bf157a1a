"""`hprior reward-lab`: a task's dataset, every rule x budget x seed, metrics, report.

The lab takes the RL loop's own settings for the task from its `preset` (reward ensemble,
reward-update schedule, segment length, queries per round, λ, world-model sizes), so a rule
trains its reward exactly as in an RL run of that preset, only on fixed data.
"""
from __future__ import annotations

import dataclasses
import json
import resource
import time
from pathlib import Path

import numpy as np

from hprior_jax import dir_lock, presets
from hprior_jax.lab import resume as lab_resume
from hprior_jax.lab import world_model_cache
from hprior_jax.lab.config import (NO_PRIOR, UNLABELLED_SEGMENTS, WORLD_MODEL_CREDITS, GivenLabels,
                                   LabConfig, check_budgets)
from hprior_jax.lab.dataset import Dataset
from hprior_jax.lab.learn import Lab
from hprior_jax.lab.metrics import reward_quality, uniform_credit_ceiling
from hprior_jax.lab.npz_files import write_atomically
from hprior_jax.lab.report import write_report
from hprior_jax.lab.report_notes import report_notes, write_diagnostics
from hprior_jax.lab.rules import ABLATIONS, OWN_PROGRAM, default_rules, own_rule, rules
from hprior_jax.methods import registry
from hprior_jax.networks.reward_ensemble import RewardConfig
from hprior_jax.pbrl.preference import PreferenceConfig
from hprior_jax.pbrl.teacher import PRESETS as TEACHERS


SHIFTED = "~shift"  # RULE~shift: the rule with the shifted target form (prior/loss.py)


def parse_rule(name: str) -> tuple[str, float | None, bool]:
    """RULE[~shift][@LAMBDA] -> (RULE, LAMBDA as a float or None, whether the target form is
    the shifted one): prior@25 is PRIOR with its own λ, oracle~shift the oracle credit with
    the target α·(R̂ + T) − 1."""
    base, at, lam = name.partition("@")
    rule, tilde, form = base.partition("~")
    if tilde and "~" + form != SHIFTED:
        raise ValueError(f"rule {name!r}: the only target form to ask for is RULE{SHIFTED}")
    if not at:
        return rule, None, bool(tilde)
    try:
        return rule, float(lam), bool(tilde)
    except ValueError:
        raise ValueError(f"rule {name!r}: write RULE@LAMBDA with a number, e.g. prior@25")


def with_settings(config, settings: list[str] | None, refused: dict[str, str] | None = None):
    """`config` (a frozen dataclass) with FIELD=VALUE settings, each value read as its field's
    current type: the world-model ablations (`wm_layers=2`, `wm_update_steps=500`).
    `refused`: {field: why it may not be set here}."""
    fields = {f.name for f in dataclasses.fields(config)}
    changes = {}
    for setting in settings or ():
        name, eq, text = setting.partition("=")
        name = name.strip().replace("-", "_")
        if name in (refused or {}):
            raise ValueError(f"setting {setting!r}: {refused[name]}")
        if not eq or name not in fields:
            raise ValueError(f"setting {setting!r}: write FIELD=VALUE with FIELD one of "
                             f"{', '.join(sorted(fields))}")
        current = getattr(config, name)
        if isinstance(current, bool):
            if text.lower() not in ("true", "false"):
                raise ValueError(f"setting {setting!r}: {name} is true or false")
            changes[name] = text.lower() == "true"
        else:
            try:
                changes[name] = type(current)(text)
            except ValueError:
                raise ValueError(f"setting {setting!r}: {name} is a "
                                 f"{type(current).__name__}") from None
    return dataclasses.replace(config, **changes)  # __post_init__ checks the values


# PRIOR's two ablations are lab rules, so a lab can hold them beside PRIOR
AS_RULES = {"exclude_own_step": "a lab rule, not a setting: --rules ... prior_no_own_step",
            "clip_targets": "a lab rule, not a setting: --rules ... prior_clipped"}


def check_arguments(task: str, preset: str, rule_names, seeds: int, budgets, teacher: str,
                    prior_settings: list[str] | None = None,
                    queries_per_round: int | None = None) -> None:
    """The checks of `lab_config` that need no dataset, each naming its flag: `hprior
    reward-lab` runs them before it loads or builds one (a build takes minutes)."""
    if seeds < 1:
        raise ValueError(f"--seeds {seeds}: give the number of seeds, at least 1")
    if queries_per_round is not None and queries_per_round < 1:
        raise ValueError(f"--queries-per-round {queries_per_round}: give at least 1")
    try:
        check_budgets(budgets)
    except ValueError as e:
        raise ValueError(f"--budgets {' '.join(map(str, budgets))}: {e}") from None
    try:
        _parsed_rules(list(rule_names or default_rules()))
    except ValueError as e:
        raise ValueError(f"--rules: {e}") from None
    try:
        _check_teacher(teacher)
    except ValueError as e:
        raise ValueError(f"--teacher: {e}") from None
    if not prior_settings:
        return
    rl = presets.train_preset(task, registry.PROPOSED, preset)  # an unknown task: named
    try:
        with_settings(rl.prior, prior_settings, refused=AS_RULES)
    except ValueError as e:
        raise ValueError(f"--prior-set: {e}") from None


def _parsed_rules(rule_names: list[str]) -> list[tuple[str, float | None, bool]]:
    known = rules()
    parsed = [parse_rule(r) for r in rule_names]
    unknown = [r for r, *_ in parsed if r not in known]
    if unknown:
        raise ValueError(f"unknown lab rule {unknown}; available: {', '.join(known)}")
    if len(set(rule_names)) < len(rule_names):
        raise ValueError(f"a rule is named twice: {rule_names}")
    without_term = [r for r, lam, shifted in parsed if (lam is not None or shifted)
                    and known[r] in (*NO_PRIOR, OWN_PROGRAM)]
    if without_term:
        raise ValueError(f"{without_term} train no prior term: @LAMBDA or {SHIFTED} has "
                         "nothing to change")
    return parsed


def _check_teacher(teacher: str) -> None:
    if teacher not in TEACHERS:
        raise ValueError(f"unknown teacher {teacher!r}; available: {', '.join(TEACHERS)}")
    if TEACHERS[teacher].human:
        raise ValueError("the lab's teacher labels as the rounds go: a person labels the "
                         "dataset's pairs first (`hprior label --from-lab`), then "
                         "`hprior reward-lab --labels DIR` trains on those answers")


def lab_config(data: Dataset, preset: str = "reduced", rule_names=None, seeds=20,
               budgets=(25, 100, 400), queries_per_round: int | None = None,
               feed_type: str | None = None, teacher: str = "oracle", one_shot: bool = False,
               lam: float | None = None, prior_settings: list[str] | None = None,
               tag: str | None = None) -> LabConfig:
    """The lab's settings from the RL preset's. `prior_settings` (FIELD=VALUE) change the
    proposed method's config (world-model size, training amount, ...); the rules that read the
    world model are then reported as RULE[TAG] (TAG: `tag`, or the settings), so labs of
    several world models merge into one report (`hprior reward-lab report`)."""
    known = rules()
    rule_names = list(rule_names or default_rules())
    parsed = _parsed_rules(rule_names)
    _check_teacher(teacher)
    rl = presets.train_preset(data.task, registry.PROPOSED, preset)
    p, prior = rl.pebble, with_settings(rl.prior, prior_settings, refused=AS_RULES)
    # the bisimulation rule's λ_bisim and transitions from its method's preset
    bisim = next((presets.train_preset(data.task, r, preset).bisim
                  for r, *_ in parsed if known[r] == "bisimulation"), None)
    if p.segment_len != data.segment_len:
        raise ValueError(f"the dataset's segments are {data.segment_len} steps, the preset's "
                         f"{p.segment_len}")
    # the world-model steps of an RL run as long as the dataset: pre-training at the first
    # round, then `wm_update_steps` every `wm_every` env steps
    first_round = rl.num_seed_steps + p.num_unsup_steps
    updates = max(0, (data.info.get("steps", 0) - first_round) // prior.wm_every)
    tag = tag or ",".join(prior_settings or ())
    credits = tuple(known[r] for r, *_ in parsed)
    if tag:
        rule_names = [f"{r}[{tag}]" if c in WORLD_MODEL_CREDITS else r
                      for r, c in zip(rule_names, credits)]
    return LabConfig(
        rules=tuple(rule_names), credits=credits,
        lam=prior.lam if lam is None else lam,
        clips=tuple(r in ABLATIONS and ABLATIONS[r][1] for r, *_ in parsed),
        shifts=tuple(shifted for *_, shifted in parsed),
        unlabelled=tuple(r in ABLATIONS and ABLATIONS[r][2] for r, *_ in parsed),
        unlabelled_segments=prior.unlabelled_segments or UNLABELLED_SEGMENTS,
        rule_lams=tuple(lam for _, lam, _ in parsed), budgets=tuple(budgets),
        queries_per_round=queries_per_round or p.queries_per_round,
        feed_type=feed_type or p.feed_type, large_batch=p.large_batch, one_shot=one_shot,
        seeds=tuple(range(seeds)) if isinstance(seeds, int) else tuple(seeds),
        reward=RewardConfig(hidden_sizes=(p.reward_hidden,) * p.reward_depth,
                            ensemble_size=p.ensemble_size,
                            # with BISIM's rule every cell has BISIM's head: the others never
                            # read it, and their reward layers are the same with or without it
                            next_embedding_head="bisimulation" in credits),
        **({} if bisim is None else dict(bisim_lam=bisim.lam,
                                         bisim_transitions=bisim.transitions_per_pair)),
        discount=rl.sac.discount,
        own_rules=tuple((r, own_rule(r, presets.train_preset(data.task, r, preset)))
                        for r, *_ in parsed if known[r] == OWN_PROGRAM),
        preference=PreferenceConfig(batch_size=p.reward_batch, max_epochs=p.reward_epochs,
                                    lr=p.reward_lr),
        teacher=TEACHERS[teacher],
        world_model=prior.world_model(data.train_obs.shape[-1], data.train_act.shape[-1],
                                      data.segment_len),
        wm_pretrain_steps=prior.wm_pretrain_steps, wm_steps=updates * prior.wm_update_steps,
        wm_order=prior.wm_order, wm_normalize_obs=prior.wm_normalize_obs,
        attention_query=prior.attention_query)


def score(rows: list[dict], data: Dataset) -> list[dict]:
    """Lab rows with predictions -> rows of (task, rule, budget, seed, the held-out metrics,
    the round's training metrics); predictions dropped."""
    out = []
    for row in rows:
        row = dict(row)
        quality = reward_quality(row.pop("prediction"), data.test_reward, data.pair_index,
                                 data.pair_label, data.segment_len)
        head = {k: row.pop(k) for k in ("rule", "budget", "seed")}
        out.append({"task": data.task, **head, **quality, **row})
    return out


def save_predictions(path: Path, rows: list[dict]) -> Path:
    """Every cell's held-out predictions r̂ [E, L] (compressed, float32) beside its seed,
    rule and budget, so a later metric needs no retraining; written whole, then renamed."""
    return write_atomically(path, dict(
        seed=np.asarray([r["seed"] for r in rows]), rule=np.asarray([r["rule"] for r in rows]),
        budget=np.asarray([r["budget"] for r in rows]),
        prediction=np.stack([r["prediction"] for r in rows]).astype(np.float32)),
        compressed=True)


def run_lab(data: Dataset, cfg: LabConfig, out: Path, progress=print,
            given: GivenLabels | None = None, reuse_world_models: bool = True,
            contrasts=(), resume: bool = False, checkpoint_every_s: float = 600.0) -> dict:
    """Runs the sweep; writes OUT/run_info.json (time, memory, settings), the report
    (results.csv with every (rule, budget, seed), summary.csv, report.md, PNGs; `contrasts`:
    the pre-registered ones, experiments.contrasts) and predictions.npz (every cell's
    held-out r̂). The report is rewritten as each budget is reached, so a stopped lab keeps
    the budgets it reached.
    `given`: labels given beforehand (a person's) instead of the teacher's.
    `reuse_world_models`: the seeds' world models come from the lab cache when a lab of the
    same dataset, seeds and world-model settings trained them (`world_model_cache`), and
    are kept there when trained here.
    `resume`: go on from the state a stopped lab left in OUT (OUT/lab_state.npz, written
    between rounds at most `checkpoint_every_s` apart and at every budget, removed when the
    lab ends); without it such a state is an error, not overwritten. One process at a time
    writes OUT."""
    out = Path(out)
    checkpoints = lab_resume.Checkpoints(out / lab_resume.STATE_NAME,
                                         lab_resume.fingerprint(cfg, data, given),
                                         checkpoint_every_s)
    with dir_lock.DirLock(out):
        if resume:
            checkpoints.check()  # another lab's state: refused before any work
        elif checkpoints.path.exists():
            raise FileExistsError(f"{out} holds a lab that stopped before its end: add "
                                  "--resume to go on from where it stopped, or choose "
                                  "another --out")
        info = _run(data, cfg, out, progress, given, reuse_world_models, contrasts,
                    checkpoints)
        checkpoints.discard()
    return info


def _run(data, cfg, out, progress, given, reuse_world_models, contrasts, checkpoints) -> dict:
    """run_lab's work, in OUT locked."""
    t0 = time.perf_counter()
    cached = world_model_cache.cache_path(cfg, data) if (
        reuse_world_models and cfg.needs_world_model) else None
    lab = Lab(cfg, data, given, world_model_cache=cached)
    rows, predicted = [], []
    ceiling = uniform_credit_ceiling(data.test_reward, data.segment_len)
    title = f"Reward-learning lab: {data.task}"

    def report_budget(reached: list[dict]) -> None:
        predicted.extend(reached)
        save_predictions(out / "predictions.npz", predicted)
        rows.extend(score(reached, data))
        write_report(rows, out, title=title, contrasts=contrasts,
                     notes=report_notes(lab.diagnostics, ceiling, data.segment_len))

    lab.run(progress, on_budget=report_budget, checkpoints=checkpoints)
    wall = lab.wall_before + time.perf_counter() - t0
    cells = len(cfg.seeds) * len(cfg.rules)
    info = {
        "task": data.task, "dataset": data.info, "dataset_digest": data.digest(),
        "wall_seconds": round(wall, 1),
        "seconds": {k: round(v, 1) for k, v in lab.seconds.items()},
        "compile_seconds": {k: round(v, 1) for k, v in lab.compile_seconds.items()},
        "world_model_cache": None if cached is None else dict(
            path=str(cached), loaded=lab.world_model_loaded),
        "cells": cells, "adam_steps": lab.adam_steps,
        "uniform_credit_ceiling": ceiling, "segment_len": data.segment_len,
        "ms_per_adam_step_per_cell": round(1000 * lab.seconds.get("rounds", 0.0)
                                           / max(lab.adam_steps * cells, 1), 2),
        "peak_rss_gib": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20, 2),
        "config": json.loads(json.dumps(dataclasses.asdict(cfg), default=str)),
    }
    if lab.diagnostics:  # the world model's, per seed (prior.diagnostics)
        names = [k for k in lab.diagnostics[0] if k != "seed"]
        info["world_model_diagnostics_mean"] = {
            k: round(float(np.mean([d[k] for d in lab.diagnostics])), 5) for k in names}
        write_diagnostics(out / "diagnostics.csv", lab.diagnostics)
    (out / "run_info.json").write_text(json.dumps(info, indent=2))
    return info
