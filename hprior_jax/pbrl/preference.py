"""Bradley-Terry preference loss and PEBBLE's reward-training schedule.

BPref `reward_model.py#L601-L718` (`train_reward`, `train_soft_reward`), `train_PEBBLE.py#L155-L165`:
- P_i[σ1 ≻ σ2] = softmax([R̂_i(σ1), R̂_i(σ2)])[0] with R̂_i(σ) = Σ_t r̂_i(s_t, a_t) (sums, no temperature).
- Labels: 1 = σ2 preferred, 0 = σ1 preferred, -1 = equal (target 0.5/0.5, as `train_soft_reward`).
  Optional `label_margin` m: target one_hot·(1-2m) + m.
- Minibatch loss = Σ_members (batch-mean cross-entropy of that member); one Adam step per minibatch.
- An epoch = one pass over all stored pairs in minibatches of 128, with an independent shuffle per
  member. Up to `max_epochs` epochs; stop early once the epoch's mean accuracy over members > 0.97.

Everything is pure and shape-static: the label store has a fixed capacity and a `count`; padding is
masked, and the last partial minibatch is a masked mean over its real pairs (as BPref's short batch).
`tx` (an optax GradientTransformation) and the configs are static: close over them or pass them
with functools.partial before jit.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import jax
import jax.numpy as jnp
import optax

from hprior_jax.buffers.preferences import PreferenceBatch, PreferenceStore
from hprior_jax.networks.reward_ensemble import (Params, RewardConfig, member_rewards,
                                                 per_member_rewards)


GRAD_RATIO_STREAM = 0x67726164  # folded off a round's key: its epochs draw what they drew


@dataclass(frozen=True)
class PreferenceConfig:
    batch_size: int = 128  # BPref `train_batch_size`, hard-coded
    max_epochs: int = 50  # BPref `reward_update` (config 200; scripts: 50 DMC, 10 MetaWorld)
    acc_threshold: float = 0.97  # early stop when mean train accuracy over members > this
    label_margin: float = 0.0  # BPref `label_margin` (soft targets)
    lr: float = 3e-4  # BPref `reward_lr` (Table 3: 3e-4 MetaWorld, 5e-4 walker/cheetah, 1e-4 quadruped)


@dataclass(frozen=True)
class RewardTerm:
    """An auxiliary reward-learning loss: the update minimises CE + Σ weight · loss.

    `loss(step_r1[K, b, T], step_r2[K, b, T], rows, mask[b], params) -> scalar` is unweighted
    (and logged so); `rows` are the minibatch's rows of `data`, a pytree whose leaves have the
    preference store's leading capacity axis, gathered with the same per-member indices
    ([K, b, ...]); `params` are the ensemble parameters being trained (a term that reads the
    networks' insides, e.g. an embedding, differentiates through them). `weight` may be a
    traced scalar (a pytree leaf of the run state), so a sweep over it is vmapped, not
    recompiled."""

    name: str  # its metric key, e.g. "prior/loss"
    weight: Any
    loss: Callable
    data: Any = None


def make_optimizer(cfg: PreferenceConfig = PreferenceConfig()) -> optax.GradientTransformation:
    """One Adam over the stacked ensemble == PyTorch's single Adam over all members (eps 1e-8)."""
    return optax.adam(cfg.lr, b1=0.9, b2=0.999, eps=1e-8)


def preference_targets(labels: jax.Array, label_margin: float = 0.0) -> jax.Array:
    """Target probability that σ2 is preferred: label 0 -> m, 1 -> 1-m, -1 (equal) -> 0.5."""
    hard = labels.astype(jnp.float32) * (1.0 - 2.0 * label_margin) + label_margin
    return jnp.where(labels < 0, 0.5, hard)


def bt_loss_from_returns(ret1: jax.Array, ret2: jax.Array, labels: jax.Array,
                         mask: jax.Array | None = None, label_margin: float = 0.0):
    """Bradley-Terry CE from segment returns.

    ret1, ret2: [K, B] predicted segment returns per member; labels [B] or [K, B]; mask likewise
    (True = real pair). Returns (loss = Σ_k masked-mean CE_k, per-member loss [K],
    per-member correct count [K], number of real pairs per member [K]).

    Accuracy copies BPref: predicted = argmax([R̂1, R̂2]) (a tie predicts σ1) compared with the
    label, where equal labels (-1) count as label 0 (BPref sets them to 0 before the comparison).
    """
    labels = jnp.broadcast_to(labels, ret1.shape)
    mask = jnp.ones(ret1.shape, bool) if mask is None else jnp.broadcast_to(mask, ret1.shape)
    target = preference_targets(labels, label_margin)
    logits = jnp.stack([ret1, ret2], axis=-1)
    logp = jax.nn.log_softmax(logits, axis=-1)
    ce = -((1.0 - target) * logp[..., 0] + target * logp[..., 1])
    w = mask.astype(jnp.float32)
    n = w.sum(-1)
    per_member = (ce * w).sum(-1) / jnp.maximum(n, 1.0)
    predicted = (ret2 > ret1).astype(jnp.int32)
    correct = ((predicted == jnp.maximum(labels, 0)) & mask).sum(-1)
    return per_member.sum(), per_member, correct, n


def segment_returns(params: Params, obs: jax.Array, act: jax.Array,
                    reward_cfg: RewardConfig = RewardConfig()) -> jax.Array:
    """obs[B, T, ds], act[B, T, da] -> R̂[K, B] (every member on the same segments)."""
    return member_rewards(params, obs, act, reward_cfg).sum(-1)


def preference_probs(params: Params, obs1, act1, obs2, act2,
                     reward_cfg: RewardConfig = RewardConfig()) -> jax.Array:
    """P_i[σ1 ≻ σ2] per member: [K, B] (BPref `p_hat_member`)."""
    r1 = segment_returns(params, obs1, act1, reward_cfg)
    r2 = segment_returns(params, obs2, act2, reward_cfg)
    return jax.nn.sigmoid(r1 - r2)


def preference_loss(params: Params, batch: PreferenceBatch, mask: jax.Array | None = None,
                    reward_cfg: RewardConfig = RewardConfig(), label_margin: float = 0.0):
    """BT loss with every member on the same batch (obs*[B, T, ds]). Returns (loss, aux dict)."""
    r1 = segment_returns(params, batch.obs1, batch.act1, reward_cfg)
    r2 = segment_returns(params, batch.obs2, batch.act2, reward_cfg)
    loss, per_member, correct, n = bt_loss_from_returns(r1, r2, batch.labels, mask, label_margin)
    return loss, {"per_member_loss": per_member, "accuracy": correct / jnp.maximum(n, 1.0)}


def _member_batch_loss(params, batch: PreferenceBatch, mask, reward_cfg, label_margin,
                       terms: tuple[RewardTerm, ...] = (), rows=()):
    """Per-member minibatches: every batch leaf has a leading K axis ([K, b, T, ...]).
    CE plus Σ weight · loss of the `terms` (their minibatch `rows`); aux = (per-member CE,
    correct, n, unweighted term values)."""
    s1 = per_member_rewards(params, batch.obs1, batch.act1, reward_cfg)
    s2 = per_member_rewards(params, batch.obs2, batch.act2, reward_cfg)
    loss, per_member, correct, n = bt_loss_from_returns(s1.sum(-1), s2.sum(-1), batch.labels, mask,
                                                        label_margin)
    values = tuple(term.loss(s1, s2, r, mask, params) for term, r in zip(terms, rows))
    for term, value in zip(terms, values):
        loss = loss + term.weight * value
    return loss, (per_member, correct, n, values)


def _gather(store: PreferenceStore, terms: tuple[RewardTerm, ...], idx: jax.Array):
    """The stored pairs and the terms' rows at per-member indices idx[K, b]."""
    batch = PreferenceBatch(obs1=store.obs1[idx], act1=store.act1[idx], obs2=store.obs2[idx],
                            act2=store.act2[idx], labels=store.labels[idx])
    return batch, tuple(jax.tree.map(lambda x: x[idx], term.data) for term in terms)


def term_gradient_ratios(params: Params, store: PreferenceStore, key: jax.Array, *,
                         reward_cfg: RewardConfig, cfg: PreferenceConfig,
                         terms: tuple[RewardTerm, ...]) -> dict[str, jax.Array]:
    """‖∇ weight·term‖ / ‖∇ CE‖ (global norms over the ensemble's parameters) on one minibatch
    of stored pairs drawn as an epoch draws its first one: how hard each auxiliary term pulls
    against the preference loss. Keyed "<term name>/grad_ratio"; 0 with an empty store."""
    k, bs = reward_cfg.ensemble_size, cfg.batch_size
    perm = member_permutations(key, store.count, store.capacity, k)
    idx = jnp.pad(perm, ((0, 0), (0, max(bs - store.capacity, 0))))[:, :bs]
    mask = jnp.arange(bs) < store.count
    batch, rows = _gather(store, terms, idx)

    def ce(p):  # the update's loss without terms
        return _member_batch_loss(p, batch, mask, reward_cfg, cfg.label_margin)[0]

    def weighted(term, r):
        def loss(p):
            s1 = per_member_rewards(p, batch.obs1, batch.act1, reward_cfg)
            s2 = per_member_rewards(p, batch.obs2, batch.act2, reward_cfg)
            return term.weight * term.loss(s1, s2, r, mask, p)
        return loss

    ce_norm = optax.global_norm(jax.grad(ce)(params))
    return {f"{t.name}/grad_ratio": jnp.where(
                store.count > 0,
                optax.global_norm(jax.grad(weighted(t, r))(params)) / jnp.maximum(ce_norm, 1e-12),
                0.0)
            for t, r in zip(terms, rows)}


def member_permutations(key: jax.Array, count: jax.Array, capacity: int, ensemble_size: int) -> jax.Array:
    """[K, capacity] int32: row k starts with an independent random permutation of 0..count-1
    (BPref: `np.random.permutation(max_len)` per member); the tail is padding (indices >= count)."""
    def one(k):
        # 31 random bits per row (float32 uniforms would tie often at 5e5 rows); padding sorts last.
        u = jax.random.bits(k, (capacity,), jnp.uint32) >> 1
        u = jnp.where(jnp.arange(capacity) < count, u, jnp.uint32(0xFFFFFFFF))
        return jnp.argsort(u).astype(jnp.int32)

    return jax.vmap(one)(jax.random.split(key, ensemble_size))


def train_epoch(params: Params, opt_state: Any, store: PreferenceStore, key: jax.Array, *,
                tx: optax.GradientTransformation, reward_cfg: RewardConfig = RewardConfig(),
                cfg: PreferenceConfig = PreferenceConfig(), terms: tuple[RewardTerm, ...] = ()):
    """One pass over the `store.count` stored pairs in ceil(count/batch_size) minibatches.

    Returns (params, opt_state, metrics) with metrics:
      accuracy [K]: per-member fraction of correct predictions over the epoch's minibatches
                    (BPref `ensemble_acc / total`, predictions taken before each step);
      loss: mean over minibatches of Σ_members batch-mean CE. With count == 0 nothing changes.
      terms: {name: mean over minibatches of each `RewardTerm`'s unweighted loss}.
    No terms = PEBBLE.
    """
    k = reward_cfg.ensemble_size
    cap = store.capacity
    bs = cfg.batch_size
    n_batches_max = -(-cap // bs)
    perm = member_permutations(key, store.count, cap, k)
    perm = jnp.pad(perm, ((0, 0), (0, n_batches_max * bs - cap)))  # static pad to a multiple of bs
    n_batches = (store.count + bs - 1) // bs
    grad_fn = jax.grad(_member_batch_loss, has_aux=True)

    def body(i, carry):
        params, opt_state, correct, total, loss_sum, term_sums = carry
        start = i * bs
        idx = jax.lax.dynamic_slice_in_dim(perm, start, bs, axis=1)  # [K, bs]
        mask = (start + jnp.arange(bs)) < store.count  # [bs]
        batch, rows = _gather(store, terms, idx)
        grads, (per_member, c, n, values) = grad_fn(params, batch, mask, reward_cfg,
                                                    cfg.label_margin, terms, rows)
        updates, opt_state = tx.update(grads, opt_state, params)
        params = optax.apply_updates(params, updates)
        term_sums = tuple(a + v for a, v in zip(term_sums, values))
        return params, opt_state, correct + c, total + n, loss_sum + per_member.sum(), term_sums

    zeros = jnp.zeros((k,), jnp.float32)
    scalar = jnp.zeros((), jnp.float32)
    params, opt_state, correct, total, loss_sum, term_sums = jax.lax.fori_loop(
        0, n_batches, body, (params, opt_state, zeros, zeros, scalar, (scalar,) * len(terms)))
    denom = jnp.maximum(n_batches, 1).astype(jnp.float32)
    metrics = {"accuracy": correct / jnp.maximum(total, 1.0), "loss": loss_sum / denom,
               "terms": {t.name: v / denom for t, v in zip(terms, term_sums)}}
    return params, opt_state, metrics


def train_reward(params: Params, opt_state: Any, store: PreferenceStore, key: jax.Array, *,
                 tx: optax.GradientTransformation, reward_cfg: RewardConfig = RewardConfig(),
                 cfg: PreferenceConfig = PreferenceConfig(), terms: tuple[RewardTerm, ...] = ()):
    """PEBBLE's reward update for one query round: up to `cfg.max_epochs` epochs, stopping after
    the first epoch whose mean accuracy over members exceeds `cfg.acc_threshold` (lax.while_loop).

    Returns (params, opt_state, metrics) with metrics "reward/epochs" (int32), "reward/train_acc"
    (mean over members, last epoch), "reward/train_acc_member" [K], "reward/loss" (last epoch's
    CE), every term's unweighted loss under its name (last epoch) and its gradient-norm ratio
    to the CE before the first epoch ("<name>/grad_ratio", `term_gradient_ratios`). With an
    empty store, no epoch runs (epochs = 0, accuracy 0).
    """
    k = reward_cfg.ensemble_size

    def cond(c):
        epoch, _, _, _, acc, _, _ = c
        return (epoch < cfg.max_epochs) & (acc.mean() <= cfg.acc_threshold) & (store.count > 0)

    def body(c):
        epoch, params, opt_state, key, _, _, _ = c
        key, sub = jax.random.split(key)
        params, opt_state, m = train_epoch(params, opt_state, store, sub, tx=tx,
                                           reward_cfg=reward_cfg, cfg=cfg, terms=terms)
        return epoch + 1, params, opt_state, key, m["accuracy"], m["loss"], m["terms"]

    # how hard each term pulls against the CE where the round starts (the new labels' pull)
    ratios = term_gradient_ratios(params, store, jax.random.fold_in(key, GRAD_RATIO_STREAM),
                                  reward_cfg=reward_cfg, cfg=cfg, terms=terms)
    scalar = jnp.zeros((), jnp.float32)
    init = (jnp.zeros((), jnp.int32), params, opt_state, key, jnp.zeros((k,), jnp.float32),
            scalar, {t.name: scalar for t in terms})
    epochs, params, opt_state, _, acc, loss, term_values = jax.lax.while_loop(cond, body, init)
    metrics = {"reward/epochs": epochs, "reward/train_acc": acc.mean(),
               "reward/train_acc_member": acc, "reward/loss": loss,
               **term_values, **ratios}
    return params, opt_state, metrics
