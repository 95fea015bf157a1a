"""benchmarks/research/gpu_campaign.py at its tiny scale on toy data: every part writes complete
files, the lab's rounds read part 1's world models, and a budget too small drops parts with a
message instead of crashing. In-process, without the watchdog (`--grace-s 0`)."""
import csv
import dataclasses
import json
import math
import time

import jax.numpy as jnp
import numpy as np
import pytest

from benchmarks.research import gpu_campaign as gc
from benchmarks.research._gpu_campaign_world_model import residual_vs_reward_change
from hprior_jax.lab.dataset import Dataset, heldout_pairs, split_episodes

# slow: the campaign at toy sizes takes minutes; run it (-m slow) before a GPU session
pytestmark = pytest.mark.slow

SEEDS, LAB_SEEDS, CHECKPOINTS = 2, 2, (50, 100, 150)


def toy_dataset(path) -> str:
    """toy_point-shaped episodes (the task the tests register; smoke preset: segments of
    10 steps) whose reward is a smooth function of the state."""
    rng = np.random.default_rng(0)
    episodes, length = 12, 20
    n = episodes * length
    act = rng.uniform(-1, 1, (n, 1)).astype(np.float32)
    pos = np.cumsum(0.1 * act[:, 0]).astype(np.float32)
    obs = np.stack([pos, act[:, 0]], 1).astype(np.float32)
    reward = -np.abs(pos - 0.5).astype(np.float32)
    (tr_o, te_o), (tr_a, te_a), (tr_r, te_r) = split_episodes(obs, act, reward, length)
    index, label = heldout_pairs(te_r, 10, 50, rng)
    Dataset(task="toy_point", segment_len=10, train_obs=tr_o, train_act=tr_a, train_reward=tr_r,
            test_obs=te_o, test_act=te_a, test_reward=te_r, pair_index=index, pair_label=label,
            info={"steps": n, "preset": "smoke"}).save(path)
    return str(path)


def read_csv(path):
    with open(path) as f:
        return list(csv.DictReader(f))


