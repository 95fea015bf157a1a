"""Reward-learning lab report: intervals, paired tests and power against scipy computed
independently here, and the written report on a small synthetic lab."""
import csv
import math

import numpy as np
import pytest
from scipy import stats

from hprior_jax.commands.reward_lab import report as report_command
from hprior_jax.lab import report as lab_report
from hprior_jax.lab.report import METRICS, summarize, write_report
from hprior_jax.statistics import (mean_ci, minimum_detectable_effect, paired_comparison,
                                   paired_power)


def _power_by_nct(effects, sd, n, alpha=0.05):
    """Two-sided paired t-test power, written out here so the module is not its own check."""
    df = n - 1
    critical = stats.t.ppf(1 - alpha / 2, df)
    noncentrality = np.asarray(effects) * math.sqrt(n) / sd
    return stats.nct.sf(critical, df, noncentrality) + stats.nct.cdf(-critical, df, noncentrality)


def test_mean_ci_is_the_t_interval_without_nans():
    values = [0.61, 0.72, float("nan"), 0.58, 0.69, 0.75]
    kept = np.array([0.61, 0.72, 0.58, 0.69, 0.75])
    for level in (0.95, 0.9):
        mean, lo, hi, n = mean_ci(values, level)
        want_lo, want_hi = stats.t.interval(level, 4, loc=kept.mean(), scale=stats.sem(kept))
        assert n == 5
        assert mean == pytest.approx(kept.mean(), abs=1e-12)
        assert (lo, hi) == pytest.approx((want_lo, want_hi), abs=1e-12)
    mean, lo, hi, n = mean_ci([0.4, float("nan")])
    assert (mean, n) == (0.4, 1) and math.isnan(lo) and math.isnan(hi)


def test_paired_comparison_uses_common_non_nan_seeds():
    reference = {0: 0.50, 1: 0.60, 2: 0.55, 3: 0.70, 4: 0.65, 5: float("nan"), 9: 0.10}
    other = {0: 0.55, 1: 0.62, 2: 0.60, 3: 0.71, 4: 0.70, 5: 0.80, 7: 0.90}
    ref, oth = np.array([0.50, 0.60, 0.55, 0.70, 0.65]), np.array([0.55, 0.62, 0.60, 0.71, 0.70])
    d = oth - ref
    lo, hi = stats.t.interval(0.95, 4, loc=d.mean(), scale=stats.sem(d))

    got = paired_comparison(reference, other)

    assert got["n"] == 5
    assert got["diff"] == pytest.approx(d.mean(), abs=1e-12)
    assert (got["diff_lo"], got["diff_hi"]) == pytest.approx((lo, hi), abs=1e-12)
    assert got["p"] == pytest.approx(stats.ttest_rel(oth, ref).pvalue, abs=1e-12)
    assert got["sd"] == pytest.approx(d.std(ddof=1), abs=1e-12)
    assert got["mde80"] == pytest.approx(minimum_detectable_effect(d.std(ddof=1), 5), rel=1e-9)


def test_power_is_alpha_at_zero_and_target_at_mde_and_grows_with_n_and_effect():
    sd, n = 0.1, 10
    mde = minimum_detectable_effect(sd, n)
    assert paired_power(mde, sd, n) == pytest.approx(0.80, abs=1e-3)
    assert paired_power(-mde, sd, n) == pytest.approx(0.80, abs=1e-3)  # two-sided
    assert paired_power(0.0, sd, n) == pytest.approx(0.05, abs=1e-3)
    assert paired_power(0.0, sd, n, alpha=0.01) == pytest.approx(0.01, abs=1e-3)
    by_n = [paired_power(0.05, sd, m) for m in (3, 5, 10, 20, 40)]
    by_effect = [paired_power(e, sd, n) for e in (0.01, 0.03, 0.05, 0.1)]
    assert np.all(np.diff(by_n) > 0) and np.all(np.diff(by_effect) > 0)
    assert math.isnan(paired_power(0.05, sd, 1)) and math.isnan(minimum_detectable_effect(0.0, n))


