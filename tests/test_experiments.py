"""Normalized scores, the paired t-test, the report on a synthetic results directory, and
grid skip/resume on the toy task."""
import csv
import json

import numpy as np
import pytest
from scipy import stats

from hprior_jax.runs.build import train
from hprior_jax.runs.run_dir import prepare_run_dir
from hprior_jax.agents.sac import SACConfig
from hprior_jax.experiments import grid, report
from hprior_jax.experiments.scores import normalized_score, reference_curve, task_scores
from hprior_jax.statistics import paired_t_test


def _curve(steps, values):
    return np.asarray(steps), np.asarray(values, float)


def test_normalized_score_by_hand():
    ours = _curve([5, 10, 15, 20], [1.0, 2.0, 3.0, 4.0])
    sac = _curve([5, 10, 15, 20], [2.0, 0.0, 6.0, 2.0])
    # after step 5; step 10 has no ratio (SAC 0): mean(3/6, 4/2)
    assert normalized_score(ours, sac, after_step=5) == (pytest.approx(1.25), 2)
    # every step, the one with SAC 0 left out: mean(1/2, 3/6, 4/2)
    assert normalized_score(ours, sac) == (pytest.approx(1.0), 3)
    assert normalized_score(ours, sac, "ratio-of-means", after_step=5) == (
        pytest.approx(9 / 8), 3)
    assert normalized_score(ours, sac, min_reference=2.5) == (pytest.approx(0.5), 1)
    assert np.isnan(normalized_score(ours, _curve([7], [1.0]))[0])
    with pytest.raises(ValueError, match="mean-of-ratios"):
        normalized_score(ours, sac, "median")


def test_reference_is_the_seed_mean_at_shared_steps_and_pairing_by_seed():
    sac = {1: _curve([10, 20, 30], [2.0, 4.0, 9.0]), 2: _curve([10, 20], [4.0, 8.0])}
    steps, mean = reference_curve(sac)
    assert steps.tolist() == [10, 20] and mean.tolist() == [3.0, 6.0]
    pbrl = {1: _curve([10, 20], [3.0, 3.0]), 2: _curve([10, 20], [4.0, 4.0])}
    shared = task_scores(pbrl, sac)
    assert shared[1] == (pytest.approx((1 + 0.5) / 2), 2)
    paired = task_scores(pbrl, sac, pair_by_seed=True)
    assert paired[1] == (pytest.approx((1.5 + 0.75) / 2), 2)
    assert paired[2] == (pytest.approx((1 + 0.5) / 2), 2)
    with pytest.raises(ValueError, match="same --seeds"):
        task_scores({3: pbrl[1]}, sac, pair_by_seed=True)


def test_paired_t_test_by_hand_and_against_scipy():
    baseline, prior = [0.4, 0.6, 0.5], [0.5, 0.9, 0.6]
    # d = [-0.1, -0.3, -0.1]: mean -1/6, sd 0.11547, se 1/15 -> t = -2.5, df 2;
    # for df 2 the t survival function is (1 - t / sqrt(t^2 + 2)) / 2
    t, p, n = paired_t_test(baseline, prior)
    assert n == 3 and t == pytest.approx(-2.5)
    assert p == pytest.approx(1 - 2.5 / np.sqrt(8.25))
    ref = stats.ttest_rel(baseline, prior)
    assert (t, p) == (pytest.approx(ref.statistic), pytest.approx(ref.pvalue))
    # NaN pairs are dropped; one pair is not a test
    t, p, n = paired_t_test([0.4, np.nan, 0.5], [0.5, 0.9, np.nan])
    assert n == 1 and np.isnan(t) and np.isnan(p)
    with pytest.raises(ValueError, match="differ in length"):
        paired_t_test([1.0], [1.0, 2.0])


