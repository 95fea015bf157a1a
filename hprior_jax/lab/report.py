"""Report of a reward-learning lab: how well reward models learned by several labelling rules
match the true reward, against the reference rule PEBBLE, at several label budgets.

The lab's raw results are rows, one per (task, rule, budget, seed), holding the reward-quality
metrics of `METRICS` measured on held-out data (other columns are carried along, not used).
`write_report` turns them into summary.csv, results.csv, one plot per (task, metric) and
report.md; `hprior reward-lab report RESULTS_CSV OUT_DIR` rebuilds all of it
from a saved results.csv (several RESULTS_CSV: one report of several labs, `merge_results`).

Statistical choices:
- a mean over seeds comes with a Student t-interval (n - 1 degrees of freedom); NaN values are
  dropped, and with fewer than 2 values the interval is NaN.
- each rule is compared with pebble at the same task and budget by a two-sided paired t-test
  on the seeds both ran (seed s against seed s), with a t-interval on the mean paired
  difference (rule - pebble).
- a difference the test does not detect is reported with MDE80, the smallest true mean
  difference the test detects with 80% power at alpha 0.05 for this n, taking the observed sd
  of the paired differences as the true one. Power is exact under normal differences (the
  t statistic follows a noncentral t), not the normal approximation, which is optimistic at
  few seeds.
"""
from __future__ import annotations

import csv
import math
from collections import defaultdict
from pathlib import Path

import numpy as np

from hprior_jax.lab import contrasts as contrast_tests
from hprior_jax.lab.metrics import METRIC_LABEL, METRICS
from hprior_jax.lab.report_figures import plot_metric, png_name
from hprior_jax.lab.rules import REFERENCE
from hprior_jax.statistics import ALPHA, NAN, mean_ci, paired_comparison

DEFAULT_TITLE = "Reward-learning lab"
MIN_PAIRED = 3  # paired seeds below which no direction is called


def rule_order(rows) -> list[str]:
    """Rules in the order they first appear, the reference first."""
    rules = list(dict.fromkeys(row["rule"] for row in rows))
    if REFERENCE in rules:
        rules.remove(REFERENCE)
        rules.insert(0, REFERENCE)
    return rules


def _cells(rows) -> dict[tuple[str, str, int], dict[int, dict]]:
    """{(task, rule, budget): {seed: row}}. Pairing needs one row per seed, so a repeated
    (task, rule, budget, seed) is an error."""
    cells: dict[tuple[str, str, int], dict[int, dict]] = defaultdict(dict)
    for row in rows:
        cell = cells[(row["task"], row["rule"], int(row["budget"]))]
        seed = int(row["seed"])
        if seed in cell:
            raise ValueError(f"two rows for task {row['task']!r}, rule {row['rule']!r}, "
                             f"budget {row['budget']}, seed {seed}")
        cell[seed] = row
    return cells


def _by_seed(cell: dict[int, dict], metric: str) -> dict[int, float]:
    return {seed: float(row.get(metric, NAN)) for seed, row in cell.items()}


def summarize(rows) -> list[dict]:
    """One dict per (task, rule, budget, metric): n, mean, ci_lo, ci_hi and, for rules other
    than pebble, the `paired_comparison` with pebble as vs_pebble_* fields. Sorted by task,
    metric (in `METRICS` order), budget, rule (`rule_order`)."""
    cells = _cells(rows)
    rules = rule_order(rows)
    metrics = [m for m in METRICS if any(m in row for row in rows)]
    summary = []
    for task in sorted({task for task, _, _ in cells}):
        budgets = sorted({budget for t, _, budget in cells if t == task})
        for metric in metrics:
            for budget in budgets:
                reference = _by_seed(cells.get((task, REFERENCE, budget), {}), metric)
                for rule in rules:
                    if (task, rule, budget) not in cells:
                        continue
                    values = _by_seed(cells[(task, rule, budget)], metric)
                    mean, lo, hi, n = mean_ci(list(values.values()))
                    entry = {"task": task, "metric": metric, "budget": budget, "rule": rule,
                             "n": n, "mean": mean, "ci_lo": lo, "ci_hi": hi}
                    if rule != REFERENCE and REFERENCE in rules:
                        comparison = paired_comparison(reference, values)
                        entry.update({f"vs_pebble_{k}": v for k, v in comparison.items()})
                    summary.append(entry)
    return summary