def test_mde80_matches_brute_force_search_and_exceeds_normal_approximation():
    sd, n, step = 0.2, 8, 1e-5
    effects = np.arange(0.0, 0.5, step)
    brute = effects[np.argmax(_power_by_nct(effects, sd, n) >= 0.80)]

    mde = minimum_detectable_effect(sd, n)

    assert brute - step <= mde <= brute
    normal_approximation = (stats.norm.ppf(0.975) + stats.norm.ppf(0.80)) * sd / math.sqrt(n)
    assert mde > 1.1 * normal_approximation  # with 7 df the t-test needs clearly more


BUDGETS = (25, 100, 400)
SEED_NOISE = (0.0, 0.02, -0.01, 0.03, -0.02)  # shared by the rules: seeds are paired
SMALL_NOISE = (0.004, -0.004, 0.008, -0.008, 0.0)  # sums to 0: "same" equals pebble on average


def _synthetic_rows():
    """One task, rules appearing as better, pebble, same (pebble must still come first)."""
    rows = []
    for rule, shift in (("better", 0.1), ("pebble", 0.0), ("same", 0.0)):
        for budget in BUDGETS:
            for seed in range(5):
                base = 0.5 + 0.05 * math.log(budget / 25) + SEED_NOISE[seed] + shift
                jitter = SMALL_NOISE[seed] if rule != "pebble" else 0.0
                row = {"task": "toy", "rule": rule, "budget": budget, "seed": seed,
                       "wall_s": 12.5, "note": "synthetic"}
                for k, metric in enumerate(METRICS):
                    row[metric] = base + jitter - 0.05 * k
                rows.append(row)
    # A NaN pebble value at the seed whose jitter is 0: "same" stays equal to pebble on average.
    next(r for r in rows if (r["rule"], r["budget"], r["seed"]) == ("pebble", 25, 4)
         )["kendall_tau"] = float("nan")
    return rows


def test_summarize_orders_and_compares_only_against_pebble():
    summary = summarize(_synthetic_rows())

    assert len(summary) == len(METRICS) * len(BUDGETS) * 3
    keys = [(e["metric"], e["budget"], e["rule"]) for e in summary]
    rules = ("pebble", "better", "same")
    assert keys == [(m, b, r) for m in METRICS for b in BUDGETS for r in rules]
    assert all(("vs_pebble_p" in e) == (e["rule"] != "pebble") for e in summary)
    nan_cell = next(e for e in summary if (e["metric"], e["budget"], e["rule"])
                    == ("kendall_tau", 25, "better"))
    assert nan_cell["n"] == 5 and nan_cell["vs_pebble_n"] == 4
    assert nan_cell["vs_pebble_diff"] == pytest.approx(0.1, abs=1e-9)


def test_summarize_rejects_a_repeated_seed():
    rows = _synthetic_rows()
    with pytest.raises(ValueError, match="two rows"):
        summarize(rows + [dict(rows[0])])


