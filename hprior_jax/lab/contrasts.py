"""Pre-registered contrasts of a lab: rule A − rule B, named before the lab runs, tested as a
family with Holm's correction, and, where a margin is given, for equivalence (TOST).

A contrast is written `A:B` or `A:B@MARGIN`, MARGIN a number or `C:D/K`: the mean of contrast
C − D at the same (task, metric, budget) divided by K (e.g. "half the oracle's headroom":
`prior~shift:positional~shift@oracle~shift:rvar/2`); where that mean is not positive there is
no headroom to be within, and no equivalence is tested. The family of a metric is every
contrast at every budget (and task) of that metric, so each adjusted p answers "is this one
of the named differences real?" at α over all of them.

Verdicts: "A higher"/"A lower" when the Holm-adjusted p < α; "equivalent within ±m" when the
TOST p (Holm-adjusted within the contrasts that have a margin) < α; otherwise "not detected"
(with MDE80, what this n could have detected), never "no difference". A contrast whose margin
is another contrast's (`C:D/K`) also reports its share of C − D (`statistics.share_ci`).
"""
from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass

import numpy as np

from hprior_jax import statistics
from hprior_jax.statistics import NAN, holm, paired_comparison, pooled_difference, tost_p


@dataclass(frozen=True)
class Contrast:
    a: str
    b: str
    margin: float | None = None  # a fixed equivalence margin
    margin_of: tuple[str, str, float] | None = None  # (C, D, K): mean(C − D) / K

    @property
    def name(self) -> str:
        return f"{self.a} − {self.b}"

    @staticmethod
    def parse(text: str) -> "Contrast":
        pair, at, margin = text.partition("@")
        a, colon, b = pair.partition(":")
        if not colon or not a or not b:
            raise ValueError(f"contrast {text!r}: write A:B or A:B@MARGIN")
        if not at:
            return Contrast(a, b)
        try:
            return Contrast(a, b, margin=float(margin))
        except ValueError:
            pass
        of, slash, k = margin.partition("/")
        c, colon, d = of.partition(":")
        try:
            return Contrast(a, b, margin_of=(c, d, float(k) if slash else 1.0))
        except ValueError:
            raise ValueError(f"contrast {text!r}: MARGIN is a number or C:D/K") from None


def _differences(cell_a: dict[int, float], cell_b: dict[int, float]) -> np.ndarray:
    seeds = sorted(set(cell_a) & set(cell_b))
    return np.asarray([cell_a[s] - cell_b[s] for s in seeds], dtype=float)


def evaluate(by_cell: dict, contrasts: list[Contrast], metrics: list[str]) -> list[dict]:
    """`by_cell` {(task, rule, budget): {seed: {metric: value}}} -> one dict per (contrast,
    task, metric, budget) both rules ran: the paired comparison, the margin, the TOST p and
    the Holm-adjusted p's, and the verdict."""
    out = []
    for metric in metrics:
        value = lambda cell: {s: float(row.get(metric, NAN)) for s, row in cell.items()}
        family = []
        for contrast in contrasts:
            for task, rule, budget in sorted(by_cell):
                if rule != contrast.a or (task, contrast.b, budget) not in by_cell:
                    continue
                a = value(by_cell[(task, contrast.a, budget)])
                b = value(by_cell[(task, contrast.b, budget)])
                c = paired_comparison(b, a)
                margin = contrast.margin
                share, share_of = (NAN, NAN, NAN), ""
                if contrast.margin_of is not None:
                    x, y, k = contrast.margin_of
                    margin = NAN  # no reference contrast, or one <= 0: nothing to be within
                    if (task, x, budget) in by_cell and (task, y, budget) in by_cell:
                        cx = value(by_cell[(task, x, budget)])
                        cy = value(by_cell[(task, y, budget)])
                        headroom = float(np.nanmean(_differences(cx, cy))) / k
                        margin = headroom if headroom > 0 else NAN
                        seeds = sorted(set(a) & set(b) & set(cx) & set(cy))
                        share_of = f"{x} − {y}"
                        share = statistics.share_ci([a[s] - b[s] for s in seeds],
                                                    [cx[s] - cy[s] for s in seeds])
                tost = tost_p(_differences(a, b), margin) if margin is not None else NAN
                family.append({"contrast": contrast.name, "task": task, "metric": metric,
                               "budget": budget, **c,
                               "margin": NAN if margin is None else margin,
                               "tost_p": tost, "share_of": share_of,
                               **dict(zip(("share", "share_lo", "share_hi"), share))})
        for key, adjusted in (("p", "p_holm"), ("tost_p", "tost_p_holm")):
            for entry, p in zip(family, holm([e[key] for e in family])):
                entry[adjusted] = p
        for entry in family:
            entry["verdict"] = verdict(entry)
        out += family
    return out


def verdict(e: dict) -> str:
    return statistics.verdict(e["contrast"].split(" − ")[0], e["n"], e["diff"], e["p_holm"],
                              e["tost_p_holm"], e["margin"], e["mde80"])


def pooled(results: list[dict]) -> list[dict]:
    """Each (contrast, metric, budget) replicated on several tasks, pooled (fixed effect)."""
    groups = defaultdict(list)
    for e in results:
        groups[(e["contrast"], e["metric"], e["budget"])].append(e)
    return [{"contrast": c, "metric": m, "budget": b,
             "tasks": ",".join(e["task"] for e in entries), **pooled_difference(entries)}
            for (c, m, b), entries in groups.items() if len(entries) > 1]