@pytest.fixture(scope="module")
def campaign(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("campaign")
    dataset = toy_dataset(tmp / "toy.npz")
    out = tmp / "out"
    # the campaign's clock starts at its module's import (a device session counts its imports);
    # pytest imported it when collecting, maybe many minutes of other tests ago
    gc._T0 = None
    t0 = time.perf_counter()
    assert gc.main(["--scale", "tiny", "--dataset", dataset, "--out", str(out), "--grace-s", "0",
                    "--seeds", str(SEEDS), "--checkpoints", *map(str, CHECKPOINTS),
                    "--probe-steps", "20", "--lab-seeds", str(LAB_SEEDS),
                    "--lab-budgets", "10"]) == 0
    return dataset, out, time.perf_counter() - t0


def test_every_part_runs_and_writes_complete_files(campaign):
    _, out, _ = campaign
    record = json.loads((out / "campaign.json").read_text())
    assert record["finished"] and not record["dropped"] and "hard_stop" not in record
    assert [d["item"] for d in record["done"]] == [
        "world_model timing", "world_model@50", "world_model@100", "probe@30", "probe@15",
        "world_model@150", "lab"]
    assert all(p["admitted"] for p in record["plan"])
    assert record["timing"]["updates"] == 50 and record["timing"]["ms_per_update"] > 0
    # part 1: a row per seed and checkpoint, every diagnostic a number
    rows = read_csv(out / "world_model.csv")
    assert [(int(r["updates"]), int(r["seed"])) for r in rows] == [
        (c, s) for c in CHECKPOINTS for s in range(SEEDS)]
    for name in ("wm/skill_vs_persistence", "alpha/position_r2", "alpha/shuffle_tv_position",
                 "alpha/shuffle_tv_content", "alpha/reward_corr", "alpha/residual_abs_dr_corr",
                 "alpha/residual_abs_dr_corr_within", "train_dyn_loss"):
        assert all(math.isfinite(float(r[name])) for r in rows), name
    assert set(record["world_model"]) == {str(c) for c in CHECKPOINTS}
    assert record["world_model_verdict"].startswith("at 150 updates")
    profile = read_csv(out / "alpha_profile.csv")
    assert len(profile) == len(CHECKPOINTS) * SEEDS * 10
    for c in CHECKPOINTS:
        for s in range(SEEDS):
            alpha = [float(r["alpha"]) for r in profile
                     if int(r["updates"]) == c and int(r["seed"]) == s]
            assert abs(sum(alpha) - 1) < 1e-4  # a mean of α's, each summing to 1
    # part 2: both delays, the every-step control, the numbers the decision reads
    probe = read_csv(out / "probe.csv")
    assert [int(r["delay"]) for r in probe] == [30, 15]
    for r in probe:
        assert float(r["reveal_mse_predict_zero"]) > 0 and float(r["uniform"]) == 1 / 50
    for delay in (30, 15):
        full = json.loads((out / f"probe_delay{delay}.json").read_text())
        assert full["config"]["reveal"] == "every_step" and full["config"]["steps"] == 20
    assert "delay 30" in record["probe_verdict"]
    # no temporary file left behind
    assert not list(out.rglob("*.tmp"))


def test_the_lab_rounds_read_part_1s_world_models(campaign):
    _, out, _ = campaign
    record = json.loads((out / "campaign.json").read_text())
    lab = out / "lab"
    info = json.loads((lab / "run_info.json").read_text())
    assert info["world_model_cache"]["loaded"] and record["lab"]["world_models_loaded"]
    assert info["config"]["wm_pretrain_steps"] + info["config"]["wm_steps"] == CHECKPOINTS[-1]
    results = read_csv(lab / "results.csv")
    tag = gc.SCALES["tiny"]["tag"]
    expected = {r if r in ("pebble", "rvar", "oracle~shift") else f"{r}[{tag}]"
                for r in gc.LAB_RULES}
    assert {r["rule"] for r in results} == expected
    assert len(results) == len(gc.LAB_RULES) * LAB_SEEDS
    # the lab's own diagnostics of its world models = part 1's at the last checkpoint (same
    # held-out segments): lab seed i read world model i mod SEEDS
    ours = {int(r["seed"]): r for r in read_csv(out / "world_model.csv")
            if int(r["updates"]) == CHECKPOINTS[-1]}
    for row in read_csv(lab / "diagnostics.csv"):
        mine = ours[int(row["seed"]) % SEEDS]
        for name in ("wm/skill_vs_persistence", "alpha/position_r2", "alpha/reward_corr"):
            assert float(row[name]) == pytest.approx(float(mine[name]), rel=1e-3, abs=1e-5)


def test_a_budget_too_small_drops_the_parts_with_a_message(campaign, tmp_path, capsys):
    dataset, _, _ = campaign
    out = tmp_path / "short"
    assert gc.main(["--scale", "tiny", "--dataset", dataset, "--out", str(out), "--grace-s", "0",
                    "--seeds", str(SEEDS), "--checkpoints", *map(str, CHECKPOINTS),
                    "--probe-steps", "20", "--budget-s", "0.5"]) == 0
    printed = capsys.readouterr().out
    record = json.loads((out / "campaign.json").read_text())
    assert record["finished"] and [d["item"] for d in record["done"]] == ["world_model timing"]
    dropped = [d["item"] for d in record["dropped"]]
    assert dropped == ["world_model@50", "world_model@100", "probe@30", "probe@15",
                       "world_model@150", "lab"]
    assert not any(p["admitted"] for p in record["plan"])
    assert printed.count("DROPPED") == len(dropped) and "left" in printed
    assert not (out / "world_model.csv").exists() and not (out / "lab").exists()


def test_the_plan_admits_in_priority_order_and_drops_what_needs_a_dropped_item():
    items = [gc.Item("a", 10), gc.Item("b", 30, needs="a"), gc.Item("c", 5),
             gc.Item("d", 10, needs="b"), gc.Item("e", 4)]
    out = gc.plan(items, 20)
    assert [p["admitted"] for p in out] == [True, False, True, False, True]
    assert "left" in out[1]["why"] and "needs b" in out[3]["why"]


def test_the_verdicts_follow_the_readmes_rules():
    mean = {"wm/skill_vs_persistence": 0.8, "alpha/position_r2": 0.96}
    assert "holds" in gc.world_model_verdict(mean)
    assert "does not hold" in gc.world_model_verdict(mean | {"alpha/position_r2": 0.9})
    assert "undecided" in gc.world_model_verdict(mean | {"wm/skill_vs_persistence": 0.6})
    row = {"alpha_t_star_over_uniform": 11.0, "reveal_error_over_predict_zero": 0.4}
    assert "holds" in gc.probe_verdict(row)
    assert "α does not show it" in gc.probe_verdict(row | {"alpha_t_star_over_uniform": 9.0})
    assert "not restored" in gc.probe_verdict(row | {"reveal_error_over_predict_zero": 0.6})


def test_the_paper_world_model_is_prior_configs_default_and_table_5():
    from hprior_jax.methods.prior import PriorConfig

    defaults = {f.name: f.default for f in dataclasses.fields(PriorConfig)}
    assert {k: defaults[k] for k in gc.PAPER_WORLD_MODEL} == gc.PAPER_WORLD_MODEL
    cfg = PriorConfig(lam=5.0, **gc.PAPER_WORLD_MODEL).world_model(17, 6, 50)
    assert (cfg.num_layers, cfg.num_heads, cfg.embed_dim, cfg.ff_dim, cfg.batch_size,
            cfg.obs_hidden, cfg.latent_dim) == (10, 4, 256, 1024, 100, (512, 512), 32)


def test_residual_against_reward_change_matches_numpy():
    rng = np.random.default_rng(1)
    alpha, reward = rng.random((6, 8)), rng.random((6, 8))
    reward[2] = 1.0  # constant: left out of the within-segment mean
    profile = alpha.mean(0)
    out = residual_vs_reward_change(jnp.asarray(alpha), jnp.asarray(profile), jnp.asarray(reward))
    res, dr = alpha[:, 1:] - profile[1:], np.abs(np.diff(reward, axis=1))
    assert float(out["alpha/residual_abs_dr_corr"]) == pytest.approx(
        np.corrcoef(res.ravel(), dr.ravel())[0, 1], abs=1e-5)
    within = [np.corrcoef(res[i], dr[i])[0, 1] for i in range(6) if i != 2]
    assert float(out["alpha/residual_abs_dr_corr_within"]) == pytest.approx(
        np.mean(within), abs=1e-5)


def test_the_watchdog_ends_the_process_and_records_where(tmp_path, monkeypatch):
    exits = []
    monkeypatch.setattr(gc.os, "_exit", exits.append)
    run = gc.Campaign(tmp_path, budget_s=1.0, record={}, t0=time.perf_counter())
    run.running = "probe@30"
    run.watchdog(0.05).join(timeout=5)
    assert exits == [3]
    assert "probe@30" in json.loads((tmp_path / "campaign.json").read_text())["hard_stop"]