def test_write_report_and_the_report_command_regenerate_it(tmp_path):
    out = tmp_path / "lab"
    report = write_report(_synthetic_rows(), out)

    assert report == out / "report.md"
    text = report.read_text()
    assert "5 seeds per (task, rule, budget)" in text
    for metric in METRICS:
        assert (out / f"toy_{metric}.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    better = [line for line in text.splitlines() if line.startswith("- better − pebble at")]
    same = [line for line in text.splitlines() if line.startswith("- same − pebble at")]
    assert len(better) == len(same) == len(METRICS) * len(BUDGETS)
    assert all("better higher than pebble" in line for line in better)
    assert all("no difference detected; this n detects ≥" in line for line in same)
    assert not any("higher" in line or "lower" in line for line in same)
    with (out / "summary.csv").open() as f:
        assert len(list(csv.DictReader(f))) == len(METRICS) * len(BUDGETS) * 3

    again = tmp_path / "again"
    assert report_command([str(out / "results.csv"), str(again)]) == again / "report.md"
    for name in ("summary.csv", "results.csv", "report.md"):
        assert (again / name).read_bytes() == (out / name).read_bytes()


def test_hprior_reward_lab_report_runs_the_report_command(tmp_path, capsys):
    """`hprior reward-lab report`: exit 0 and the report's path; a bad argument exits 2
    before anything is written; the report module has no entry of its own."""
    from hprior_jax import cli

    write_report(_synthetic_rows(), tmp_path / "in", figures=False)
    results = str(tmp_path / "in" / "results.csv")
    assert cli.main(["reward-lab", "report", results, str(tmp_path / "out"), "--no-figures"]) == 0
    assert capsys.readouterr().out.strip() == str(tmp_path / "out" / "report.md")
    assert (tmp_path / "out" / "report.md").read_bytes() == (
        tmp_path / "in" / "report.md").read_bytes()
    with pytest.raises(SystemExit) as e:
        cli.main(["reward-lab", "report", results, str(tmp_path / "bad"), "--pairs", "better"])
    assert e.value.code == 2 and "write each pair as A:B" in capsys.readouterr().err
    assert not (tmp_path / "bad").exists() and not hasattr(lab_report, "main")


def test_no_figures_writes_tables_only_and_no_reference_is_named_when_none_ran(tmp_path):
    rows = [r for r in _synthetic_rows() if r["rule"] != "pebble"]
    write_report(rows, tmp_path / "in")
    assert "![" in (tmp_path / "in" / "report.md").read_text()
    text = report_command([str(tmp_path / "in" / "results.csv"), str(tmp_path / "out"),
                            "--no-figures"]).read_text()
    assert not list((tmp_path / "out").glob("*.png")) and "![" not in text and ".png" not in text
    assert "Differences are on the seeds both ran" in text and "pebble" not in text
    assert "Differences vs pebble are rule − pebble" in write_report(
        _synthetic_rows(), tmp_path / "ref", figures=False).read_text()


def test_the_report_command_merges_labs_keeping_the_first_files_shared_rows(tmp_path, capsys):
    """Two labs of the same seeds (e.g. two world models): their own rules join one report;
    the reference rule both ran is kept once, from the first file, and a disagreement between
    the two copies is counted and said."""
    rows = _synthetic_rows()
    write_report([r for r in rows if r["rule"] != "same"], tmp_path / "a")
    second = [dict(r) for r in rows if r["rule"] != "better"]
    moved = next(r for r in second if (r["rule"], r["seed"]) == ("pebble", 0))
    moved["pearson"] += 0.5
    write_report(second, tmp_path / "b")
    paths = [tmp_path / "a" / "results.csv", tmp_path / "b" / "results.csv"]

    merged, differing = lab_report.merge_results(paths)
    assert differing == 1
    assert len(merged) == len(rows)
    kept = next(r for r in merged if (r["rule"], r["seed"], r["budget"])
                == (moved["rule"], 0, moved["budget"]))
    assert kept["pearson"] == pytest.approx(moved["pearson"] - 0.5)
    report_command([*map(str, paths), str(tmp_path / "both")])
    assert "1 rows found in several files differ" in capsys.readouterr().err
    text = (tmp_path / "both" / "report.md").read_text()
    assert "- better − pebble at" in text and "- same − pebble at" in text


def test_tags_rename_a_labs_rules_so_two_settings_of_every_rule_compare(tmp_path):
    """--tags '' T: the second lab's rules, pebble included, become RULE[T] and are all kept
    (a lab with --one-shot or another --feed changes every rule); --pairs compares across."""
    rows = _synthetic_rows()
    write_report(rows, tmp_path / "a")
    shifted = [dict(r, pearson=r["pearson"] + 0.25) for r in rows]
    write_report(shifted, tmp_path / "b")
    paths = [tmp_path / "a" / "results.csv", tmp_path / "b" / "results.csv"]
    merged, differing = lab_report.merge_results(paths, ["", "t"])
    assert differing == 0 and len(merged) == 2 * len(rows)
    assert {r["rule"] for r in merged} == {"pebble", "better", "same",
                                           "pebble[t]", "better[t]", "same[t]"}
    with pytest.raises(ValueError, match="one per file"):
        lab_report.merge_results(paths, ["t"])
    report_command([*map(str, paths), str(tmp_path / "both"), "--tags", "", "t",
                     "--pairs", "pebble[t]:pebble"])
    with (tmp_path / "both" / "pairs.csv").open() as f:
        pearson = [r for r in csv.DictReader(f) if r["metric"] == "pearson"]
    assert len(pearson) == len(BUDGETS)
    assert all(float(r["diff"]) == pytest.approx(0.25) for r in pearson)
    report_command([*map(str, paths), str(tmp_path / "some"), "--tags", "", "t",
                     "--only", "pebble", "pebble[t]"])
    assert {r["rule"] for r in lab_report.read_results(tmp_path / "some" / "results.csv")} == {
        "pebble", "pebble[t]"}


def test_pairs_compare_any_two_rules_as_the_reference_comparison_does(tmp_path):
    """--pairs A:B: A − B paired by seed. better:pebble must equal the summary's comparison
    with pebble, number for number; a pair of rules that never ran together is an error."""
    rows = _synthetic_rows()
    write_report(rows, tmp_path, pairs=[("better", "pebble"), ("same", "better")])
    summary = {(e["metric"], e["budget"], e["rule"]): e for e in summarize(rows)}
    with (tmp_path / "pairs.csv").open() as f:
        pairs = list(csv.DictReader(f))
    assert len(pairs) == 2 * len(METRICS) * len(BUDGETS)
    for p in pairs:
        if p["versus"] == "pebble":
            want = summary[(p["metric"], int(p["budget"]), "better")]
            for k in ("diff", "diff_lo", "diff_hi", "p", "mde80"):
                assert float(p[k]) == pytest.approx(want[f"vs_pebble_{k}"], nan_ok=True)
        else:
            assert float(p["diff"]) == pytest.approx(-0.1, abs=1e-9)
    text = (tmp_path / "report.md").read_text()
    assert "## Paired differences between rules" in text
    assert "| better − pebble |" in text and "- same − better at 25 labels:" in text
    with pytest.raises(ValueError, match="both rules"):
        write_report(rows, tmp_path / "x", pairs=[("better", "oracle")])
    assert report_command([str(tmp_path / "results.csv"), str(tmp_path / "again"), "--pairs",
                            "better:pebble", "same:better"])
    assert (tmp_path / "again" / "pairs.csv").read_bytes() == (tmp_path / "pairs.csv").read_bytes()


def test_within_episode_metrics_see_credit_that_the_pooled_ones_hide():
    """Two rewards with each episode's level right: one also orders the steps within each
    episode right, the other reverses them. Pearson over all states barely tells them
    apart (the levels dominate); the within-episode metrics do, with opposite signs."""
    from hprior_jax.lab.metrics import reward_quality, uniform_credit_ceiling

    rng = np.random.default_rng(0)
    level = rng.uniform(-1, 1, (8, 1)) * 5
    shape = rng.normal(size=(8, 40))
    true = level + shape
    right, reversed_ = level + 0.1 * shape, level - 0.1 * shape
    pairs = np.array([[0, 0, 1, 10], [2, 5, 3, 20], [4, 0, 5, 30]])
    q_right = reward_quality(right, true, pairs, np.zeros(3, int), 10)
    q_rev = reward_quality(reversed_, true, pairs, np.zeros(3, int), 10)
    assert abs(q_right["pearson"] - q_rev["pearson"]) < 0.1
    assert q_right["episode_pearson"] == pytest.approx(1.0)
    assert q_rev["episode_pearson"] == pytest.approx(-1.0)
    assert q_right["segment_rank"] == pytest.approx(1.0)
    assert q_rev["segment_rank"] == pytest.approx(-1.0)
    # a reward constant within episodes has no within-episode credit; its moving mean
    # (uniform credit's best) sees only the smooth part
    flat = np.repeat(level, 40, axis=1)
    assert np.isnan(uniform_credit_ceiling(flat, 10)["episode_pearson"])
    ramp = np.tile(np.linspace(0, 1, 40), (8, 1)) + 0.0 * level
    assert uniform_credit_ceiling(ramp, 10)["episode_pearson"] > 0.95
    assert uniform_credit_ceiling(true, 10)["episode_pearson"] < 0.6  # white noise shape


def test_report_warns_when_the_world_model_does_not_predict_and_says_where_it_fails():
    from hprior_jax.lab.report_notes import report_notes

    seed = {"wm/skill_vs_persistence": -50.0, "wm/latent_skill_vs_persistence": 0.4,
            "wm/reconstruction_error": 0.2, "wm/persistence_error": 0.004}
    ceiling = {"pearson": 0.9, "episode_pearson": 0.8}
    warned, said = report_notes([seed, seed], ceiling, 50)
    assert "does not predict" in warned and "-50.000" in warned
    assert "latent space its skill over persistence is +0.400" in warned and "0.2 against" in warned
    assert "50-step moving mean): Pearson 0.900, within-episode Pearson 0.800" in said
    predicting = report_notes([{**seed, "wm/skill_vs_persistence": 0.3, "alpha/position_r2": 0.4},
                               {**seed, "wm/skill_vs_persistence": -0.1,
                                "alpha/position_r2": 0.6}], ceiling, 50)
    assert not any("does not predict" in n for n in predicting)
    assert ("World model: skill over persistence +0.100, mean of 2 seeds, 1 of them above 0; "
            "the share of its α's variance that step position explains (R²) is 0.50"
            in predicting[0])


def test_seed_shards_merge_into_one_report_with_their_world_model_notes(tmp_path):
    """Two seed shards of one lab: the merged report warns from the mean skill over every
    seed (each shard alone would say otherwise) and writes their diagnostics as one file; two
    labs of the same seeds (two world models) keep their diagnostics apart."""
    import json

    from hprior_jax.lab.report_notes import read_diagnostics, write_diagnostics

    rows = _synthetic_rows()
    skills = {0: 0.5, 1: -2.0, 2: 0.1, 3: 0.2, 4: 0.3}  # mean -0.18: does not predict
    for name, seeds in (("a", (0, 1)), ("b", (2, 3, 4))):
        write_report([r for r in rows if r["seed"] in seeds], tmp_path / name)
        write_diagnostics(tmp_path / name / "diagnostics.csv",
                          [{"seed": s, "wm/skill_vs_persistence": skills[s]} for s in seeds])
        (tmp_path / name / "run_info.json").write_text(json.dumps(dict(
            uniform_credit_ceiling={"pearson": 0.9, "episode_pearson": 0.8}, segment_len=50)))
    paths = [str(tmp_path / n / "results.csv") for n in ("a", "b")]
    text = report_command([*paths, str(tmp_path / "both")]).read_text()
    assert "5 seeds per (task, rule, budget)" in text
    assert "does not predict** (skill over persistence -0.180, mean of 5 seeds" in text
    assert "within-episode Pearson 0.800" in text
    assert [d["seed"] for d in read_diagnostics(tmp_path / "both" / "diagnostics.csv")] == [
        0, 1, 2, 3, 4]
    assert "different datasets" not in text
    text = report_command([paths[0], paths[0], str(tmp_path / "twice")]).read_text()
    assert "does not predict" not in text and not (tmp_path / "twice" / "diagnostics.csv").exists()
    for name, digest in (("a", "d1"), ("b", "d2")):  # a shard built its dataset differently
        info = tmp_path / name / "run_info.json"
        info.write_text(json.dumps({**json.loads(info.read_text()), "dataset_digest": digest}))
    text = report_command([*paths, str(tmp_path / "mixed")]).read_text()
    assert "these labs learned from different datasets** (digests d1, d2)" in text
