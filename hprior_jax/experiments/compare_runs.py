"""Two runs of one task, seed by seed: does a change (a flag, the physics, the code) move the
result, and could this many seeds have seen it?

    python -m hprior_jax.experiments.compare_runs RUN_A RUN_B [--out DIR] [--after 5000]

Per seed, from each run's eval.csv (true return, or success where the task has one): the
final evaluation, and the mean of the evaluations after step `--after` (default 5000, SAC's
uniform-random seed steps, which the normalized score leaves out too). Then B − A on the seeds
both ran: the mean difference with its 95% t-interval, the two-sided paired t-test and the
smallest true difference that test detects with 80% power at this n and this spread
(`statistics.paired_comparison`). Runs of the same seed are still different draws when the
programs differ, so "paired" removes the seed's share of the variance, not all of it.
"""
from __future__ import annotations

import argparse
import csv
from pathlib import Path

import numpy as np

from hprior_jax.statistics import mean_ci, paired_comparison
from hprior_jax.plotting import read_eval_csv

STATISTICS = ("final", "mean_after")


def seed_statistics(eval_csv: Path, after: int) -> tuple[str, dict[str, dict[int, float]]]:
    """(metric, {statistic: {seed: value}}) of one run's eval.csv."""
    metric = "success" if read_eval_csv(eval_csv, "success") else "true_return"
    curves = read_eval_csv(eval_csv, metric)
    final = {s: float(v[np.argmax(steps)]) for s, (steps, v) in curves.items()}
    mean_after = {s: float(np.mean(v[steps > after])) if (steps > after).any() else np.nan
                  for s, (steps, v) in curves.items()}
    return metric, {"final": final, "mean_after": mean_after}


def compare(run_a: Path, run_b: Path, after: int = 5000) -> tuple[list[dict], list[dict]]:
    """-> (per-seed rows, one summary row per statistic)."""
    metric_a, a = seed_statistics(Path(run_a) / "eval.csv", after)
    metric_b, b = seed_statistics(Path(run_b) / "eval.csv", after)
    if metric_a != metric_b:
        raise ValueError(f"{run_a} reports {metric_a}, {run_b} {metric_b}: not one task")
    seeds = sorted(set(a["final"]) | set(b["final"]))
    per_seed = [{"seed": s, **{f"{stat}_{side}": run[stat].get(s, np.nan)
                               for stat in STATISTICS for side, run in (("a", a), ("b", b))}}
                for s in seeds]
    summary = []
    for stat in STATISTICS:
        row = {"statistic": f"{stat} {metric_a}"}
        for side, run in (("a", a), ("b", b)):
            mean, lo, hi, n = mean_ci(list(run[stat].values()))
            row |= {f"mean_{side}": mean, f"lo_{side}": lo, f"hi_{side}": hi, f"n_{side}": n}
        summary.append(row | paired_comparison(a[stat], b[stat]))
    return per_seed, summary


def markdown(summary: list[dict], run_a, run_b) -> str:
    lines = [f"A = {run_a}", f"B = {run_b}", "",
             "| statistic | A mean [95% CI] | B mean [95% CI] | B − A [95% CI] | p | pairs | MDE80 |",
             "|---|---|---|---|---|---|---|"]
    ci = lambda m, lo, hi: f"{m:.3g} [{lo:.3g}, {hi:.3g}]"
    for r in summary:
        lines.append(f"| {r['statistic']} | {ci(r['mean_a'], r['lo_a'], r['hi_a'])} | "
                     f"{ci(r['mean_b'], r['lo_b'], r['hi_b'])} | "
                     f"{ci(r['diff'], r['diff_lo'], r['diff_hi'])} | {r['p']:.3g} | {r['n']} | "
                     f"{r['mde80']:.3g} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m hprior_jax.experiments.compare_runs",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("run_a", type=Path)
    parser.add_argument("run_b", type=Path)
    parser.add_argument("--after", type=int, default=5000)
    parser.add_argument("--out", type=Path,
                        help="writes per_seed.csv, summary.csv and report.md there")
    args = parser.parse_args(argv)
    per_seed, summary = compare(args.run_a, args.run_b, args.after)
    text = markdown(summary, args.run_a, args.run_b)
    print(text)
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        for name, rows in (("per_seed.csv", per_seed), ("summary.csv", summary)):
            with open(args.out / name, "w", newline="") as f:
                writer = csv.DictWriter(f, fieldnames=list(rows[0]), lineterminator="\n")
                writer.writeheader()
                writer.writerows(rows)
        (args.out / "report.md").write_text(text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
