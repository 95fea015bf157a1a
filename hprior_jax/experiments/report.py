"""`hprior report DIR`: appendix Tables 6-7, paired t-tests, learning curves, reward
correlation and attention maps from a results directory of `hprior grid` (ROOT/<task>/<algo>/).

Everything but the attention maps is read from the run directories' files (eval.csv,
metrics.jsonl, config.json), so a report needs no JAX and can be made while a grid runs."""
from __future__ import annotations

import csv
import json
from collections import defaultdict
from pathlib import Path

import numpy as np

from hprior_jax.experiments.attention_map import attention_maps_for_run
from hprior_jax.experiments.scores import task_scores
from hprior_jax.methods import registry
from hprior_jax.plotting import read_eval_csv, save_figure
from hprior_jax.run_log import read_jsonl
from hprior_jax.statistics import paired_t_test

REFERENCE = registry.REFERENCE  # every score is normalised by it
METHOD = registry.PROPOSED  # the t-tests compare every other method with it
TABLE_NAME = {"success": "Table 6: normalized success rate (MetaWorld)",
              "true_return": "Table 7: normalized returns (DM Control)"}


def discover(root: Path) -> dict[str, dict[str, Path]]:
    """{task: {algo: run_dir}} of every run directory under `root` with an eval.csv."""
    if not Path(root).is_dir():
        raise FileNotFoundError(f"{root} is not a directory; give the --out folder of an "
                                "`hprior grid` run")
    runs: dict[str, dict[str, Path]] = defaultdict(dict)
    for cfg_path in sorted(Path(root).glob("*/*/config.json")):
        run_dir = cfg_path.parent
        if not (run_dir / "eval.csv").exists():
            continue
        cfg = json.loads(cfg_path.read_text())
        runs[cfg["task"]][cfg["algo"]] = run_dir
    if not runs:
        raise FileNotFoundError(f"no run directories with eval.csv under {root}; make them "
                                f"with `hprior grid --out {root} ...`")
    return dict(runs)


def metric_of(run_dir: Path) -> str:
    """success where the task defines it (MetaWorld), true return otherwise (DM Control)."""
    return "success" if read_eval_csv(run_dir / "eval.csv", "success") else "true_return"


def _order(algos) -> list[str]:
    """Columns in the registry's order (the paper's tables)."""
    return registry.table_order(algos)


def compute_scores(runs, how: str, min_reference: float, pair_by_seed: bool) -> list[dict]:
    """One row per (task, PbRL algo, seed) with its normalized score."""
    rows = []
    for task, by_algo in sorted(runs.items()):
        if REFERENCE not in by_algo:
            print(f"warning: {task} has no {REFERENCE} run; its scores cannot be normalized "
                  f"(run `hprior grid --tasks {task} --algos {REFERENCE} ...`)")
            continue
        metric = metric_of(by_algo[REFERENCE])
        sac = read_eval_csv(by_algo[REFERENCE] / "eval.csv", metric)
        sac_cfg = json.loads((by_algo[REFERENCE] / "config.json").read_text())
        for algo in _order(a for a in by_algo if a != REFERENCE):
            curves = read_eval_csv(by_algo[algo] / "eval.csv", metric)
            # only steps at which SAC has begun policy training count (scores.py)
            for seed, (score, used) in task_scores(
                    curves, sac, how, min_reference, pair_by_seed,
                    after_step=sac_cfg["num_seed_steps"]).items():
                rows.append(dict(task=task, algo=algo, seed=seed, metric=metric,
                                 score=score, eval_steps_used=used))
    return rows


def score_table(rows) -> dict[str, dict[str, dict[str, float]]]:
    """{metric: {task: {algo: mean score over seeds}}}."""
    acc = defaultdict(lambda: defaultdict(lambda: defaultdict(list)))
    for r in rows:
        acc[r["metric"]][r["task"]][r["algo"]].append(r["score"])
    return {m: {t: {a: float(np.nanmean(v)) if not np.all(np.isnan(v)) else float("nan")
                    for a, v in by_algo.items()} for t, by_algo in by_task.items()}
            for m, by_task in acc.items()}


def t_tests(rows, pair_by: str = "task") -> list[dict]:
    """PRIOR against every other PbRL algorithm, over per-task mean scores (`pair_by="task"`,
    as the issue and appendix F describe) or over per-(task, seed) scores (`"seed"`)."""
    if pair_by not in ("task", "seed"):
        raise ValueError(f"--pair-by must be task or seed, got {pair_by!r}")
    units = defaultdict(lambda: defaultdict(list))
    for r in rows:
        key = (r["metric"], r["task"]) if pair_by == "task" else (r["metric"], r["task"], r["seed"])
        units[r["algo"]][key].append(r["score"])
    if METHOD not in units:
        return []
    mean = {a: {k: float(np.mean(v)) for k, v in u.items()} for a, u in units.items()}
    out = []
    for algo in _order(a for a in mean if a != METHOD):
        for metric in sorted({k[0] for k in mean[METHOD]}):
            keys = sorted(k for k in mean[METHOD] if k[0] == metric and k in mean[algo])
            t, p, n = paired_t_test([mean[algo][k] for k in keys], [mean[METHOD][k] for k in keys])
            out.append(dict(metric=metric, baseline=algo, pair_by=pair_by, pairs=n, t=t, p=p))
    return out