def _write_csv(path: Path, rows) -> None:
    """Columns in the order they first appear; a row without a column leaves it blank."""
    fields = list(dict.fromkeys(key for row in rows for key in row))
    with path.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=fields, restval="")
        writer.writeheader()
        writer.writerows(rows)


def read_results(path: Path) -> list[dict]:
    """Raw rows from a results.csv: budget and seed as int, the metrics as float (blank ->
    NaN); other columns stay text, so that writing them again reproduces the file."""
    rows = []
    with Path(path).open(newline="") as f:
        for row in csv.DictReader(f):
            row["budget"], row["seed"] = int(row["budget"]), int(row["seed"])
            for metric in METRICS:
                if metric in row:
                    row[metric] = float(row[metric]) if row[metric] != "" else NAN
            rows.append(row)
    return rows


def merge_results(paths, tags=None) -> tuple[list[dict], int]:
    """The rows of several results.csv as one lab's (labs of one dataset and seeds, e.g. one
    per world model, their rules tagged apart). `tags`, one per path, renames every rule of
    that lab RULE[TAG] ("" keeps the names): labs that differ in a setting every rule shares
    (`--one-shot`, `--feed`), so that `--pairs pebble[one-shot]:pebble` compares them. A
    (task, rule, budget, seed) row found again in a later file (the reference rule, run by
    every lab) is dropped: the first file's is kept. -> (rows, how many of the dropped rows
    differed from the kept one in a metric)."""
    tags = [""] * len(paths) if tags is None else list(tags)
    if len(tags) != len(paths):
        raise ValueError(f"{len(tags)} tags for {len(paths)} results.csv: give one per file")
    kept, differing = {}, 0
    for path, tag in zip(paths, tags):
        for row in read_results(path):
            if tag:
                row["rule"] = f"{row['rule']}[{tag}]"
            key = (row["task"], row["rule"], row["budget"], row["seed"])
            if key not in kept:
                kept[key] = row
            elif any(not np.isclose(kept[key][m], row[m], atol=1e-6, equal_nan=True)
                     for m in METRICS if m in row):
                differing += 1
    return list(kept.values()), differing


def _comparison_of(entry: dict) -> dict:
    """The paired comparison stored in a summary entry, without the vs_pebble_ prefix."""
    prefix = "vs_pebble_"
    return {k[len(prefix):]: v for k, v in entry.items() if k.startswith(prefix)}


def _p_text(p: float) -> str:
    return "p < 0.001" if p < 0.001 else f"p = {p:.2g}"


def _mean_cell(entry: dict) -> str:
    return f"{entry['mean']:.3f} [{entry['ci_lo']:.3f}, {entry['ci_hi']:.3f}]"


def _difference_text(c: dict) -> str:
    if c["n"] < 2:
        return f"not testable, n={c['n']}"
    return (f"{c['diff']:+.3f} [{c['diff_lo']:.3f}, {c['diff_hi']:.3f}], {_p_text(c['p'])}, "
            f"n={c['n']}, MDE80={c['mde80']:.3f}")


def _difference_cell(entry: dict) -> str:
    return _difference_text(_comparison_of(entry))


def _sentence(rule: str, versus: str, budget: int, c: dict) -> str:
    head = f"{rule} − {versus} at {budget} labels"
    if c["n"] < MIN_PAIRED:  # at n = 2 a t-test calls a -0.001 "lower" when both agree
        return f"{head}: not testable (n = {c['n']} paired seeds; {MIN_PAIRED} needed)"
    estimate = (f"{c['diff']:+.3f} [{c['diff_lo']:.3f}, {c['diff_hi']:.3f}] "
                f"({_p_text(c['p'])}, n = {c['n']})")
    if c["p"] < ALPHA:
        direction = "higher" if c["diff"] > 0 else "lower"
        return f"{head}: {estimate}: {rule} {direction} than {versus}"
    # MDE80 is NaN only when every paired difference is identical (sd 0).
    detectable = (f"; this n detects ≥ {c['mde80']:.3f} with 80% power"
                  if math.isfinite(c["mde80"]) else "")
    return f"{head}: {estimate}: no difference detected{detectable}"


def comparison_sentence(entry: dict) -> str:
    """Plain-language reading of one comparison with pebble; a difference the test does not
    detect is stated as such, with the smallest difference this n would have detected."""
    return _sentence(entry["rule"], REFERENCE, entry["budget"], _comparison_of(entry))