def _fake_run(root, task, algo, evals, success=None, rounds=(), num_seed_steps=5):
    """A run directory as `hprior train` writes it: config.json, eval.csv, metrics.jsonl."""
    d = root / task / algo
    d.mkdir(parents=True)
    (d / "config.json").write_text(json.dumps(dict(task=task, algo=algo,
                                                   num_seed_steps=num_seed_steps)))
    with (d / "eval.csv").open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["step", "seed", "true_return", "success"])
        for seed, values in evals.items():
            for i, v in enumerate(values):
                s = "" if success is None else success[seed][i]
                w.writerow([5 * (i + 1), seed, v, s])
    lines = [dict(step=step, seed=seed, **{"feedback/total_labeled": n, "reward/true_corr": r})
             for step, seed, n, r in rounds]
    (d / "metrics.jsonl").write_text("".join(json.dumps(x) + "\n" for x in lines))
    return d


def test_report_on_a_synthetic_results_directory(tmp_path):
    # DMC-like task (returns); evaluations at 5 (random phase of SAC: left out), 10, 15
    _fake_run(tmp_path, "walk", "sac", {1: [0.1, 10, 20], 2: [0.1, 30, 40]})
    _fake_run(tmp_path, "walk", "pebble", {1: [5, 10, 15], 2: [5, 30, 15]},
              rounds=[(10, 1, 20, 0.3), (10, 2, 20, 0.5)])
    _fake_run(tmp_path, "walk", "prior", {1: [5, 30, 30], 2: [5, 20, 45]},
              rounds=[(10, 1, 20, 0.6), (10, 2, 20, 0.7)])
    _fake_run(tmp_path, "walk", "rvar", {1: [5, 20, 30], 2: [5, 20, 30]})
    _fake_run(tmp_path, "walk", "prior_nrp", {1: [5, 20, 30], 2: [5, 20, 30]})
    # MetaWorld-like task (success); SAC succeeds only from the third evaluation
    sac_s = {1: [0, 0, 1.0, 0.5], 2: [0, 0, 0.0, 0.5]}
    _fake_run(tmp_path, "open", "sac", {s: [0] * 4 for s in sac_s}, success=sac_s)
    peb_s = {1: [0, 1, 0.25, 0.5], 2: [0, 0, 0.25, 0.0]}
    _fake_run(tmp_path, "open", "pebble", {s: [0] * 4 for s in peb_s}, success=peb_s)
    pri_s = {1: [0, 0, 0.5, 0.5], 2: [0, 0, 0.5, 0.25]}
    _fake_run(tmp_path, "open", "prior", {s: [0] * 4 for s in pri_s}, success=pri_s)

    md = report.make_report(tmp_path, attention=False)
    out = md.parent
    rows = {(r["task"], r["algo"], int(r["seed"])): float(r["score"])
            for r in csv.DictReader((out / "scores.csv").open())}
    # walk: SAC mean at 10, 15 = 20, 30
    assert rows[("walk", "pebble", 1)] == pytest.approx((10 / 20 + 15 / 30) / 2)
    assert rows[("walk", "prior", 2)] == pytest.approx((20 / 20 + 45 / 30) / 2)
    # open: SAC mean success at 10, 15, 20 = 0, 0.5, 0.5; step 10 has no ratio
    assert rows[("open", "pebble", 1)] == pytest.approx((0.25 / 0.5 + 0.5 / 0.5) / 2)
    assert rows[("open", "prior", 2)] == pytest.approx((0.5 / 0.5 + 0.25 / 0.5) / 2)
    table = {r["task"]: r for r in csv.DictReader((out / "table_true_return.csv").open())}
    assert float(table["walk"]["prior"]) == pytest.approx((1.25 + 1.25) / 2)
    assert float(table["walk"]["pebble"]) == pytest.approx((0.5 + 1.0) / 2)
    assert (out / "table_success.csv").exists()
    text = md.read_text()
    assert "Table 6: normalized success rate" in text and "Table 7: normalized returns" in text
    assert text.index("Table 6") < text.index("Table 7")
    # columns in the registry's order: PRIOR, PEBBLE, then its variants
    assert "| Env/Algorithm | PRIOR | PEBBLE | PRIOR_NRP | RVAR |" in text
    assert "| walk | 1.25 | 0.75 | 1.00 | 1.00 |" in text
    # one task per metric: the per-task t-test has one pair, so no t; per seed it has two
    tests = list(csv.DictReader((out / "t_tests.csv").open()))
    assert {(r["metric"], r["baseline"], r["pairs"]) for r in tests} == {
        ("true_return", "pebble", "1"), ("true_return", "prior_nrp", "1"),
        ("true_return", "rvar", "1"), ("success", "pebble", "1"),
        ("success", "prior_nrp", "0"), ("success", "rvar", "0")}  # no MetaWorld runs of those
    by_seed = report.t_tests(report.compute_scores(report.discover(tmp_path), "mean-of-ratios",
                                                   0.0, False), pair_by="seed")
    walk = next(r for r in by_seed if r["metric"] == "true_return")
    ref = stats.ttest_rel([0.5, 1.0], [1.25, 1.25])
    assert walk["pairs"] == 2 and walk["t"] == pytest.approx(ref.statistic)
    corr = list(csv.DictReader((out / "reward_correlation.csv").open()))
    assert len(corr) == 4 and {float(r["true_corr"]) for r in corr} == {0.3, 0.5, 0.6, 0.7}
    for task in ("walk", "open"):
        for axis in ("steps", "labels"):
            assert (out / "curves" / f"{task}_vs_{axis}.png").stat().st_size > 0


