"""The statistics every comparison in the project uses (host side, NumPy + scipy): means with
Student t-intervals, paired t-tests with their power, equivalence (TOST), Holm's correction
for a family of pre-registered contrasts, and a fixed-effect pool of one contrast replicated
on several datasets.

Choices:
- intervals and tests are Student t on n - 1 degrees of freedom; NaN values are dropped; with
  fewer than 2 values they are NaN.
- MDE80 is the smallest true mean difference the two-sided paired t-test at α = 0.05 detects
  with 80% power at this n, taking the observed sd of the paired differences as the true one
  (exact under normal differences: a noncentral t, not the optimistic normal approximation).
- "no difference" is claimed only by TOST: both one-sided tests at α reject |Δ| >= margin,
  i.e. the 90% t-interval lies inside (-margin, +margin).
- Holm's step-down correction controls the family-wise error of the contrasts named before a
  lab ran; each adjusted p is compared with α directly.
- a share (one contrast's mean as a fraction of another's on the same seeds, e.g. of the
  oracle's headroom) is the ratio of the two means with a paired BCa bootstrap interval
  (10,000 resamples of the seeds, a fixed stream): a ratio has no t-interval. Only where the
  other contrast's t-interval lies above 0.
- pooling: the inverse-variance weighted mean of each dataset's mean paired difference
  (fixed effect; the datasets are replications of one contrast, not a sample of tasks).
"""
from __future__ import annotations

import math

import numpy as np
from scipy import optimize, stats

LEVEL = 0.95
ALPHA = 0.05
TARGET_POWER = 0.80
NAN = float("nan")


def _clean(values) -> np.ndarray:
    x = np.asarray(values, dtype=float)
    return x[~np.isnan(x)]


def mean_ci(values, level: float = LEVEL) -> tuple[float, float, float, int]:
    """(mean, lo, hi, n) of the non-NaN `values` with a Student t-interval at `level`."""
    x = _clean(values)
    n = int(x.size)
    if n == 0:
        return NAN, NAN, NAN, 0
    mean = float(x.mean())
    if n < 2:
        return mean, NAN, NAN, n
    # written out rather than stats.t.interval, which gives NaN when all values are equal
    half_width = stats.t.ppf((1 + level) / 2, n - 1) * x.std(ddof=1) / math.sqrt(n)
    return mean, float(mean - half_width), float(mean + half_width), n


def paired_t_test(baseline, other) -> tuple[float, float, int]:
    """Two-tailed paired t-test with dependent means (the paper's appendix F): (t, p, pairs).
    t is computed on baseline − other, the sign the appendix reports (negative where `other`
    scores higher). NaN pairs are dropped; with fewer than 2 pairs t and p are NaN."""
    a, b = np.asarray(baseline, float), np.asarray(other, float)
    if a.shape != b.shape:
        raise ValueError(f"paired samples differ in length: {a.shape} vs {b.shape}")
    keep = ~(np.isnan(a) | np.isnan(b))
    d = a[keep] - b[keep]
    n = int(d.size)
    if n < 2:
        return NAN, NAN, n
    sd = d.std(ddof=1)
    if sd == 0:
        t = 0.0 if d.mean() == 0 else float(np.copysign(np.inf, d.mean()))
    else:
        t = float(d.mean() / (sd / np.sqrt(n)))
    return t, float(2 * stats.t.sf(abs(t), n - 1)), n


def paired_power(effect: float, sd: float, n: int, alpha: float = ALPHA) -> float:
    """Probability that the two-sided paired t-test at `alpha` rejects on n pairs whose
    differences are normal with true mean `effect` and sd `sd` (NaN when n < 2 or sd <= 0)."""
    if n < 2 or not sd > 0:
        return NAN
    df = n - 1
    critical = stats.t.ppf(1 - alpha / 2, df)
    noncentrality = effect * math.sqrt(n) / sd
    return float(stats.nct.sf(critical, df, noncentrality)
                 + stats.nct.cdf(-critical, df, noncentrality))


def minimum_detectable_effect(sd: float, n: int, power: float = TARGET_POWER,
                              alpha: float = ALPHA) -> float:
    """Smallest true mean difference (> 0) that the two-sided paired t-test at `alpha` detects
    with probability `power` on n pairs of sd `sd`. NaN when n < 2 or sd is not positive."""
    if n < 2 or not sd > 0:
        return NAN

    def shortfall(effect_in_sds: float) -> float:
        return paired_power(effect_in_sds, 1.0, n, alpha) - power

    upper = 1.0
    while shortfall(upper) < 0:  # power grows with the effect: widen until it brackets
        upper *= 2
        if upper > 1e3:  # at 2-3 seeds the noncentral t gives NaN before 80% power
            return NAN
    if math.isnan(shortfall(upper)):
        return NAN
    return float(sd * optimize.brentq(shortfall, 0.0, upper))


