"""Learning-curve plots from a run directory's eval.csv (host side)."""
from __future__ import annotations

import json
import textwrap
from collections import defaultdict
from pathlib import Path

import numpy as np

from hprior_jax.run_log import read_eval_rows


def read_eval_csv(path: Path, column: str = "true_return"):
    """{seed: (steps[], values[])} from eval.csv."""
    per_seed = defaultdict(list)
    header, *rows = read_eval_rows(path)
    for row in (dict(zip(header, r)) for r in rows):
        if row[column] != "":
            per_seed[int(row["seed"])].append((int(row["step"]), float(row[column])))
    return {s: tuple(map(np.asarray, zip(*sorted(v)))) for s, v in per_seed.items()}


def returns_summary(eval_csv: Path) -> str:
    """One line per evaluation step: the true return's mean over seeds (and its range over
    seeds when there are several), the success rate beside it where the task has one."""
    def by_step(column):
        values = defaultdict(list)
        for steps, per_seed in read_eval_csv(eval_csv, column).values():
            for step, value in zip(steps, per_seed):
                values[int(step)].append(value)
        return values

    returns, rates = by_step("true_return"), by_step("success")
    lines = []
    for step in sorted(returns):
        v = np.asarray(returns[step])
        line = f"  step {step:>8}: return {v.mean():8.1f}"
        if len(v) > 1:
            line += f" (seeds {v.min():.1f} to {v.max():.1f})"
        if rates[step]:
            line += f", success {np.mean(rates[step]):.0%}"
        lines.append(line)
    return "\n".join(lines)


def plot_learning_curve(eval_csv: Path, out_png: Path, title: str = "") -> Path:
    """Each seed thin, the mean over seeds bold with a +-1 std band (where steps align):
    the true return, and beside it the success rate where the task has one (MetaWorld)."""
    panels = [("true_return", "evaluation true return")]
    if read_eval_csv(eval_csv, "success"):
        panels.insert(0, ("success", "evaluation success rate"))
    # a Figure of its own, not pyplot's global state: the grid writes curves from threads
    from matplotlib.figure import Figure  # ~1 s to import: only when a curve is drawn

    fig = Figure(figsize=(6 * len(panels), 4))
    axes = fig.subplots(1, len(panels), squeeze=False)
    for ax, (column, ylabel) in zip(axes[0], panels):
        _plot_seeds(ax, read_eval_csv(eval_csv, column), ylabel)
    fig.suptitle(title)
    if read_eval_csv(eval_csv, "success"):
        axes[0][0].set_ylim(-0.02, 1.02)  # a rate
    fig.tight_layout()
    return save_figure(fig, out_png)


def wrapped(title: str, width: int = 60) -> str:
    """A title broken into lines that fit the figure (a long one is clipped otherwise)."""
    return "\n".join(textwrap.wrap(title, width))


def save_figure(fig, path: Path, dpi: int = 120, **kwargs) -> Path:
    """Saves `fig` as a PNG whose text chunks say what it shows ("Title" and, as JSON in
    "Description", each axes' title, axis labels, y range, legend entries, labelled lines'
    colours and position): what a reader or a test can check without looking."""
    axes = [dict(title=ax.get_title(), xlabel=ax.get_xlabel(), ylabel=ax.get_ylabel(),
                 ylim=[float(v) for v in ax.get_ylim()],
                 legend=[t.get_text() for t in ax.get_legend().get_texts()]
                 if ax.get_legend() else [],
                 lines={line.get_label(): line.get_color() for line in ax.get_lines()
                        if not line.get_label().startswith("_")},
                 position=[round(float(v), 4) for v in ax.get_position().bounds])
            for ax in fig.get_axes()]
    title = fig._suptitle.get_text() if fig._suptitle else (axes[0]["title"] if axes else "")
    fig.savefig(path, dpi=dpi, metadata={"Title": title, "Description": json.dumps(axes)},
                **kwargs)
    return Path(path)


def _plot_seeds(ax, curves: dict, ylabel: str) -> None:
    for seed, (steps, values) in sorted(curves.items()):
        ax.plot(steps, values, lw=0.8, alpha=0.5, label=f"seed {seed}")
    if len(curves) > 1:
        common = sorted(set.intersection(*(set(s.tolist()) for s, _ in curves.values())))
        if common:
            stacked = np.stack([[dict(zip(s.tolist(), v.tolist()))[c] for c in common]
                                for s, v in curves.values()])
            mean, std = stacked.mean(0), stacked.std(0)
            ax.plot(common, mean, color="k", lw=2, label="mean")
            ax.fill_between(common, mean - std, mean + std, color="k", alpha=0.15)
    ax.set_xlabel("environment steps")
    ax.set_ylabel(ylabel)
    ax.grid(alpha=0.3)
    if curves:
        ax.legend(fontsize=7)