def test_report_says_how_many_seeds_each_column_has_when_they_differ(tmp_path):
    _fake_run(tmp_path, "walk", "sac", {1: [0.1, 10, 20], 2: [0.1, 30, 40]})
    _fake_run(tmp_path, "walk", "prior", {1: [5, 30, 30], 2: [5, 20, 45]})
    _fake_run(tmp_path, "walk", "surf", {1: [5, 20, 30]})
    text = report.make_report(tmp_path, attention=False).read_text()
    assert "Mean over each column's seeds" in text and "| seeds | 2 | 1 |" in text
    (tmp_path / "report").rename(tmp_path / "old")
    (tmp_path / "walk" / "surf").rename(tmp_path / "surf_gone")
    text = report.make_report(tmp_path, attention=False).read_text()
    assert "Mean over seeds 1, 2 of" in text and "| seeds |" not in text


def test_labels_used_counts_rounds_before_the_evaluation():
    rounds = [(10, 20.0), (20, 40.0)]
    assert [report._labels_used(rounds, s) for s in (5, 10, 15, 20, 25)] == [0, 0, 20, 20, 40]


def test_report_names_the_fix_for_an_empty_directory(tmp_path):
    with pytest.raises(FileNotFoundError, match="hprior grid"):
        report.make_report(tmp_path, attention=False)


TINY = dict(steps=80, num_seed_steps=20, chunk_steps=20, eval_every=40, checkpoint_every=40,
            num_eval_episodes=2, sac=SACConfig(hidden_dim=16, hidden_depth=1, batch_size=8))


