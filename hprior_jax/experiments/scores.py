"""Normalized scores and the paired t-test of appendix D and F (pure NumPy, host side).

Appendix D, eqs. 6-7, write the normalized return as (1/T) Σ_t r(π_PbRL) / r(π_PbRL): the
numerator and the denominator are the same expression, a typo. The text around them says
what is meant, and that is what `normalized_score` computes: at each evaluation step t, the
PbRL policy's true return (DMC) or success rate (MetaWorld) divided by that of SAC trained
on the true reward at the same step, averaged over the evaluation steps of training.

T counts "policy training steps": evaluation steps at which the SAC reference has not yet
trained (its uniform-random seed steps, 5000 in BPref) are left out (`after_step`); there
SAC's return is that of an untrained policy and the ratio measures nothing (at 5000 steps
on cheetah_run SAC returns 0.1 and PEBBLE, already pre-trained, 30: a ratio of 300).

Three further choices the appendix leaves open, made here and exposed as arguments:
- the SAC reference at step t is the mean over the SAC run's seeds (`reference_curve`); the
  alternative, each PbRL seed over the SAC run of the same seed, is `pair_by_seed=True` in
  `task_scores`.
- a step where the reference is not positive (SAC success 0 early in MetaWorld) has no
  ratio and is left out of the average (`min_reference`); `how="ratio-of-means"`
  (Σ_t PbRL / Σ_t SAC) is the robust variant for curves that start near zero.
"""
from __future__ import annotations

import numpy as np

HOW = ("mean-of-ratios", "ratio-of-means")

Curve = tuple  # (steps[int], values[float]) of one seed


def reference_curve(curves: dict[int, Curve]) -> Curve:
    """Mean over seeds at the steps every seed evaluated."""
    if not curves:
        raise ValueError("no reference (SAC) curves: run --algo sac on the task first")
    common = sorted(set.intersection(*(set(np.asarray(s).tolist()) for s, _ in curves.values())))
    if not common:
        raise ValueError("the reference seeds share no evaluation step")
    values = np.stack([_at(c, common) for c in curves.values()])
    return np.asarray(common), values.mean(0)


def _at(curve: Curve, steps) -> np.ndarray:
    lookup = dict(zip(np.asarray(curve[0]).tolist(), np.asarray(curve[1]).tolist()))
    return np.asarray([lookup[s] for s in steps], dtype=float)


def normalized_score(curve: Curve, reference: Curve, how: str = "mean-of-ratios",
                     min_reference: float = 0.0, after_step: int = 0) -> tuple[float, int]:
    """(score, number of evaluation steps it averages) of one PbRL seed's `curve` against
    the SAC `reference`, over the steps after `after_step` that both evaluated. NaN when no
    step qualifies."""
    if how not in HOW:
        raise ValueError(f"unknown normalization {how!r}; available: {', '.join(HOW)}")
    steps = sorted(s for s in set(np.asarray(curve[0]).tolist())
                   & set(np.asarray(reference[0]).tolist()) if s > after_step)
    if not steps:
        return float("nan"), 0
    ours, ref = _at(curve, steps), _at(reference, steps)
    if how == "ratio-of-means":
        total = ref.sum()
        return (float(ours.sum() / total) if total > min_reference else float("nan")), len(steps)
    keep = ref > min_reference
    if not keep.any():
        return float("nan"), 0
    return float(np.mean(ours[keep] / ref[keep])), int(keep.sum())


def task_scores(pbrl: dict[int, Curve], sac: dict[int, Curve], how: str = "mean-of-ratios",
                min_reference: float = 0.0, pair_by_seed: bool = False,
                after_step: int = 0) -> dict[int, tuple[float, int]]:
    """{seed: (normalized score, steps used)} of one (task, PbRL algorithm)."""
    out = {}
    shared = reference_curve(sac) if not pair_by_seed else None
    for seed, curve in sorted(pbrl.items()):
        if pair_by_seed:
            if seed not in sac:
                raise ValueError(f"pair_by_seed: the SAC run has no seed {seed}; run it "
                                 "with the same --seeds or drop pair_by_seed")
            ref = (np.asarray(sac[seed][0]), np.asarray(sac[seed][1], dtype=float))
        else:
            ref = shared
        out[seed] = normalized_score(curve, ref, how, min_reference, after_step)
    return out
