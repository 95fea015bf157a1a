"""The lab report's figures: each metric against the label budget, one line per rule."""
from __future__ import annotations

from pathlib import Path

from hprior_jax.lab.metrics import METRIC_LABEL
from hprior_jax.plotting import save_figure, wrapped


def png_name(task: str, metric: str) -> str:
    return f"{task}_{metric}.png"


def plot_metric(entries: list[dict], out_png: Path, title: str) -> Path:
    """Mean over seeds against the label budget, one line per rule, its 95% CI shaded."""
    from matplotlib.figure import Figure  # ~1 s to import: only when a figure is drawn

    fig = Figure(figsize=(6, 4))
    ax = fig.subplots()
    for rule in dict.fromkeys(e["rule"] for e in entries):
        points = [e for e in entries if e["rule"] == rule]  # budget-sorted by summarize
        budgets = [e["budget"] for e in points]
        (line,) = ax.plot(budgets, [e["mean"] for e in points], marker="o", label=rule)
        ax.fill_between(budgets, [e["ci_lo"] for e in points], [e["ci_hi"] for e in points],
                        color=line.get_color(), alpha=0.2)
    budgets = sorted({e["budget"] for e in entries})
    if budgets[0] > 0 and budgets[-1] > 4 * budgets[0]:
        ax.set_xscale("log")
        ax.minorticks_off()
    ax.set_xticks(budgets, [str(b) for b in budgets])  # ticks at the budgets that were run
    ax.set_xlabel("preference labels")
    ax.set_ylabel(METRIC_LABEL[entries[0]["metric"]])
    ax.set_title(wrapped(title), fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return save_figure(fig, out_png)
