"""Learning-curve plots from a run directory's eval.csv (host side)."""
from __future__ import annotations

import csv
from collections import defaultdict
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


def read_eval_csv(path: Path, column: str = "true_return"):
    """{seed: (steps[], values[])} from eval.csv."""
    per_seed = defaultdict(list)
    with Path(path).open() as f:
        for row in csv.DictReader(f):
            if row[column] != "":
                per_seed[int(row["seed"])].append((int(row["step"]), float(row[column])))
    return {s: tuple(map(np.asarray, zip(*sorted(v)))) for s, v in per_seed.items()}


def plot_learning_curve(eval_csv: Path, out_png: Path, title: str = "",
                        column: str = "true_return") -> Path:
    """Each seed thin, the mean over seeds bold with a +-1 std band (where steps align)."""
    curves = read_eval_csv(eval_csv, column)
    fig, ax = plt.subplots(figsize=(6, 4))
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
    ax.set_ylabel("evaluation " + column.replace("_", " "))
    ax.set_title(title)
    ax.grid(alpha=0.3)
    if curves:
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out_png, dpi=120)
    plt.close(fig)
    return Path(out_png)
