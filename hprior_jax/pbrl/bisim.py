"""BISIM baseline: a bisimulation auxiliary loss on the reward model (appendix G.2, eq. 8).

    J_bisim = (‖z_i − z_j‖_1 − sg(|r_i − r_j| + γ ‖ẑ'_i − ẑ'_j‖_2))²
    J_trans = mean_h (ẑ'_i − sg(z_{i+1}))²
    L       = Σ_k [ CE_k + λ · (mean_{real pairs} J_bisim,k + mean_{real transitions} J_trans,k) ]

adapted by the paper from Kemertas & Aumentado-Armstrong (2021), eq. 4. States come from the
replay buffer (the trajectory buffer PRIOR also reads), not from the labelled segments.

Decisions (one reason each):
- Per member k: z = member k's last hidden activation (the input of its final Dense(1)), r = its
  r̂(s, a), ẑ' = its `next_embedding` head on z (`RewardConfig.next_embedding_head`). Each
  member is its own reward model, as in the CE and PRIOR's term.
- The bisimulation target |r_i − r_j| + γ‖ẑ'_i − ẑ'_j‖_2 is under stop_gradient, as in DBC
  (Zhang et al. 2021), whose bisim loss detaches the reward and transition distances: only
  ‖z_i − z_j‖_1 carries gradient. Consequence: the final Dense(1) gets no gradient from this
  term (z does not depend on it and r is detached); the CE alone trains it.
- The head is trained by J_trans against the next step's embedding (stopped): eq. 8 alone never
  moves it (it only appears in the stopped target).
- Pairs (i, j): each transition with the next one of the same member's flattened minibatch
  (a roll by one, cyclic). The rows arrive in a random order per member, so this is a random
  pairing. A pair is real when both its transitions are (minibatch mask and `valid`).
- Reduction: per member, the mean over real pairs of J_bisim plus the mean over real
  transitions of J_trans, summed over members like the CE (so λ does not scale with K);
  unweighted, λ weighs the sum.
"""
from __future__ import annotations

import flax.struct
import jax
import jax.numpy as jnp

from hprior_jax.buffers import episodes
from hprior_jax.buffers.replay import ReplayState
from hprior_jax.networks.reward_ensemble import RewardConfig, per_member_embeddings
from hprior_jax.pbrl.preference import RewardTerm


@flax.struct.dataclass
class BisimTransitions:
    """m buffer transitions per stored-pair row: obs, next_obs [C, m, ds], act, next_act
    [C, m, da], valid bool [C, m] (C = the preference store's capacity, so `train_epoch`
    gathers them with the pairs' per-member indices)."""

    obs: jax.Array
    act: jax.Array
    next_obs: jax.Array
    next_act: jax.Array
    valid: jax.Array


def sample_transitions(key: jax.Array, buf: ReplayState, episode_len: int, capacity: int,
                       per_row: int) -> BisimTransitions:
    """capacity * per_row transitions drawn uniformly (with replacement) from the stored steps
    that are not the last of their episode; (next_obs, next_act) = row i + 1.

    Assumes the preference-based runs' buffer layout: whole fixed-length episodes in order from
    row 0, never wrapped, so row i + 1 follows row i unless (i + 1) % episode_len == 0 (the last
    step of an episode) or i + 1 >= size (the episode in progress). valid is False when the
    buffer holds fewer than 2 steps, and also at a true termination (not_done[i] == 0; none in
    fixed-length tasks), where row i + 1 would start another episode."""
    if episode_len < 2:
        raise ValueError(f"episode_len={episode_len}: a transition needs an episode of 2 steps")
    i, any_step = episodes.rows_with_next(key, buf.size, episode_len, (capacity, per_row),
                                          buf.capacity)
    valid = any_step & (buf.not_done[i] > 0)
    return BisimTransitions(obs=buf.obs[i], act=buf.action[i], next_obs=buf.obs[i + 1],
                            next_act=buf.action[i + 1], valid=valid)


def bisim_loss(params, rows: BisimTransitions, mask: jax.Array, *, reward_cfg: RewardConfig,
               discount: float) -> tuple[jax.Array, dict]:
    """rows leaves [K, b, m, ...] (each member its own rows), mask [b] (real minibatch rows)
    -> (Σ_k loss_k, {"bisimulation": [K], "transition": [K]}), loss_k = bisim_k + transition_k."""
    k = reward_cfg.ensemble_size
    # One forward pass over (s, a) and (s', a') per member: [K, b, 2m, ...].
    obs = jnp.concatenate([rows.obs, rows.next_obs], axis=2)
    act = jnp.concatenate([rows.act, rows.next_act], axis=2)
    r, z, z_pred = per_member_embeddings(params, obs, act, reward_cfg)
    m = rows.obs.shape[2]
    flat = lambda x: x.reshape((k, -1) + x.shape[3:])  # [K, b, m, ...] -> [K, b*m, ...]
    z_next = flat(z[:, :, m:])  # embedding of (s', a')
    r, z, z_pred = flat(r[:, :, :m]), flat(z[:, :, :m]), flat(z_pred[:, :, :m])
    w = flat(mask[None, :, None] & rows.valid).astype(jnp.float32)  # real transitions [K, b*m]

    # Partner j of transition i: the next one of the member's flattened minibatch (cyclic); the
    # rows come in a per-member random order, so this is a random pairing.
    roll = lambda x: jnp.roll(x, -1, axis=1)
    z_dist = jnp.abs(z - roll(z)).sum(-1)  # ‖z_i − z_j‖_1, carries the gradient
    # Target under stop_gradient (DBC); the transition distance is the L2 norm of eq. 8. sqrt of a
    # sum is safe here: no gradient is taken through it.
    target = jax.lax.stop_gradient(
        jnp.abs(r - roll(r)) + discount * jnp.sqrt(jnp.sum((z_pred - roll(z_pred)) ** 2, -1)))
    w_pair = w * roll(w)
    bisim = ((z_dist - target) ** 2 * w_pair).sum(-1) / jnp.maximum(w_pair.sum(-1), 1.0)

    # The head learns to predict the next step's embedding (a fixed target for this loss).
    trans = jnp.mean((z_pred - jax.lax.stop_gradient(z_next)) ** 2, axis=-1)
    transition = (trans * w).sum(-1) / jnp.maximum(w.sum(-1), 1.0)
    return (bisim + transition).sum(), {"bisimulation": bisim, "transition": transition}


def bisim_term(lam, transitions: BisimTransitions, *, reward_cfg: RewardConfig,
               discount: float) -> RewardTerm:
    """The BISIM loss as a reward term of `train_reward`: name "bisim/loss", weight λ (a float
    or a traced scalar), data = `transitions` (leaves [C, m, ...], C = the store's capacity).
    `reward_cfg` must have `next_embedding_head=True` (and the params the head)."""
    if not reward_cfg.next_embedding_head:
        raise ValueError("bisim_term needs RewardConfig(next_embedding_head=True)")

    def loss(step_r1, step_r2, rows: BisimTransitions, mask, params):
        return bisim_loss(params, rows, mask, reward_cfg=reward_cfg, discount=discount)[0]

    return RewardTerm(name="bisim/loss", weight=lam, loss=loss, data=transitions)
