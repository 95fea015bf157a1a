"""A pre-registered comparison of methods in returns, run as grid pieces (seed shards,
one method at a time) over sessions: `collect` keeps each finished piece's small summary
(evaluation returns, last-round reward correlation, provenance) in a results folder, and
`report` computes the plan's contrasts from those files alone, so the analysis reruns from
what is committed, without run directories.

    python -m hprior_jax.experiments.returns_verdict collect GRID_ROOT [...] --into DIR
    python -m hprior_jax.experiments.returns_verdict report DIR

The plan (`Plan`, kept as `plan.json` in the results folder): each seed's true return averaged over its last K
evaluations, divided by the reference's (SAC on the true reward) mean over its seeds and the
same steps; paired contrasts per task with a 95% t-interval, Holm over every planned test
(a task not yet complete counts its tests as not rejected, p = 1), TOST where a margin is
named, MDE80 from each contrast's own spread. A task is tested only once every method has
all its seeds and the reference all of its own (no interim tests)."""
from __future__ import annotations

import argparse
import csv
import dataclasses
import json
from collections import defaultdict
from pathlib import Path

import numpy as np

from hprior_jax import statistics
from hprior_jax.experiments.report import discover, reward_correlations
from hprior_jax.experiments.scores import normalized_score, reference_curve
from hprior_jax.plotting import read_eval_csv, save_figure
from hprior_jax.run_log import read_jsonl
from hprior_jax.statistics import holm, mean_ci, paired_comparison, tost_p

EVALS, CORR, PIECES, PLAN = "evals.csv", "reward_corr.csv", "pieces.csv", "plan.json"


@dataclasses.dataclass(frozen=True)
class Plan:
    tasks: tuple[str, ...]
    methods: tuple[str, ...]
    seeds: tuple[int, ...]
    reference: str
    reference_seeds: tuple[int, ...]
    last_evals: int
    contrasts: tuple[tuple[str, str], ...]  # (a, b): a − b
    tost_margins: dict  # {(a, b): {task: margin}}
    paper: dict  # {task: {method: normalized return}}: the paper's Table 7, for reference

    @staticmethod
    def load(path: Path) -> "Plan":
        """A plan written as JSON beside its results (`plan.json`): the fields above, contrasts
        as [a, b] pairs, tost_margins as {"a - b": {task: margin}}."""
        d = json.loads(Path(path).read_text())
        return Plan(
            tasks=tuple(d["tasks"]), methods=tuple(d["methods"]), seeds=tuple(d["seeds"]),
            reference=d["reference"], reference_seeds=tuple(d["reference_seeds"]),
            last_evals=int(d["last_evals"]),
            contrasts=tuple(tuple(c) for c in d["contrasts"]),
            tost_margins={tuple(k.split(" - ")): v for k, v in d["tost_margins"].items()},
            paper=d.get("paper", {}))


# -- collect: a finished piece's summary into the results folder ---------------------------
def _read(path: Path) -> list[dict]:
    return list(csv.DictReader(path.open())) if path.exists() else []


def _write(path: Path, rows: list[dict], fields: list[str]) -> None:
    tmp = path.with_suffix(".tmp")
    with tmp.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=fields, lineterminator="\n")
        w.writeheader()
        w.writerows(rows)
    tmp.replace(path)


def _replace(path: Path, new: list[dict], fields: list[str], key) -> None:
    """`path`'s rows with those of `new`'s keys replaced by `new` (collecting twice is safe)."""
    keys = {key(r) for r in new}
    kept = [r for r in _read(path) if key(r) not in keys]
    _write(path, sorted(kept + new, key=lambda r: tuple(str(r[f]).zfill(8) for f in fields)),
           fields)