def reward_correlations(runs) -> list[dict]:
    """Learned-vs-true reward correlation on the replay buffer at each feedback round."""
    rows = []
    for task, by_algo in sorted(runs.items()):
        for algo, run_dir in sorted(by_algo.items()):
            for rec in _metrics(run_dir):
                if "reward/true_corr" in rec:
                    rows.append(dict(task=task, algo=algo, seed=rec["seed"], step=rec["step"],
                                     labels=rec.get("feedback/total_labeled", float("nan")),
                                     true_corr=rec["reward/true_corr"]))
    return rows


def _metrics(run_dir: Path):
    path = run_dir / "metrics.jsonl"
    if path.exists():
        yield from read_jsonl(path)


def labels_at(run_dir: Path) -> dict[int, list[tuple[int, float]]]:
    """{seed: [(step, labels used so far)]} from the feedback rounds in metrics.jsonl."""
    out = defaultdict(list)
    for rec in _metrics(run_dir):
        if "feedback/total_labeled" in rec:
            out[rec["seed"]].append((rec["step"], rec["feedback/total_labeled"]))
    return out


def _labels_used(rounds: list[tuple[int, float]], step: int) -> float:
    # a round logged at step s runs before env step s; the evaluation logged at step s ran
    # after env step s - 1, so that round had not happened yet
    done = [n for s, n in rounds if s < step]
    return max(done) if done else 0.0


def method_color(algo: str) -> str:
    """The colour of `algo` in every figure: its place in the registry's list."""
    names = registry.names()
    return f"C{names.index(algo) % 10}" if algo in names else "k"


