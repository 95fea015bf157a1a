"""Reward quality on held-out data, from a learned reward's predictions r̂ of every held-out
state (host side, NumPy + scipy):

  heldout_accuracy  fraction of the fixed held-out segment pairs whose predicted returns
                    order them as the oracle does (a tie in predicted return counts as wrong)
  pearson,          correlation of r̂ with the true reward over every held-out state
  spearman
  kendall_tau       Kendall τ-b between predicted and true returns of the held-out episodes
"""
from __future__ import annotations

import numpy as np
from scipy import stats

METRICS = ("heldout_accuracy", "pearson", "spearman", "kendall_tau")


def segment_returns(reward: np.ndarray, episodes: np.ndarray, starts: np.ndarray,
                    length: int) -> np.ndarray:
    """Σ of reward[e, s:s+length] for every (episode e, start s), in float64."""
    cum = np.concatenate([np.zeros((reward.shape[0], 1)),
                          np.cumsum(reward, axis=1, dtype=np.float64)], axis=1)
    return cum[episodes, starts + length] - cum[episodes, starts]


def reward_quality(pred: np.ndarray, true: np.ndarray, pair_index: np.ndarray,
                   pair_label: np.ndarray, segment_len: int) -> dict[str, float]:
    """pred, true: [E, L] rewards of the held-out episodes; pairs as in lab.dataset."""
    p1 = segment_returns(pred, pair_index[:, 0], pair_index[:, 1], segment_len)
    p2 = segment_returns(pred, pair_index[:, 2], pair_index[:, 3], segment_len)
    predicted = np.where(p2 > p1, 1, np.where(p1 > p2, 0, -1))
    flat_pred, flat_true = pred.ravel().astype(np.float64), true.ravel().astype(np.float64)
    constant = np.ptp(flat_pred) == 0  # a collapsed reward has no correlation
    nan = float("nan")
    return {
        "heldout_accuracy": float(np.mean(predicted == pair_label)),
        "pearson": nan if constant else float(stats.pearsonr(flat_pred, flat_true)[0]),
        "spearman": nan if constant else float(stats.spearmanr(flat_pred, flat_true)[0]),
        "kendall_tau": float(stats.kendalltau(pred.sum(1, dtype=np.float64),
                                              true.sum(1, dtype=np.float64))[0]),
    }