def pair_comparisons(rows, pairs) -> list[dict]:
    """The paired comparison of rule A − rule B for each (A, B) in `pairs`, at every (task,
    metric, budget) both ran: dicts of task, metric, budget, rule (A), versus (B) and
    `paired_comparison`'s fields. E.g. (prior, positional): does the world model's α beat
    its own mean profile?"""
    cells = _cells(rows)
    metrics = [m for m in METRICS if any(m in row for row in rows)]
    out = []
    for a, b in pairs:
        for task, rule, budget in sorted(cells):
            if rule != a or (task, b, budget) not in cells:
                continue
            for metric in metrics:
                c = paired_comparison(_by_seed(cells[(task, b, budget)], metric),
                                      _by_seed(cells[(task, a, budget)], metric))
                out.append({"task": task, "metric": metric, "budget": budget, "rule": a,
                            "versus": b, **c})
    missing = [f"{a}:{b}" for a, b in pairs
               if not any(e["rule"] == a and e["versus"] == b for e in out)]
    if missing:
        raise ValueError(f"pairs {missing}: both rules must have run at some budget")
    return out


def _table(entries: list[dict], cell) -> list[str]:
    """Markdown table, rows = rules, columns = budgets."""
    budgets = sorted({e["budget"] for e in entries})
    by_key = {(e["rule"], e["budget"]): e for e in entries}
    lines = ["| rule | " + " | ".join(f"{b} labels" for b in budgets) + " |",
             "|---" * (len(budgets) + 1) + "|"]
    for rule in dict.fromkeys(e["rule"] for e in entries):
        cells = [cell(by_key[(rule, b)]) if (rule, b) in by_key else "–" for b in budgets]
        lines.append(f"| {rule} | " + " | ".join(cells) + " |")
    return lines


def _method_line(rows) -> str:
    seed_counts = sorted({len(cell) for cell in _cells(rows).values()})
    seeds = (f"{seed_counts[0]}" if len(seed_counts) == 1
             else f"{seed_counts[0]}–{seed_counts[-1]}")
    line = (f"{seeds} seeds per (task, rule, budget). Each cell is the mean over seeds with "
            "its 95% Student t-interval (NaN values dropped).")
    differences = (f"Differences vs {REFERENCE} are rule − {REFERENCE}"
                   if any(row["rule"] == REFERENCE for row in rows) else "Differences are")
    return (f"{line} {differences} on the seeds both ran, with a 95% t-interval and a "
            f"two-sided paired t-test (a difference is called higher/lower only at p < {ALPHA}); "
            "MDE80 is the smallest true difference that test detects with 80% power at this n "
            "and the observed sd of the paired differences (noncentral t).")


def _by_task_metric(summary: list[dict]) -> dict[tuple[str, str], list[dict]]:
    """Summary entries grouped by (task, metric), keeping the summary's order."""
    groups: dict[tuple[str, str], list[dict]] = defaultdict(list)
    for entry in summary:
        groups[(entry["task"], entry["metric"])].append(entry)
    return groups


def _pairs_markdown(pairs: list[dict]) -> list[str]:
    lines = ["## Paired differences between rules", ""]
    for (task, metric), entries in _by_task_metric(pairs).items():
        lines += [f"### {task}: {METRIC_LABEL[metric]}", ""]
        named = [{**e, "rule": f"{e['rule']} − {e['versus']}"} for e in entries]
        lines += _table(named, _difference_text) + [""]
        lines += [f"- {_sentence(e['rule'], e['versus'], e['budget'], e)}"
                  for e in entries] + [""]
    return lines