def plot_task_curves(task: str, by_algo: dict[str, Path], out_dir: Path) -> list[Path]:
    """Mean and ±1 std over seeds per algorithm, against env steps and against labels used."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    metric = metric_of(by_algo.get(REFERENCE, next(iter(by_algo.values()))))
    ylabel = "success rate" if metric == "success" else "true episode return"
    paths = []
    for x_axis in ("steps", "labels"):
        fig, ax = plt.subplots(figsize=(6, 4))
        for algo in [REFERENCE, *_order(a for a in by_algo if a != REFERENCE)]:
            if algo not in by_algo or (x_axis == "labels" and algo == REFERENCE):
                continue
            curves = read_eval_csv(by_algo[algo] / "eval.csv", metric)
            steps = sorted(set.intersection(*(set(s.tolist()) for s, _ in curves.values())))
            if not steps:
                continue
            values = np.stack([[dict(zip(s.tolist(), v.tolist()))[t] for t in steps]
                               for s, v in curves.values()])
            if x_axis == "labels":
                rounds = labels_at(by_algo[algo])
                x = np.mean([[_labels_used(rounds[s], t) for t in steps] for s in curves], 0)
            else:
                x = np.asarray(steps)
            mean, std = values.mean(0), values.std(0)
            n = len(curves)
            color = method_color(algo)  # one colour per method in every figure
            ax.plot(x, mean, lw=1.8, color=color,
                    label=f"{algo} ({n} seed{'s' if n != 1 else ''})")
            ax.fill_between(x, mean - std, mean + std, color=color, alpha=0.15)
        ax.set_xlabel("environment steps" if x_axis == "steps" else "preference labels used")
        ax.set_ylabel(f"evaluation {ylabel}")
        if metric == "success":
            ax.set_ylim(-0.02, 1.02)  # a rate
        ax.set_title(task)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
        fig.tight_layout()
        path = save_figure(fig, out_dir / f"{task}_vs_{x_axis}.png")
        plt.close(fig)
        paths.append(path)
    return paths


def _fmt(x: float, digits: int = 2) -> str:
    return "n/a" if x is None or np.isnan(x) else f"{x:.{digits}f}"


def _write_csv(path: Path, rows: list[dict]) -> None:
    if not rows:
        path.write_text("")
        return
    with path.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)


def markdown_tables(table, tests, rows) -> str:
    lines = []
    # Table 6 (success, MetaWorld) before Table 7 (returns, DM Control), as the appendix
    for metric, by_task in sorted(table.items(), key=lambda kv: kv[0] != "success"):
        algos = _order({a for t in by_task.values() for a in t})
        seeds = {a: sorted({r["seed"] for r in rows if r["metric"] == metric
                            and r["algo"] == a}) for a in algos}
        same = len({tuple(s) for s in seeds.values()}) == 1
        which = (f"seeds {', '.join(map(str, seeds[algos[0]]))}" if same else
                 "each column's seeds (they differ: the `seeds` row counts them)")
        lines += [f"### {TABLE_NAME.get(metric, metric)}", "",
                  f"Mean over {which} of each seed's normalized score (SAC on the true "
                  "reward = 1).", "",
                  "| Env/Algorithm | " + " | ".join(a.upper() for a in algos) + " |",
                  "|---|" + "---|" * len(algos)]
        if not same:
            lines.append("| seeds | " + " | ".join(str(len(seeds[a])) for a in algos) + " |")
        for task, by_algo in sorted(by_task.items()):
            lines.append(f"| {task} | " + " | ".join(_fmt(by_algo.get(a, float("nan")))
                                                    for a in algos) + " |")
        lines.append("")
    if tests:
        lines += ["### Two-tailed paired t-tests, PRIOR against each baseline", "",
                  "t on baseline − PRIOR (negative: PRIOR higher), as appendix F reports it.", "",
                  "| metric | baseline | paired over | pairs | t | p |", "|---|---|---|---|---|---|"]
        for r in tests:
            lines.append(f"| {r['metric']} | {r['baseline']} | {r['pair_by']} | {r['pairs']} | "
                         f"{_fmt(r['t'], 3)} | {_fmt(r['p'], 4)} |")
        lines.append("")
    return "\n".join(lines)


def make_report(root: Path, out: Path | None = None, how: str = "mean-of-ratios",
                min_reference: float = 0.0, pair_by_seed: bool = False, pair_by: str = "task",
                attention: bool = True) -> Path:
    """Writes the report into `out` (default ROOT/report) and returns the Markdown path."""
    root = Path(root)
    out = Path(out) if out else root / "report"
    runs = discover(root)  # before anything is written
    (out / "curves").mkdir(parents=True, exist_ok=True)
    rows = compute_scores(runs, how, min_reference, pair_by_seed)
    table = score_table(rows)
    tests = t_tests(rows, pair_by)
    corr = reward_correlations(runs)
    _write_csv(out / "scores.csv", rows)
    for metric, by_task in table.items():
        algos = _order({a for t in by_task.values() for a in t})
        _write_csv(out / f"table_{metric}.csv",
                   [dict(task=t, **{a: by_algo.get(a, float("nan")) for a in algos})
                    for t, by_algo in sorted(by_task.items())])
    _write_csv(out / "t_tests.csv", tests)
    _write_csv(out / "reward_correlation.csv", corr)
    md = [f"# Results of {Path(root).name}", "",
          f"Normalization: {how} over the evaluation steps after SAC's random seed steps "
          "(appendix D; see "
          "hprior_jax/experiments/scores.py), SAC reference "
          f"{'of the same seed' if pair_by_seed else 'averaged over its seeds'}.", "",
          markdown_tables(table, tests, rows)]
    md += ["### Learning curves", ""]
    for task, by_algo in sorted(runs.items()):
        for path in plot_task_curves(task, by_algo, out / "curves"):
            md.append(f"![{path.stem}](curves/{path.name})")
    md.append("")
    if corr:
        md += ["### Learned vs true reward (Pearson r on the replay buffer, last round)", "",
               "| task | algo | seed | labels | r |", "|---|---|---|---|---|"]
        last = {}
        for r in corr:
            last[(r["task"], r["algo"], r["seed"])] = r
        for (task, algo, seed), r in sorted(last.items()):
            md.append(f"| {task} | {algo} | {seed} | {r['labels']:.0f} | {_fmt(r['true_corr'])} |")
        md.append("")
    if attention:
        md += _attention_section(runs, out)
    path = out / "report.md"
    path.write_text("\n".join(md) + "\n")
    return path


def _attention_section(runs, out: Path) -> list[str]:
    lines = ["### World-model attention (appendix Figure 8 style; first labelled pair)", ""]
    for task, by_algo in sorted(runs.items()):
        for algo in _order(by_algo):
            run_dir = by_algo[algo]
            if not (registry.get(algo).has_world_model and (run_dir / "checkpoints").exists()):
                continue
            where = out / "attention" / task / algo
            try:
                paths = attention_maps_for_run(run_dir, pair=0, out=where)
            except (ValueError, FileNotFoundError) as e:  # e.g. no labelled pair yet
                lines.append(f"{task} {algo}: no attention map ({e})")
                continue
            for path in paths:
                lines.append(f"![{task} {algo} {path.stem}](attention/{task}/{algo}/{path.name})")
    return lines + [""]