def test_grid_skips_complete_runs_and_resumes_interrupted_ones(tmp_path):
    seeds = (1, 2)
    # an interrupted run: 1 of 4 chunks, checkpointed at the stop
    cfg = grid.run_config(tmp_path, "toy_point", "sac", seeds, "smoke", TINY)
    train(cfg, prepare_run_dir(cfg), progress=False, max_chunks=1)
    assert grid.run_status(cfg) == "interrupted"

    calls = []

    def recording_train(cfg, run_dir, resume):
        calls.append((cfg.task, cfg.algo, resume))
        train(cfg, run_dir, resume=resume, progress=False)

    info = {"command": "hprior grid ...", "git_commit": "abc"}
    runs = grid.run_grid(tmp_path, ["toy_point", "toy_scaled"], ["sac"], seeds, "smoke", TINY,
                         train_fn=recording_train, run_info=info)
    # a new run records what produced it (the resumed one keeps its own config)
    assert json.loads((tmp_path / "toy_scaled" / "sac" / "config.json").read_text())[
        "run_info"] == info
    assert [(r.task, r.status) for r in runs] == [("toy_point", "interrupted"),
                                                  ("toy_scaled", "new")]
    assert calls == [("toy_point", "sac", True), ("toy_scaled", "sac", False)]
    rows = list(csv.DictReader((tmp_path / "toy_point" / "sac" / "eval.csv").open()))
    assert sorted((int(r["step"]), int(r["seed"])) for r in rows) == [
        (40, 1), (40, 2), (80, 1), (80, 2)]
    assert json.loads((tmp_path / "grid.json").read_text())["seeds"] == [1, 2]

    calls.clear()
    runs = grid.run_grid(tmp_path, ["toy_point", "toy_scaled"], ["sac"], seeds, "smoke", TINY,
                         train_fn=recording_train)
    assert calls == [] and {r.status for r in runs} == {"complete"}

    with pytest.raises(ValueError, match="different configuration.*steps"):
        grid.run_grid(tmp_path, ["toy_point"], ["sac"], seeds, "smoke", {**TINY, "steps": 100},
                      train_fn=recording_train)
    with pytest.raises(ValueError, match="unknown algorithm"):
        grid.plan(tmp_path, ["toy_point"], ["ppo"], seeds)


def test_cli_grid_and_report_errors_name_the_fix(tmp_path, capsys):
    from hprior_jax import cli

    assert cli.main(["grid", "--tasks", "toy_point", "--algos", "ppo",
                     "--out", str(tmp_path / "g")]) == 2
    assert "available: sac" in capsys.readouterr().err
    assert cli.main(["report", str(tmp_path / "empty")]) == 2
    assert "hprior grid" in capsys.readouterr().err
    _fake_run(tmp_path / "r", "walk", "sac", {1: [0.1, 10, 20]})
    _fake_run(tmp_path / "r", "walk", "pebble", {1: [5, 5, 10]})
    assert cli.main(["report", str(tmp_path / "r"), "--no-attention"]) == 0
    assert "| walk | 0.50 |" in capsys.readouterr().out


def test_compare_runs_pairs_seeds_like_numpy_and_scipy(tmp_path):
    """B − A per seed on the final evaluation and on the mean after the seed steps; the
    difference, its t-interval and p equal a direct computation (scipy's ttest_rel)."""
    from hprior_jax.experiments import compare_runs

    rng = np.random.default_rng(0)
    seeds, steps = [1, 2, 3, 4, 5], [5000, 10000, 15000]
    values = {run: rng.normal(100, 20, (len(seeds), len(steps))) for run in ("a", "b")}
    for run, v in values.items():
        (tmp_path / run).mkdir()
        rows = ["step,seed,true_return,success"] + [
            f"{st},{s},{v[i, j]},"
            for j, st in enumerate(steps) for i, s in enumerate(seeds)]
        (tmp_path / run / "eval.csv").write_text("\n".join(rows) + "\n")
    assert compare_runs.main([str(tmp_path / "a"), str(tmp_path / "b"),
                              "--out", str(tmp_path / "cmp")]) == 0
    _, summary = compare_runs.compare(tmp_path / "a", tmp_path / "b")
    for row, (a, b) in zip(summary, [(values["a"][:, -1], values["b"][:, -1]),
                                     (values["a"][:, 1:].mean(1), values["b"][:, 1:].mean(1))]):
        d = b - a
        assert row["n"] == 5 and row["diff"] == pytest.approx(d.mean())
        half = stats.t.ppf(0.975, 4) * d.std(ddof=1) / np.sqrt(5)
        assert (row["diff_lo"], row["diff_hi"]) == pytest.approx((d.mean() - half, d.mean() + half))
        assert row["p"] == pytest.approx(stats.ttest_rel(b, a).pvalue)
        assert 0 < row["mde80"] < np.inf
    assert {p.name for p in (tmp_path / "cmp").iterdir()} == {"per_seed.csv", "summary.csv",
                                                               "report.md"}