def collect(roots, into: Path) -> list[str]:
    """Adds every complete run under each grid `roots` to `into`'s summaries; returns one
    line per run collected."""
    into = Path(into)
    into.mkdir(parents=True, exist_ok=True)
    lines = []
    for root in roots:
        runs = discover(Path(root))
        for task, by_algo in runs.items():
            for algo, run_dir in by_algo.items():
                cfg = json.loads((run_dir / "config.json").read_text())
                evals = [dict(task=task, algo=algo, seed=seed, step=int(t), true_return=float(v))
                         for seed, (steps, values) in read_eval_csv(run_dir / "eval.csv").items()
                         for t, v in zip(steps, values)]
                if max((e["step"] for e in evals), default=0) < cfg["steps"]:
                    lines.append(f"{task}/{algo} in {root}: not complete, skipped")
                    continue
                _replace(into / EVALS, evals, ["task", "algo", "seed", "step", "true_return"],
                         lambda r: (r["task"], r["algo"], str(r["seed"])))
                last = {}
                for r in reward_correlations({task: {algo: run_dir}}):
                    last[r["seed"]] = r  # rounds come in step order: the last one stays
                corr = [dict(task=task, algo=algo, seed=s, step=r["step"], labels=r["labels"],
                             true_corr=r["true_corr"]) for s, r in sorted(last.items())]
                _replace(into / CORR, corr, ["task", "algo", "seed", "step", "labels",
                                             "true_corr"],
                         lambda r: (r["task"], r["algo"], str(r["seed"])))
                info = cfg.get("run_info") or {}
                piece = dict(task=task, algo=algo, seeds=" ".join(map(str, cfg["seeds"])),
                             steps=cfg["steps"], preset=cfg["preset"],
                             git_commit=info.get("git_commit", ""),
                             started=info.get("started", ""),
                             chunk_s=round(_chunk_seconds(run_dir)))
                _replace(into / PIECES, [piece], list(piece),
                         lambda r: (r["task"], r["algo"], r["seeds"]))
                lines.append(f"{task}/{algo} seeds {piece['seeds']}: collected")
    return lines


def _chunk_seconds(run_dir: Path) -> float:
    """Seconds the run spent in its env + update chunks (`perf/chunk_s`, once per chunk)."""
    seen, total = set(), 0.0
    for rec in read_jsonl(run_dir / "metrics.jsonl"):
        if "perf/chunk_s" in rec and rec["step"] not in seen:
            seen.add(rec["step"])
            total += rec["perf/chunk_s"]
    return total


# -- report: the plan's contrasts from the summaries ----------------------------------------
def curves(rows) -> dict:
    """{(task, algo): {seed: {step: true_return}}}."""
    out = defaultdict(lambda: defaultdict(dict))
    for r in rows:
        out[(r["task"], r["algo"])][int(r["seed"])][int(r["step"])] = float(r["true_return"])
    return out


def complete_tasks(plan: Plan, by_run: dict) -> dict[str, str]:
    """{task: "" if complete, else what is missing}."""
    state = {}
    for task in plan.tasks:
        missing = []
        for algo, seeds in [(m, plan.seeds) for m in plan.methods] + [
                (plan.reference, plan.reference_seeds)]:
            have = set(by_run.get((task, algo), {}))
            lack = [s for s in seeds if s not in have]
            if lack:
                missing.append(f"{algo} seeds {_span(lack)}")
        state[task] = "; ".join(missing)
    return state


def _span(seeds) -> str:
    seeds = sorted(seeds)
    return f"{seeds[0]}-{seeds[-1]}" if seeds == list(range(seeds[0], seeds[-1] + 1)) \
        else " ".join(map(str, seeds))


def scores(plan: Plan, by_run: dict, task: str) -> tuple[dict, list[int]]:
    """({algo: {seed: normalized score}}, the steps averaged) of a complete task: the
    project's normalization (`experiments.scores`: the reference's mean over its seeds),
    as a ratio of means over the reference's last `plan.last_evals` evaluation steps."""
    as_curve = lambda d: (np.asarray(sorted(d)), np.asarray([d[t] for t in sorted(d)]))  # noqa: E731
    ref = reference_curve({s: as_curve(by_run[(task, plan.reference)][s])
                           for s in plan.reference_seeds})
    steps = [int(t) for t in ref[0][-plan.last_evals:]]
    out = {algo: {s: normalized_score(as_curve(by_run[(task, algo)][s]), ref, "ratio-of-means",
                                      after_step=steps[0] - 1)[0] for s in plan.seeds}
           for algo in plan.methods}
    return out, steps