def _contrasts_markdown(results: list[dict], pools: list[dict]) -> list[str]:
    lines = ["## Pre-registered contrasts", "",
             "Named before the lab ran. Holm's correction over every contrast and budget of a "
             "metric (p_holm); equivalence by TOST within the stated margin (its p Holm-"
             "corrected over the contrasts with a margin); 'not detected' is not 'no "
             "difference'.", ""]
    for (task, metric), entries in _by_task_metric(results).items():
        lines += [f"### {task}: {METRIC_LABEL[metric]}", "",
                  "| contrast | labels | difference [95% CI] | p | p_holm | margin | "
                  "TOST p_holm | verdict |", "|---|---|---|---|---|---|---|---|"]
        for e in entries:
            margin = "–" if not math.isfinite(e["margin"]) else f"±{e['margin']:.3f}"
            tost = "–" if not math.isfinite(e["tost_p_holm"]) else f"{e['tost_p_holm']:.3g}"
            lines.append(f"| {e['contrast']} | {e['budget']} | {e['diff']:+.3f} "
                         f"[{e['diff_lo']:.3f}, {e['diff_hi']:.3f}] | {e['p']:.3g} | "
                         f"{e['p_holm']:.3g} | {margin} | {tost} | {e['verdict']} |")
        lines.append("")
        lines += [f"- {e['contrast']} at {e['budget']} labels as a share of {e['share_of']}: "
                  f"{e['share']:+.2f} [{e['share_lo']:.2f}, {e['share_hi']:.2f}] "
                  "(ratio of means, BCa bootstrap over seeds)"
                  for e in entries if math.isfinite(e.get("share", NAN))]
        if lines[-1] != "":
            lines.append("")
    if pools:
        lines += ["### Pooled over tasks (fixed effect, inverse-variance weights)", "",
                  "| contrast | metric | labels | tasks | difference [95% CI] | p |",
                  "|---|---|---|---|---|---|"]
        lines += [f"| {e['contrast']} | {e['metric']} | {e['budget']} | {e['tasks']} | "
                  f"{e['diff']:+.3f} [{e['diff_lo']:.3f}, {e['diff_hi']:.3f}] | {e['p']:.3g} |"
                  for e in pools] + [""]
    return lines


def _markdown(rows, summary: list[dict], title: str, pairs: list[dict] = (),
              contrasts: list[dict] = (), pools: list[dict] = (), notes=(),
              figures: bool = True) -> str:
    lines = [f"# {title}", ""] + [f"{note}\n" for note in notes] + [_method_line(rows), ""]
    if contrasts:
        lines += _contrasts_markdown(contrasts, pools)
    current_task = None
    for (task, metric), entries in _by_task_metric(summary).items():
        if task != current_task:
            lines += [f"## {task}", ""]
            current_task = task
        label = METRIC_LABEL[metric]
        lines += [f"### {label}", ""]
        if figures:
            lines += [f"![{task}: {label}]({png_name(task, metric)})", ""]
        lines += _table(entries, _mean_cell) + [""]
        comparisons = [e for e in entries if "vs_pebble_n" in e]
        if comparisons:
            lines += [f"Paired differences vs {REFERENCE}:", ""]
            lines += _table(comparisons, _difference_cell) + [""]
            lines += [f"- {comparison_sentence(e)}" for e in comparisons] + [""]
    if pairs:
        lines += _pairs_markdown(pairs)
    return "\n".join(lines)


def write_report(rows, out_dir, title: str = DEFAULT_TITLE, pairs=(), contrasts=(),
                 notes=(), figures: bool = True) -> Path:
    """Writes summary.csv, results.csv (the raw rows), <task>_<metric>.png and report.md to
    `out_dir`; with `pairs` ((rule A, rule B), ...) pairs.csv and a section of A − B; with
    `contrasts` (`contrasts.Contrast`s or their text) contrasts.csv and the pre-registered
    section first (Holm, TOST, pooled over tasks); `notes`: paragraphs under the title (a
    warning the reader must see); `figures=False`: no PNGs and no links to them (a results
    folder that keeps only the tables). Returns the path of report.md."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    summary = summarize(rows)
    _write_csv(out_dir / "results.csv", rows)
    _write_csv(out_dir / "summary.csv", summary)
    compared = pair_comparisons(rows, pairs)
    if compared:
        _write_csv(out_dir / "pairs.csv", compared)
    named = [c if isinstance(c, contrast_tests.Contrast) else contrast_tests.Contrast.parse(c)
             for c in contrasts]
    metrics = [m for m in METRICS if any(m in row for row in rows)]
    tested = contrast_tests.evaluate(_cells(rows), named, metrics) if named else []
    pools = contrast_tests.pooled(tested)
    if tested:
        _write_csv(out_dir / "contrasts.csv", tested + pools)
    for (task, metric), entries in _by_task_metric(summary).items() if figures else ():
        plot_metric(entries, out_dir / png_name(task, metric),
                    f"{title}: {task}, {METRIC_LABEL[metric]}")
    report = out_dir / "report.md"
    report.write_text(_markdown(rows, summary, title, compared, tested, pools, notes, figures))
    return report
