"""The B-Pref scripted teacher (BPref `reward_model.py#L372-L422`, `train_PEBBLE.py#L232-L279`).

Labels follow BPref: 1 = segment 2 preferred, 0 = segment 1 preferred, -1 = equally preferable.
For a batch of pairs with true per-step rewards r1[B, T], r2[B, T]:

1. R = Σ_t r_t (undiscounted). Skip (only if thres_skip > 0): keep pairs with max(R1, R2) > thres_skip.
2. Equal mask: |R1 - R2| < thres_equal (undiscounted sums).
3. Myopic sums R̃ = Σ_t γ^(T-1-t) r_t (the last step has weight 1).
4. β > 0 finite: y ~ Bernoulli(softmax([βR̃1, βR̃2])[1]); else y = 1[R̃1 < R̃2] (a tie gives 0).
5. Mistake: flip y with probability ε_mistake. 6. y = -1 on the equal mask.

Skipped pairs still get a label here; `valid` is False for them and the preference store drops
them (BPref removes them from the batch, which static shapes cannot do).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import flax.struct
import jax
import jax.numpy as jnp


@dataclass(frozen=True)
class TeacherConfig:
    """Knobs of the B-Pref teacher. Defaults = the oracle."""

    beta: float = -1.0  # rationality; <= 0 or inf = perfectly rational (deterministic)
    gamma: float = 1.0  # myopia discount, applied backwards from the last step
    eps_mistake: float = 0.0  # probability of flipping a label
    eps_skip: float = 0.0  # skip threshold = eps_skip * margin
    eps_equal: float = 0.0  # equal threshold = eps_equal * margin
    # BPref bug (train_PEBBLE.py#L275-L276 + reward_model.py#L152-L156): after the first round
    # the caller passes margin*eps and the setter multiplies by eps again, so the thresholds are
    # eps^2 * margin. Not copied by default; True reproduces it.
    bpref_squared_eps: bool = False
    # A person answers instead (`--teacher human`, `hprior_jax.labelling.teacher`): the knobs
    # above are unused; the person's "can't tell" and "equally good" are B-Pref's skip and
    # equal labels.
    human: bool = False

    @property
    def deterministic(self) -> bool:
        return self.beta <= 0 or math.isinf(self.beta)


# BPref README and scripts/*/<teacher>/run_PEBBLE.sh.
ORACLE = TeacherConfig()
NOISY = TeacherConfig(beta=1.0)  # "stoch" teacher
MISTAKE = TeacherConfig(eps_mistake=0.1)
SKIP = TeacherConfig(eps_skip=0.1)
MYOPIC = TeacherConfig(gamma=0.9)
EQUAL = TeacherConfig(eps_equal=0.1)
HUMAN = TeacherConfig(human=True)
PRESETS = {"oracle": ORACLE, "noisy": NOISY, "stoch": NOISY, "mistake": MISTAKE,
           "skip": SKIP, "myopic": MYOPIC, "equal": EQUAL, "human": HUMAN}


@flax.struct.dataclass
class TeacherThresholds:
    """Absolute return thresholds for one query round (scalars; pytree so they can be traced)."""

    skip: jax.Array
    equal: jax.Array


@flax.struct.dataclass
class TeacherOutput:
    labels: jax.Array  # [B] int32 in {-1, 0, 1}
    valid: jax.Array  # [B] bool, False where skipped
    equal: jax.Array  # [B] bool, equal-preference mask (labels == -1 there)
    mistake: jax.Array  # [B] bool, where the label was flipped by eps_mistake


def compute_thresholds(cfg: TeacherConfig, mean_episode_return: jax.Array, segment_len: int,
                       max_episode_len: int, first_round: bool | jax.Array = True) -> TeacherThresholds:
    """margin = mean true return of the last <= 10 training episodes * H / T_max
    (T_max = 1000 DMC, 500 MetaWorld): an average per-segment return (train_PEBBLE.py#L232-L279).
    thresholds = eps * margin; with `cfg.bpref_squared_eps`, eps^2 * margin after the first round."""
    margin = jnp.asarray(mean_episode_return, jnp.float32) * (segment_len / max_episode_len)
    later = jnp.logical_not(jnp.asarray(first_round)) & cfg.bpref_squared_eps

    def thres(eps):
        return jnp.where(later, eps * eps * margin, eps * margin)

    return TeacherThresholds(skip=thres(cfg.eps_skip), equal=thres(cfg.eps_equal))


def myopic_weights(segment_len: int, gamma: float) -> jax.Array:
    """[T] weights γ^(T-1-t): BPref multiplies the prefix [:i+1] by γ for i = 0..T-2."""
    return jnp.asarray(gamma, jnp.float32) ** jnp.arange(segment_len - 1, -1, -1, dtype=jnp.float32)


def teacher_labels(key: jax.Array, true_rewards_1: jax.Array, true_rewards_2: jax.Array,
                   cfg: TeacherConfig = ORACLE,
                   thresholds: TeacherThresholds | None = None) -> TeacherOutput:
    """Label B pairs from their true per-step rewards [B, T]. `thresholds` default: both 0."""
    r1 = true_rewards_1.astype(jnp.float32)
    r2 = true_rewards_2.astype(jnp.float32)
    if thresholds is None:
        thresholds = TeacherThresholds(skip=jnp.zeros(()), equal=jnp.zeros(()))
    sum1, sum2 = r1.sum(-1), r2.sum(-1)

    # Skip only if the threshold is positive (BPref `if self.teacher_thres_skip > 0`).
    valid = (thresholds.skip <= 0) | (jnp.maximum(sum1, sum2) > thresholds.skip)
    equal = jnp.abs(sum1 - sum2) < thresholds.equal

    w = myopic_weights(r1.shape[-1], cfg.gamma)
    m1, m2 = (r1 * w).sum(-1), (r2 * w).sum(-1)

    k_bt, k_mis = jax.random.split(key)
    if cfg.deterministic:
        labels = (m1 < m2).astype(jnp.int32)
    else:
        p2 = jax.nn.sigmoid(cfg.beta * (m2 - m1))  # softmax([βR̃1, βR̃2])[1]
        labels = jax.random.bernoulli(k_bt, p2).astype(jnp.int32)

    mistake = jax.random.uniform(k_mis, labels.shape) < cfg.eps_mistake
    labels = jnp.where(mistake, 1 - labels, labels)
    labels = jnp.where(equal, -1, labels)
    return TeacherOutput(labels=labels, valid=valid, equal=equal, mistake=mistake)