def contrasts(plan: Plan, by_task: dict) -> list[dict]:
    """One row per (task, contrast) of the plan; by_task {task: {algo: {seed: value}}} holds
    the complete tasks only."""
    rows = []
    for task in plan.tasks:
        for a, b in plan.contrasts:
            margin = plan.tost_margins.get((a, b), {}).get(task, float("nan"))
            row = dict(task=task, contrast=f"{a} - {b}", tost_margin=margin)
            if task in by_task:
                c = paired_comparison(by_task[task][b], by_task[task][a])
                row |= c
                d = [by_task[task][a][s] - by_task[task][b][s] for s in plan.seeds]
                row["tost_p"] = tost_p(d, margin) if margin == margin else float("nan")
            else:
                row |= dict(n=0, diff=float("nan"), diff_lo=float("nan"),
                            diff_hi=float("nan"), p=float("nan"), sd=float("nan"),
                            mde80=float("nan"), tost_p=float("nan"))
            rows.append(row)
    # the family is every planned test: an incomplete task's count as not rejected (p = 1)
    adjusted = holm([1.0 if r["p"] != r["p"] else r["p"] for r in rows])
    # the equivalence family: the tests that have a margin (holm leaves NaN out)
    tost_adjusted = holm([r["tost_p"] for r in rows])
    for r, p, tost in zip(rows, adjusted, tost_adjusted):
        r["holm_p"] = p if r["n"] else float("nan")
        r["tost_holm_p"] = tost
    return rows


def verdict(r: dict) -> str:
    if not r["n"]:
        return "not run yet"
    return statistics.verdict(r["contrast"].split(" - ")[0], r["n"], r["diff"], r["holm_p"],
                              r["tost_holm_p"], r["tost_margin"], r["mde80"])


def _fmt(x, digits=3) -> str:
    return "–" if x != x else f"{x:+.{digits}f}" if digits == 3 else f"{x:.{digits}g}"


def plot_curves(plan: Plan, by_run: dict, path: Path) -> Path:
    """True return per method (mean and 95% t-interval over seeds) against env steps, one
    panel per task that has runs."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tasks = [t for t in plan.tasks if any(k[0] == t for k in by_run)]
    fig, axes = plt.subplots(1, max(len(tasks), 1), figsize=(5.5 * max(len(tasks), 1), 4),
                             squeeze=False)
    for ax, task in zip(axes[0], tasks):
        for algo in (plan.reference, *plan.methods):
            run = by_run.get((task, algo))
            if not run:
                continue
            steps = sorted(set.intersection(*(set(v) for v in run.values())))
            stats = [mean_ci([run[s][t] for s in run]) for t in steps]
            mean = [m for m, _, _, _ in stats]
            line, = ax.plot(steps, mean, label=f"{algo} ({len(run)} seeds)")
            ax.fill_between(steps, [lo for _, lo, _, _ in stats],
                            [hi for _, _, hi, _ in stats], color=line.get_color(), alpha=0.2)
        ax.set_title(task)
        ax.set_xlabel("environment steps")
        ax.set_ylabel("true return (mean, 95% CI over seeds)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    out = save_figure(fig, path)
    plt.close(fig)
    return out


def report(into: Path, plan: Plan | None = None) -> str:
    """Writes report.md, scores.csv, contrasts.csv and curves.png into `into` (its plan:
    `plan`, else `into/plan.json`); returns the report's text."""
    into = Path(into)
    plan = plan or Plan.load(into / PLAN)
    by_run = curves(_read(into / EVALS))
    state = complete_tasks(plan, by_run)
    by_task, steps_used, score_rows = {}, {}, []
    for task in plan.tasks:
        if not state[task]:
            by_task[task], steps_used[task] = scores(plan, by_run, task)
            score_rows += [dict(task=task, algo=a, seed=s, score=v)
                           for a, by_seed in by_task[task].items() for s, v in by_seed.items()]
    rows = contrasts(plan, by_task)
    _write(into / "scores.csv", score_rows, ["task", "algo", "seed", "score"])
    fields = ["task", "contrast", "n", "diff", "diff_lo", "diff_hi", "p", "holm_p", "sd",
              "mde80", "tost_margin", "tost_p", "tost_holm_p"]
    _write(into / "contrasts.csv", [{k: r[k] for k in fields} for r in rows], fields)
    if by_run:
        plot_curves(plan, by_run, into / "curves.png")
    corr = defaultdict(dict)
    for r in _read(into / CORR):
        corr[(r["task"], r["algo"])][int(r["seed"])] = float(r["true_corr"])
    text = _markdown(plan, state, by_task, steps_used, rows, corr, bool(by_run))
    (into / "report.md").write_text(text)
    return text


