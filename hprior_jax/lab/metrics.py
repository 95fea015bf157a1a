"""Reward quality on held-out data, from a learned reward's predictions r̂ of every held-out
state (host side, NumPy + scipy):

  heldout_accuracy  fraction of the fixed held-out segment pairs whose predicted returns
                    order them as the oracle does (a tie in predicted return counts as wrong)
  pearson,          correlation of r̂ with the true reward over every held-out state
  spearman
  kendall_tau       Kendall τ-b between predicted and true returns of the held-out episodes
  episode_pearson   Pearson of r̂ and r each demeaned per held-out episode: credit *within*
                    an episode, which the metrics above barely see (they are dominated by
                    getting each episode's level right)
  segment_rank      mean over the held-out pairs' segments of the Spearman correlation of r̂_t
                    and r_t within the segment (segments whose true reward is constant are
                    left out; a constant r̂ there scores 0): does the reward order a
                    segment's steps as the true one does?

`uniform_credit_ceiling` bounds what uniform credit (RVAR) can reach on a dataset.
"""
from __future__ import annotations

import numpy as np
from scipy import stats

METRICS = ("heldout_accuracy", "pearson", "spearman", "kendall_tau", "episode_pearson",
           "segment_rank")
NAN = float("nan")


def segment_returns(reward: np.ndarray, episodes: np.ndarray, starts: np.ndarray,
                    length: int) -> np.ndarray:
    """Σ of reward[e, s:s+length] for every (episode e, start s), in float64."""
    cum = np.concatenate([np.zeros((reward.shape[0], 1)),
                          np.cumsum(reward, axis=1, dtype=np.float64)], axis=1)
    return cum[episodes, starts + length] - cum[episodes, starts]


def _pearson(a: np.ndarray, b: np.ndarray) -> float:
    a, b = a.ravel().astype(np.float64), b.ravel().astype(np.float64)
    if np.ptp(a) == 0 or np.ptp(b) == 0:  # a collapsed reward has no correlation
        return NAN
    return float(stats.pearsonr(a, b)[0])


def episode_pearson(pred: np.ndarray, true: np.ndarray) -> float:
    """Pearson of pred and true [E, L], each demeaned per episode (row)."""
    demean = lambda x: x - x.mean(1, keepdims=True, dtype=np.float64)
    return _pearson(demean(pred), demean(true))


def segment_rank(pred: np.ndarray, true: np.ndarray, pair_index: np.ndarray,
                 length: int) -> float:
    """Mean within-segment Spearman of pred and true over both segments of every pair."""
    episodes = np.concatenate([pair_index[:, 0], pair_index[:, 2]])
    starts = np.concatenate([pair_index[:, 1], pair_index[:, 3]])
    steps = starts[:, None] + np.arange(length)
    p = stats.rankdata(pred[episodes[:, None], steps], axis=1)
    t = stats.rankdata(true[episodes[:, None], steps], axis=1)
    p, t = p - p.mean(1, keepdims=True), t - t.mean(1, keepdims=True)
    norm = np.sqrt((p ** 2).sum(1) * (t ** 2).sum(1))
    varies = (t ** 2).sum(1) > 0
    if not varies.any():
        return NAN
    rho = np.where(norm > 0, (p * t).sum(1) / np.where(norm > 0, norm, 1.0), 0.0)
    return float(rho[varies].mean())


def reward_quality(pred: np.ndarray, true: np.ndarray, pair_index: np.ndarray,
                   pair_label: np.ndarray, segment_len: int) -> dict[str, float]:
    """pred, true: [E, L] rewards of the held-out episodes; pairs as in lab.dataset."""
    p1 = segment_returns(pred, pair_index[:, 0], pair_index[:, 1], segment_len)
    p2 = segment_returns(pred, pair_index[:, 2], pair_index[:, 3], segment_len)
    predicted = np.where(p2 > p1, 1, np.where(p1 > p2, 0, -1))
    constant = np.ptp(pred) == 0
    return {
        "heldout_accuracy": float(np.mean(predicted == pair_label)),
        "pearson": _pearson(pred, true),
        "spearman": NAN if constant else float(stats.spearmanr(pred.ravel(),
                                                               true.ravel())[0]),
        "kendall_tau": float(stats.kendalltau(pred.sum(1, dtype=np.float64),
                                              true.sum(1, dtype=np.float64))[0]),
        "episode_pearson": episode_pearson(pred, true),
        "segment_rank": segment_rank(pred, true, pair_index, segment_len),
    }


def moving_mean(x: np.ndarray, window: int) -> np.ndarray:
    """The centred moving mean of each row of x [E, L] over `window` steps, truncated at the
    episode's ends (each step averages the steps of its window that exist)."""
    cum = np.concatenate([np.zeros((x.shape[0], 1)), np.cumsum(x, 1, dtype=np.float64)], 1)
    t = np.arange(x.shape[1])
    lo = np.clip(t - window // 2, 0, x.shape[1])
    hi = np.clip(t - window // 2 + window, 0, x.shape[1])
    return (cum[:, hi] - cum[:, lo]) / (hi - lo)


def uniform_credit_ceiling(true: np.ndarray, segment_len: int) -> dict[str, float]:
    """What uniform credit could reach at best on held-out rewards true [E, L]: the Pearson
    (over all states, and within episodes) of the true reward with its own `segment_len`-step
    moving mean, the smoothest reward that segment returns pin down."""
    smooth = moving_mean(true, segment_len)
    return {"pearson": _pearson(smooth, true), "episode_pearson": episode_pearson(smooth, true)}


METRIC_LABEL = {
    "heldout_accuracy": "held-out preference accuracy",
    "pearson": "Pearson r with the true reward",
    "spearman": "Spearman rank correlation with the true reward",
    "kendall_tau": "Kendall tau with the true reward",
    "episode_pearson": "within-episode Pearson r with the true reward",
    "segment_rank": "within-segment rank agreement with the true reward",
}