def tost_p(differences, margin: float) -> float:
    """p of the paired two one-sided tests that the true mean difference lies inside
    (-margin, +margin): the larger of the two one-sided p values (NaN when n < 2, the sd is 0
    or the margin is not positive)."""
    d = _clean(differences)
    n = int(d.size)
    if n < 2 or not margin > 0 or not d.std(ddof=1) > 0:
        return NAN
    se = d.std(ddof=1) / math.sqrt(n)
    p_low = stats.t.sf((d.mean() + margin) / se, n - 1)  # H0: mean <= -margin
    p_high = stats.t.cdf((d.mean() - margin) / se, n - 1)  # H0: mean >= +margin
    return float(max(p_low, p_high))


def holm(p_values) -> list[float]:
    """Holm-adjusted p values of a family, in the given order (NaN stays NaN and does not
    count towards the family's size)."""
    p = np.asarray(p_values, dtype=float)
    adjusted = np.full(p.shape, NAN)
    finite = np.flatnonzero(~np.isnan(p))
    order = finite[np.argsort(p[finite], kind="stable")]
    m, running = len(order), 0.0
    for rank, i in enumerate(order):
        running = max(running, min(1.0, (m - rank) * p[i]))
        adjusted[i] = running
    return adjusted.tolist()


def paired_comparison(reference_by_seed: dict[int, float],
                      other_by_seed: dict[int, float]) -> dict:
    """Other − reference on the seeds both have, NaN pairs dropped: {n, diff, diff_lo,
    diff_hi, p, sd, mde80} (95% t-interval, two-sided paired t-test, MDE at 80% power)."""
    seeds = sorted(set(reference_by_seed) & set(other_by_seed))
    reference = np.asarray([reference_by_seed[s] for s in seeds], dtype=float)
    other = np.asarray([other_by_seed[s] for s in seeds], dtype=float)
    differences = other - reference  # NaN where either is; mean_ci and the test drop those
    diff, lo, hi, n = mean_ci(differences)
    _, p, _ = paired_t_test(reference, other)
    sd = float(np.nanstd(differences, ddof=1)) if n >= 2 else NAN
    return {"n": n, "diff": diff, "diff_lo": lo, "diff_hi": hi, "p": p, "sd": sd,
            "mde80": minimum_detectable_effect(sd, n)}


def share_ci(differences, reference, level: float = LEVEL) -> tuple[float, float, float]:
    """(share, lo, hi): mean(differences) / mean(reference), both paired over the same seeds
    (pairs with a NaN dropped), with a BCa bootstrap interval at `level` that resamples seeds;
    NaN when fewer than 3 pairs are left or the reference's 95% t-interval does not lie above
    0 (no room shown to take a share of: a share of a near-zero mean is any number)."""
    d, r = np.asarray(differences, dtype=float), np.asarray(reference, dtype=float)
    keep = ~(np.isnan(d) | np.isnan(r))
    d, r = d[keep], r[keep]
    if d.size < 3 or not mean_ci(r)[1] > 0:
        return NAN, NAN, NAN
    ratio = lambda x, y, axis=-1: x.mean(axis) / y.mean(axis)
    ci = stats.bootstrap((d, r), ratio, paired=True, vectorized=True, n_resamples=10_000,
                         confidence_level=level, method="BCa",
                         random_state=np.random.default_rng(0)).confidence_interval
    return float(d.mean() / r.mean()), float(ci.low), float(ci.high)


def pooled_difference(comparisons: list[dict]) -> dict:
    """The fixed-effect pool of `paired_comparison`s of one contrast on several datasets:
    {n_datasets, diff, diff_lo, diff_hi, p} (a normal interval on the weighted mean; the
    weights are 1 / se², se = sd / √n of each dataset)."""
    usable = [c for c in comparisons if c["n"] >= 2 and c["sd"] > 0]
    if not usable:
        return {"n_datasets": 0, "diff": NAN, "diff_lo": NAN, "diff_hi": NAN, "p": NAN}
    weights = np.array([c["n"] / c["sd"] ** 2 for c in usable])
    diffs = np.array([c["diff"] for c in usable])
    mean = float((weights * diffs).sum() / weights.sum())
    se = float(1 / math.sqrt(weights.sum()))
    z = stats.norm.ppf((1 + LEVEL) / 2)
    return {"n_datasets": len(usable), "diff": mean, "diff_lo": mean - z * se,
            "diff_hi": mean + z * se, "p": float(2 * stats.norm.sf(abs(mean) / se))}


def verdict(a: str, n: int, diff: float, p_holm: float, tost_p_holm: float, margin: float,
            mde80: float) -> str:
    """The words of a pre-registered contrast A − B: "A higher" / "A lower" where its
    Holm-adjusted p < ALPHA; "equivalent within ±margin" where its Holm-adjusted TOST p <
    ALPHA; otherwise "not detected" (with the MDE80 this n had), never "no difference";
    "not testable" with fewer than 2 pairs."""
    if n < 2:
        return "not testable"
    if p_holm < ALPHA:
        return f"{a} {'higher' if diff > 0 else 'lower'}"
    if tost_p_holm < ALPHA:
        return f"equivalent within ±{margin:.3f}"
    return "not detected" + (f" (MDE80 {mde80:.3f})" if np.isfinite(mde80) else "")