def _markdown(plan, state, by_task, steps_used, rows, corr, has_curves) -> str:
    md = ["# Returns: " + ", ".join(plan.methods) + f" against {plan.reference}", ""]
    md += ["Normalized return: each seed's true return over its last "
           f"{plan.last_evals} evaluations divided by {plan.reference}'s mean over seeds "
           f"{_span(plan.reference_seeds)} at the same steps. Seeds {_span(plan.seeds)}.", ""]
    md += ["| task | state |", "|---|---|"]
    md += [f"| {t} | {'complete (steps ' + ', '.join(map(str, steps_used[t])) + ')' if not s else 'missing ' + s} |"
           for t, s in state.items()]
    md += ["", "## Table 7 (normalized return, mean [95% CI] over seeds; the paper's in "
           "parentheses)", "",
           "| task | " + " | ".join(plan.methods) + " |", "|---|" + "---|" * len(plan.methods)]
    for task in plan.tasks:
        cells = []
        for algo in plan.methods:
            paper = plan.paper.get(task, {}).get(algo)
            ref = f" (paper {paper:.2f})" if paper is not None else ""
            if task in by_task:
                m, lo, hi, _ = mean_ci(list(by_task[task][algo].values()))
                cells.append(f"{m:.2f} [{lo:.2f}, {hi:.2f}]{ref}")
            else:
                cells.append(f"–{ref}")
        md.append(f"| {task} | " + " | ".join(cells) + " |")
    md += ["", f"## Contrasts (paired over seeds; Holm over all {len(rows)} planned tests)", "",
           "| task | contrast | n | diff [95% CI] | p | Holm p | MDE80 | TOST Holm p (margin) | verdict |",
           "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        tost = (f"{_fmt(r['tost_holm_p'], 2)} (±{r['tost_margin']:.2f})"
                if r["tost_margin"] == r["tost_margin"] else "–")
        md.append(f"| {r['task']} | {r['contrast']} | {r['n']} | {_fmt(r['diff'])} "
                  f"[{_fmt(r['diff_lo'])}, {_fmt(r['diff_hi'])}] | {_fmt(r['p'], 2)} | "
                  f"{_fmt(r['holm_p'], 2)} | {_fmt(r['mde80'], 3).lstrip('+')} | {tost} | {verdict(r)} |")
    md += ["", "## Secondary: learned-vs-true reward correlation at the last round", "",
           "Pearson on the replay buffer (`reward/true_corr`); the same contrasts, not in the "
           "Holm family.", "", "| task | contrast | n | diff [95% CI] | p |", "|---|---|---|---|---|"]
    for task in by_task:
        for a, b in plan.contrasts:
            if corr.get((task, a)) and corr.get((task, b)):
                c = paired_comparison(corr[(task, b)], corr[(task, a)])
                md.append(f"| {task} | {a} - {b} | {c['n']} | {_fmt(c['diff'])} "
                          f"[{_fmt(c['diff_lo'])}, {_fmt(c['diff_hi'])}] | {_fmt(c['p'], 2)} |")
    if has_curves:
        md += ["", "![learning curves](curves.png)"]
    return "\n".join(md) + "\n"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m hprior_jax.experiments.returns_verdict",
                                description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="command", required=True)
    c = sub.add_parser("collect", help="add finished grid runs' summaries to a results folder")
    c.add_argument("roots", nargs="+", type=Path)
    c.add_argument("--into", type=Path, required=True)
    r = sub.add_parser("report", help="the plan's contrasts from a results folder")
    r.add_argument("folder", type=Path)
    args = p.parse_args(argv)
    if args.command == "collect":
        print("\n".join(collect(args.roots, args.into)))
    else:
        report(args.folder)
        print(f"wrote {args.folder}/report.md, scores.csv, contrasts.csv")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
