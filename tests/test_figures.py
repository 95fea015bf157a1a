"""The figures say what they show: read back from each saved PNG's text chunks (titles, axis
ranges, legends, line colours, axes positions), written by `plotting.save_figure`."""
import json
import math

import numpy as np
from PIL import Image

from hprior_jax.experiments.attention_map import plot_attention_map
from hprior_jax.experiments.report import method_color, plot_task_curves
from hprior_jax.lab.report import comparison_sentence
from hprior_jax.lab.report_figures import plot_metric
from hprior_jax.plotting import plot_learning_curve, returns_summary


def _meta(path):
    text = Image.open(path).text
    return text["Title"], json.loads(text["Description"])


def _eval_csv(path, seeds, success: bool):
    rows = ["step,seed,true_return,success"]  # eval.csv's columns; DM Control's success empty
    for step in (1000, 2000, 3000):
        for s in seeds:
            rows.append(f"{step},{s},{step / 100 + s}," + (f"{(s + step) % 2}" if success else ""))
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(rows) + "\n")
    return path


def test_a_learning_curve_of_a_task_with_success_has_a_rate_axis(tmp_path):
    csv = _eval_csv(tmp_path / "eval.csv", (1, 2), success=True)
    title, axes = _meta(plot_learning_curve(csv, tmp_path / "curve.png", title="sac on x"))
    assert title == "sac on x"
    rate, returns = axes
    assert rate["ylabel"] == "evaluation success rate" and rate["ylim"] == [-0.02, 1.02]
    assert returns["ylabel"] == "evaluation true return" and "mean" in returns["legend"]


def test_the_terminal_summary_gives_each_evaluation_its_mean_range_and_success(tmp_path):
    csv = _eval_csv(tmp_path / "eval.csv", (1, 3), success=True)
    lines = returns_summary(csv).splitlines()
    assert len(lines) == 3 and lines[0].split() == ["step", "1000:", "return", "12.0", "(seeds",
                                                    "11.0", "to", "13.0),", "success", "100%"]
    one_seed = returns_summary(_eval_csv(tmp_path / "one" / "eval.csv", (2,), success=False))
    assert one_seed.splitlines()[-1].split() == ["step", "3000:", "return", "32.0"]


def test_grid_curves_name_seeds_in_the_singular_and_keep_a_colour_per_method(tmp_path):
    by_algo = {algo: tmp_path / algo for algo in ("sac", "pebble", "prior")}
    for algo, seeds in (("sac", (1,)), ("pebble", (1, 2)), ("prior", (1, 2))):
        _eval_csv(by_algo[algo] / "eval.csv", seeds, success=True)
    one = plot_task_curves("drawer_open", by_algo, tmp_path)[0]
    (tmp_path / "alone").mkdir()
    two = plot_task_curves("drawer_open", {"prior": by_algo["prior"]}, tmp_path / "alone")[0]
    title, (ax,) = _meta(one)
    assert ax["title"] == "drawer_open" and "/" not in title
    assert ax["legend"][0] == "sac (1 seed)"  # the reference first
    assert sorted(ax["legend"][1:]) == ["pebble (2 seeds)", "prior (2 seeds)"]
    assert ax["ylim"] == [-0.02, 1.02]
    _, (alone,) = _meta(two)
    assert alone["lines"]["prior (2 seeds)"] == ax["lines"]["prior (2 seeds)"] == (
        method_color("prior"))
    assert len(set(ax["lines"].values())) == 3


def test_an_attention_map_says_which_segment_was_preferred_and_keeps_its_colour_bar_clear(
        tmp_path):
    rows, alpha = np.random.default_rng(0).random((2, 20)), np.full(10, 0.1)
    path = plot_attention_map(rows, alpha, tmp_path / "a.png",
                              "cheetah_run seed 1 step 9: pair 0, segment 2 (preferred by "
                              "the teacher)", true_reward=np.linspace(0, 1, 10))
    title, axes = _meta(path)
    assert "(preferred by the teacher)" in title.replace("\n", " ")
    states, actions, bars, bar_colour, reward = (axes[i] for i in (0, 1, 2, 3, 4))
    assert bar_colour["xlabel"] == "attention of the final step"
    # the colour bar sits above every panel, the true reward's axis beside the bars
    assert bar_colour["position"][1] >= states["position"][1] + states["position"][3] - 1e-3
    assert reward["ylabel"] == "true reward"
    assert bars["legend"] == ["α (mean over layers)", "true reward"]


def test_a_lab_figure_title_is_wrapped_and_a_tie_at_two_seeds_is_not_called(tmp_path):
    entries = [dict(rule=r, budget=b, mean=m, ci_lo=m - 0.1, ci_hi=m + 0.1,
                    metric="episode_pearson")
               for r, m in (("pebble", 0.5), ("prior~shift", 0.6)) for b in (25, 100)]
    long = "Reward-learning lab: cheetah_run, within-episode Pearson r with the true reward"
    title, (ax,) = _meta(plot_metric(entries, tmp_path / "m.png", long))
    assert all(len(line) <= 60 for line in ax["title"].split("\n"))
    assert ax["legend"] == ["pebble", "prior~shift"]
    entry = dict(rule="rvar", budget=25, vs_pebble_n=2, vs_pebble_diff=-0.001,
                 vs_pebble_diff_lo=-0.0011, vs_pebble_diff_hi=-0.0009, vs_pebble_p=0.001,
                 vs_pebble_mde80=math.nan)
    assert "not testable" in comparison_sentence(entry)
