"""The returns verdict's analysis: pieces collected from grid run directories, scores over
the last evaluations against the reference, Holm over every planned test, no test of an
incomplete task."""
import csv
import json

import numpy as np
import pytest

from hprior_jax.experiments import returns_verdict as rv

PLAN = rv.Plan(tasks=("t1", "t2"), methods=("a", "b"), seeds=(0, 1, 2, 3, 4, 5),
               reference="sac", reference_seeds=(0, 1), last_evals=2,
               contrasts=(("a", "b"),), tost_margins={("a", "b"): {"t1": 0.5}},
               paper={"t1": {"a": 0.6}})
STEPS = (10, 20, 30)


def _run(root, task, algo, seeds, returns, corr=None, steps=30):
    """A grid run directory: config.json, eval.csv, metrics.jsonl (`returns(seed, step)`)."""
    d = root / task / algo
    d.mkdir(parents=True)
    (d / "config.json").write_text(json.dumps(dict(
        task=task, algo=algo, seeds=list(seeds), steps=steps, preset="reduced",
        run_info={"git_commit": "abc", "started": "now"})))
    with (d / "eval.csv").open("w") as f:
        f.write("step,seed,true_return,success\n")
        for t in STEPS:
            if t <= steps:
                for s in seeds:
                    f.write(f"{t},{s},{returns(s, t)},\n")
    with (d / "metrics.jsonl").open("w") as f:
        for s in seeds:
            f.write(json.dumps({"step": 10, "seed": s, "perf/chunk_s": 2.0}) + "\n")
            if corr is not None:
                for step, value in ((15, -1.0), (25, corr(s))):  # the last round counts
                    f.write(json.dumps({"step": step, "seed": s, "reward/true_corr": value,
                                        "feedback/total_labeled": 10}) + "\n")


def test_scores_contrasts_and_holm_over_the_planned_family(tmp_path):
    # t1 complete over two pieces (seed shards) and the reference; t2 has one piece only
    _run(tmp_path / "g0", "t1", "a", (0, 1, 2), lambda s, t: 60 + s + (1000 if t == 10 else 0),
         corr=lambda s: 0.5 + 0.01 * s)
    _run(tmp_path / "g0", "t1", "b", (0, 1, 2), lambda s, t: 50 + 2 * s, corr=lambda s: 0.4)
    _run(tmp_path / "g3", "t1", "a", (3, 4, 5), lambda s, t: 60 + s, corr=lambda s: 0.5)
    _run(tmp_path / "g3", "t1", "b", (3, 4, 5), lambda s, t: 50 + 2 * s, corr=lambda s: 0.4)
    _run(tmp_path / "ref", "t1", "sac", (0, 1), lambda s, t: 100 + (50 if s else -50))
    _run(tmp_path / "g0", "t2", "a", (0, 1, 2), lambda s, t: 1.0)
    _run(tmp_path / "part", "t2", "b", (0, 1, 2), lambda s, t: 1.0, steps=40)  # not finished
    lines = rv.collect([tmp_path / n for n in ("g0", "g3", "ref", "part")], tmp_path / "out")
    assert any("t2/b" in line and "not complete" in line for line in lines)
    rv.collect([tmp_path / "g0"], tmp_path / "out")  # collecting again changes nothing
    evals = list(csv.DictReader((tmp_path / "out" / rv.EVALS).open()))
    assert len(evals) == (6 + 6 + 2 + 3) * len(STEPS)
    pieces = list(csv.DictReader((tmp_path / "out" / rv.PIECES).open()))
    assert len(pieces) == 6 and {p["git_commit"] for p in pieces} == {"abc"}

    text = rv.report(tmp_path / "out", PLAN)
    scores = {(r["algo"], int(r["seed"])): float(r["score"])
              for r in csv.DictReader((tmp_path / "out" / "scores.csv").open())}
    # the last 2 evaluations (20, 30) only; the reference's mean over its seeds is 100
    assert scores[("a", 0)] == pytest.approx(0.60) and scores[("a", 5)] == pytest.approx(0.65)
    assert scores[("b", 5)] == pytest.approx(0.60)
    rows = {r["task"]: r for r in csv.DictReader((tmp_path / "out" / "contrasts.csv").open())}
    d = np.array([0.01 * s - 0.02 * s + 0.10 for s in range(6)])  # (60 + s - 50 - 2s) / 100
    assert float(rows["t1"]["diff"]) == pytest.approx(d.mean())
    # t2 is incomplete: not tested, but its test counts in the family (p = 1)
    assert rows["t2"]["n"] == "0" and rows["t2"]["p"] == "nan"
    assert float(rows["t1"]["holm_p"]) == pytest.approx(min(1.0, 2 * float(rows["t1"]["p"])))
    assert "| t2 | missing a seeds 3-5; b seeds 0-5; sac seeds 0-1 |" in text
    assert "0.60" in text and "(paper 0.60)" in text and "![learning curves](curves.png)" in text
    # the secondary contrast reads each seed's last round (0.5 + 0.01 s, not -1)
    assert "| t1 | a - b | 6 | +0.105" in text
    assert (tmp_path / "out" / "curves.png").stat().st_size > 0


def test_verdict_words():
    base = dict(contrast="a - b", n=20, diff=0.1, holm_p=0.01, tost_holm_p=float("nan"),
                tost_margin=0.07, mde80=0.15)
    assert rv.verdict(base) == "a higher"
    assert rv.verdict(base | dict(diff=-0.1)) == "a lower"
    assert rv.verdict(base | dict(holm_p=0.3, tost_holm_p=0.01)) == "equivalent within ±0.070"
    assert rv.verdict(base | dict(holm_p=0.3)) == "not detected (MDE80 0.150)"
    assert rv.verdict(base | dict(n=0)) == "not run yet"


def test_the_rl_verdicts_plan_file_is_the_pre_registered_plan():
    """benchmarks/results/rl_verdict/plan.json says what its README registered."""
    from pathlib import Path

    folder = Path(__file__).resolve().parent.parent / "benchmarks" / "results" / "rl_verdict"
    plan = rv.Plan.load(folder / rv.PLAN)
    assert plan.tasks == ("walker_walk", "cheetah_run") and plan.seeds == tuple(range(20))
    assert plan.reference_seeds == tuple(range(5)) and plan.last_evals == 5
    assert plan.contrasts == (("prior", "pebble"), ("rvar", "pebble"), ("prior", "rvar"))
    assert plan.tost_margins == {("prior", "rvar"): {"walker_walk": 0.07, "cheetah_run": 0.09}}
    readme = (folder / "README.md").read_text()
    assert "seeds 0, 1, 2, ..., 19" in readme and "walker ±0.07, cheetah\n±0.09" in readme
