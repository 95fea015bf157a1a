"""The shared statistics (TOST, Holm, pooling) and the lab's pre-registered contrasts,
against values written out here or computed another way."""
import math

import numpy as np
import pytest
from scipy import stats

from hprior_jax.lab.contrasts import Contrast, evaluate, pooled
from hprior_jax.statistics import holm, pooled_difference, share_ci, tost_p


def test_holm_by_hand():
    # sorted 0.01, 0.02, 0.04 -> 3*0.01, max(.03, 2*0.02), max(.04, 1*0.04); NaN left out
    assert holm([0.04, 0.01, float("nan"), 0.02]) == pytest.approx(
        [0.04, 0.03, float("nan"), 0.04], nan_ok=True)
    assert holm([0.5, 0.6]) == pytest.approx([1.0, 1.0])


def test_tost_is_the_larger_one_sided_p_and_the_90_interval_inside_the_margin():
    d = np.array([0.01, -0.02, 0.015, 0.0, 0.005, -0.01, 0.02, 0.0])
    se = d.std(ddof=1) / math.sqrt(d.size)
    p = tost_p(d, 0.03)
    want = max(stats.t.sf((d.mean() + 0.03) / se, 7), stats.t.cdf((d.mean() - 0.03) / se, 7))
    assert p == pytest.approx(want)
    lo, hi = stats.t.interval(0.90, 7, loc=d.mean(), scale=se)
    assert (p < 0.05) == (-0.03 < lo and hi < 0.03)
    assert tost_p(d, 0.005) > 0.05  # a margin inside the noise: not equivalent
    assert math.isnan(tost_p(d, 0.0)) and math.isnan(tost_p([0.1], 0.5))


def test_pooled_difference_weights_by_inverse_variance():
    a = {"n": 10, "diff": 0.1, "sd": 0.1}
    b = {"n": 10, "diff": 0.0, "sd": 0.2}
    out = pooled_difference([a, b])
    w = np.array([10 / 0.01, 10 / 0.04])
    assert out["diff"] == pytest.approx((w * [0.1, 0.0]).sum() / w.sum())
    half = stats.norm.ppf(0.975) / math.sqrt(w.sum())
    assert out["diff_hi"] - out["diff"] == pytest.approx(half)
    assert out["n_datasets"] == 2


def test_a_share_is_the_ratio_of_paired_means_with_an_interval_that_resamples_seeds():
    rng = np.random.default_rng(1)
    reference = rng.normal(0.2, 0.02, 10)
    part = 0.5 * reference + rng.normal(0, 0.01, 10)
    share, lo, hi = share_ci(part, reference)
    assert share == pytest.approx(part.mean() / reference.mean())
    assert lo < share < hi and 0.4 < lo and hi < 0.6
    # a noisier part: a wider interval; no room (reference mean <= 0) or < 3 pairs: NaN
    _, lo2, hi2 = share_ci(0.5 * reference + rng.normal(0, 0.05, 10), reference)
    assert hi2 - lo2 > hi - lo
    assert math.isnan(share_ci(part, -reference)[0]) and math.isnan(share_ci([1, 2], [1, 1])[0])
    # a reference whose interval reaches 0 (mean > 0, but not shown to be): no share either
    noisy = np.tile([0.11, -0.09], 5)  # mean +0.01, its interval about ±0.07
    assert math.isnan(share_ci(part, noisy)[0])
    # the interval is the same on a second call (a fixed stream)
    assert share_ci(part, reference) == (share, lo, hi)


def test_contrasts_parse_margins():
    assert Contrast.parse("a:b") == Contrast("a", "b")
    assert Contrast.parse("a~shift:b@0.02").margin == 0.02
    assert Contrast.parse("a:b@c~shift:d/2").margin_of == ("c~shift", "d", 2.0)
    with pytest.raises(ValueError):
        Contrast.parse("ab")


def test_contrasts_are_holm_corrected_and_an_equivalence_needs_its_margin():
    rng = np.random.default_rng(0)
    seeds = range(12)
    base = rng.normal(0.5, 0.05, 12)
    cell = lambda shift: {s: {"m": base[s] + shift[s]} for s in seeds}
    wiggle = np.tile([0.004, -0.004], 6)  # mean 0, sd 0.004: equal within a 0.1 margin
    by_cell = {("t", "ref", 10): cell(np.zeros(12)), ("t", "top", 10): cell(0.2 + wiggle),
               ("t", "a", 10): cell(wiggle), ("t", "b", 10): cell(np.zeros(12))}
    out = evaluate(by_cell, [Contrast.parse("top:ref"), Contrast.parse("a:b@top:ref/2")],
                   ["m"])
    top, eq = out
    assert top["verdict"] == "top higher"
    assert [top["p_holm"], eq["p_holm"]] == pytest.approx(holm([top["p"], eq["p"]]))
    assert eq["p_holm"] >= eq["p"] and top["p_holm"] == pytest.approx(2 * top["p"])
    assert eq["margin"] == pytest.approx(np.mean([by_cell[("t", "top", 10)][s]["m"]
                                                  - by_cell[("t", "ref", 10)][s]["m"]
                                                  for s in seeds]) / 2)
    assert eq["verdict"].startswith("equivalent within")
    # a's share of top − ref: about 0 (its mean difference is 0), inside its interval
    assert eq["share_of"] == "top − ref" and abs(eq["share"]) < 1e-9
    assert eq["share_lo"] < eq["share"] < eq["share_hi"]
    assert math.isnan(top["share"])  # no reference contrast, no share
    # the same two rules without a margin: at best "not detected"
    alone = evaluate(by_cell, [Contrast.parse("a:b")], ["m"])[0]
    assert alone["verdict"].startswith("not detected")
    assert pooled(out) == []  # one task: nothing to pool


def test_a_margin_from_a_reference_contrast_without_headroom_tests_no_equivalence():
    seeds = range(6)
    by_cell = {("t", r, 10): {s: {"m": v + 0.01 * s} for s in seeds}
               for r, v in (("ref", 0.5), ("top", 0.4), ("a", 0.45), ("b", 0.45))}
    (eq,) = evaluate(by_cell, [Contrast.parse("a:b@top:ref/2")], ["m"])
    assert math.isnan(eq["margin"]) and eq["verdict"].startswith("not detected")
