"""SURF's reward update: pseudo-labelled unlabelled pairs + temporal cropping (Park et al. 2022).

alinlab/SURF `reward_model_semi_dataaug.py` (`get_cropping_mask`, `semi_train_reward`,
`semi_train_soft_reward`) and `train_PEBBLE_semi_dataaug.py` (`learn_reward`):
- Stored segments (labelled store and unlabelled pool) have S = H + 2w steps (w = dataaug_window);
  the teacher labelled the middle H steps.
- num_iters = ceil(reward_update · labelled / 128) iterations, no accuracy early stop.
- Per iteration, member k takes its own labelled minibatch (≤ batch_size pairs) and its own
  unlabelled minibatch (≤ batch_size · mu pairs) from its own permutation of each pool. One start
  index per pool (shared by the members) advances by the batch size; when a pool's batch reached
  its last stored pair, that pool is reshuffled (new permutation per member) and restarts at 0,
  so the last batch before a reshuffle may be short.
- Crops: per pair a length L ~ U{H-c..H+c} and independent starts s1, s2 ~ U{0..S-L}; a segment's
  logit is Σ r̂ over its window. Fresh crops per member, per iteration, for both minibatches.
- Loss_k = CE(cropped labelled logits, label) [soft target, equal -1 -> 0.5/0.5]
         + λ_u · mean_b[CE(cropped unlabelled logits, pseudo-label) · confident], where the
  pseudo-label is argmax softmax of member k's own un-cropped middle-window sums (no gradient)
  and confident = max prob ≥ threshold_u; the mean runs over all sampled unlabelled pairs.
  One Adam step on Σ_k Loss_k per iteration.

Shape-static like `preference.py`: stores have a fixed capacity and a `count`; short batches are
masked. `tx`, the configs and the sizes are static (keyword args, close over them before jit);
`threshold_u`, `lambda_u` and `num_iters` may be traced.
"""
from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import optax
from jax import lax

from hprior_jax.buffers.preferences import PreferenceBatch, PreferenceStore, add
from hprior_jax.networks.reward_ensemble import Params, RewardConfig, per_member_rewards
from hprior_jax.pbrl.preference import bt_loss_from_returns, member_permutations
from hprior_jax.pbrl.query import sample_segment_pairs


def surf_iterations(reward_update: int, labelled: jax.Array, batch_size: int = 128) -> jax.Array:
    """ceil(reward_update * labelled / batch_size), int32 (train_PEBBLE_semi_dataaug.py)."""
    n = jnp.asarray(labelled, jnp.int32) * reward_update
    return ((n + batch_size - 1) // batch_size).astype(jnp.int32)


def add_unlabelled(pool: PreferenceStore, key: jax.Array, obs, act, true_reward, num_episodes,
                   *, queries: int, num_queries, ratio: int, segment_len: int) -> PreferenceStore:
    """A round's unlabelled pairs into the pool: `ratio` (inv_label_ratio) x the round's
    queries, uniform, of `segment_len` (stored) steps; `queries` static, `num_queries` (<=,
    traced) the ones the round really asked. Their labels are never read."""
    n = queries * ratio
    u = sample_segment_pairs(key, obs, act, true_reward, num_episodes, n, segment_len)
    batch = PreferenceBatch(u.obs1, u.act1, u.obs2, u.act2, jnp.zeros((n,), jnp.int32))
    return add(pool, batch, jnp.arange(n) < num_queries * ratio)


def _check_crop(stored_len: int, segment_len: int, crop_range: int) -> None:
    if not 0 <= crop_range < segment_len:
        raise ValueError(f"crop_range={crop_range} must be in [0, segment_len={segment_len})")
    if segment_len + crop_range > stored_len:
        raise ValueError(f"longest crop {segment_len + crop_range} exceeds the stored segment "
                         f"length {stored_len} (need crop_range <= 2 * window)")


def crop_masks(key: jax.Array, num_pairs: int, stored_len: int, segment_len: int,
               crop_range: int) -> tuple[jax.Array, jax.Array]:
    """float32 masks [num_pairs, stored_len] for segment 1 and 2 (ones on each window).

    SURF `get_cropping_mask`: one length L ~ U{H-c..H+c} per pair, shared by both segments, and
    two independent starts ~ U{0..S-L}.
    """
    _check_crop(stored_len, segment_len, crop_range)
    k_len, k1, k2 = jax.random.split(key, 3)
    length = jax.random.randint(k_len, (num_pairs,), segment_len - crop_range,
                                segment_len + crop_range + 1)
    hi = stored_len - length + 1  # exclusive
    s1 = jax.random.randint(k1, (num_pairs,), 0, hi)
    s2 = jax.random.randint(k2, (num_pairs,), 0, hi)
    t = jnp.arange(stored_len)
    window = lambda s: ((t >= s[:, None]) & (t < (s + length)[:, None])).astype(jnp.float32)
    return window(s1), window(s2)


def surf_crops(key: jax.Array, ensemble_size: int, labelled_batch: int, unlabelled_batch: int,
               stored_len: int, segment_len: int, crop_range: int):
    """The crops `surf_batch_loss` draws from `key`: (m1, m2) [K, b, S] for the labelled and
    (um1, um2) [K, bu, S] for the unlabelled minibatch (independent per member and pair)."""
    k_l, k_u = jax.random.split(key)
    k, s = ensemble_size, stored_len
    m1, m2 = crop_masks(k_l, k * labelled_batch, s, segment_len, crop_range)
    um1, um2 = crop_masks(k_u, k * unlabelled_batch, s, segment_len, crop_range)
    lab = lambda m: m.reshape(k, labelled_batch, s)
    unl = lambda m: m.reshape(k, unlabelled_batch, s)
    return lab(m1), lab(m2), unl(um1), unl(um2)


def pseudo_labels(mid_ret1, mid_ret2, threshold_u) -> tuple[jax.Array, jax.Array]:
    """(labels int32, confident bool), same leading shape as the inputs.

    p = softmax([R̂1, R̂2]) without gradient; label = argmax p (a tie -> 0, as torch.max);
    confident = max p >= threshold_u.
    """
    logits = lax.stop_gradient(jnp.stack([mid_ret1, mid_ret2], axis=-1))
    p = jax.nn.softmax(logits, axis=-1)
    return jnp.argmax(p, axis=-1).astype(jnp.int32), p.max(-1) >= threshold_u


def surf_loss_from_masks(params: Params, labelled: PreferenceBatch, labelled_mask,
                         unlabelled_obs1, unlabelled_act1, unlabelled_obs2, unlabelled_act2,
                         unlabelled_mask, masks, *, reward_cfg: RewardConfig, window: int,
                         threshold_u, lambda_u, label_margin: float = 0.0):
    """`surf_batch_loss` with given crops `masks` = (m1, m2, um1, um2) (see `surf_crops`)."""
    k = reward_cfg.ensemble_size
    b, bu = labelled.labels.shape[-1], unlabelled_obs1.shape[1]
    s = labelled.obs1.shape[-2]
    # One forward over the four segment sets (every member on its own rows): [K, 2b + 2bu, S].
    obs = jnp.concatenate([labelled.obs1, labelled.obs2, unlabelled_obs1, unlabelled_obs2], axis=1)
    act = jnp.concatenate([labelled.act1, labelled.act2, unlabelled_act1, unlabelled_act2], axis=1)
    r = per_member_rewards(params, obs, act, reward_cfg)
    r1, r2, u1, u2 = r[:, :b], r[:, b:2 * b], r[:, 2 * b:2 * b + bu], r[:, 2 * b + bu:]
    m1, m2, um1, um2 = masks

    lmask = jnp.broadcast_to(labelled_mask, (k, b))
    ce_sum, ce, correct, n = bt_loss_from_returns((m1 * r1).sum(-1), (m2 * r2).sum(-1),
                                                  labelled.labels, lmask, label_margin)

    umask = jnp.broadcast_to(unlabelled_mask, (k, bu))
    mid = slice(window, s - window)
    plabel, confident = pseudo_labels(u1[..., mid].sum(-1), u2[..., mid].sum(-1), threshold_u)
    logp = jax.nn.log_softmax(jnp.stack([(um1 * u1).sum(-1), (um2 * u2).sum(-1)], -1), -1)
    u_ce = -jnp.take_along_axis(logp, plabel[..., None], -1)[..., 0]  # [K, bu]
    w = umask.astype(jnp.float32)
    u_loss = (u_ce * confident * w).sum(-1) / jnp.maximum(w.sum(-1), 1.0)  # [K]

    loss = ce_sum + lambda_u * u_loss.sum()
    conf = (confident * w).sum() / jnp.maximum(w.sum(), 1.0)
    aux = {"labelled_ce": ce, "unlabelled_loss": u_loss, "correct": correct, "count": n,
           "confident": conf}
    return loss, aux


def surf_batch_loss(params: Params, labelled: PreferenceBatch, labelled_mask, unlabelled_obs1,
                    unlabelled_act1, unlabelled_obs2, unlabelled_act2, unlabelled_mask, key, *,
                    reward_cfg: RewardConfig, segment_len: int, window: int, crop_range: int,
                    threshold_u, lambda_u, label_margin: float = 0.0):
    """SURF's loss on one iteration's per-member minibatches, crops drawn from `key`.

    labelled leaves [K, b, S, ...] (labels [K, b]), unlabelled obs/act [K, bu, S, ...], masks
    [K, b] / [K, bu] or [b] / [bu] (True = real pair), S = segment_len + 2 * window.
    -> (loss, aux): loss = Σ_k [labelled CE_k + λ_u · unlabelled_k]; aux "labelled_ce" [K]
    (masked mean), "unlabelled_loss" [K] (unweighted: Σ_b CE·confident / real pairs),
    "correct" [K], "count" [K] (real labelled pairs), "confident" (fraction of real unlabelled
    pairs over all members whose pseudo-label passed threshold_u).
    """
    s = labelled.obs1.shape[-2]
    if s != segment_len + 2 * window:
        raise ValueError(f"stored segments have {s} steps; expected segment_len + 2 * window = "
                         f"{segment_len + 2 * window}")
    masks = surf_crops(key, reward_cfg.ensemble_size, labelled.labels.shape[-1],
                       unlabelled_obs1.shape[1], s, segment_len, crop_range)
    return surf_loss_from_masks(params, labelled, labelled_mask, unlabelled_obs1, unlabelled_act1,
                                unlabelled_obs2, unlabelled_act2, unlabelled_mask, masks,
                                reward_cfg=reward_cfg, window=window, threshold_u=threshold_u,
                                lambda_u=lambda_u, label_margin=label_margin)


# ------------------------------------------------------------------ SURF's minibatch sampler
def _when(pred: jax.Array, fn, x):
    """fn(x) where pred, else x, as a 0-or-1-trip while_loop: under vmap over seeds the body runs
    only on iterations where some seed needs it (a batched cond would be a select that pays
    for fn every time). Here fn is a reshuffle: K argsorts over the pool's capacity."""
    return lax.while_loop(lambda c: c[0], lambda c: (jnp.zeros_like(c[0]), fn(c[1])), (pred, x))[1]


def _shuffle(key, count, capacity: int, ensemble_size: int, b: int) -> jax.Array:
    """[K, capacity + b]: each member's permutation of 0..count-1 first; the padding keeps a
    slice of b from any start < count in bounds (its rows are masked)."""
    perm = member_permutations(key, count, capacity, ensemble_size)
    return jnp.pad(perm, ((0, 0), (0, b)))


def _rows(perm, start, count, b: int, batch_size: int):
    """This iteration's rows [K, b], mask [b] and SURF's `last_index` = min(start + bs, count)."""
    idx = lax.dynamic_slice_in_dim(perm, start, b, axis=1)
    mask = start + jnp.arange(b) < count
    return idx, mask, jnp.minimum(start + batch_size, count)


def _advance(perm, start, last, count, key, batch_size: int, ensemble_size: int, b: int):
    """SURF: start += bs; if last_index == max_len: reshuffle, start = 0."""
    wrap = last == count
    perm = _when(wrap & (count > 0),
                 lambda p: _shuffle(key, count, p.shape[1] - b, ensemble_size, b), perm)
    return perm, jnp.where(wrap, 0, start + batch_size).astype(jnp.int32)


def _batch_rows(batch_size: int, capacity: int) -> int:
    """Static rows per minibatch: never more than the pool can hold."""
    return min(batch_size, capacity)


def minibatch_rows(key: jax.Array, count, capacity: int, num_iters: int, *, ensemble_size: int,
                   batch_size: int):
    """The rows SURF's sampler gives over `num_iters` iterations: (idx [N, K, b], mask [N, b]),
    b = min(batch_size, capacity). `train_reward_surf` draws its labelled rows this way from
    its first key split (and the unlabelled ones from its second, with batch_size·mu)."""
    b = _batch_rows(batch_size, capacity)

    def step(c, i):
        perm, start = c
        idx, mask, last = _rows(perm, start, count, b, batch_size)
        perm, start = _advance(perm, start, last, count, jax.random.fold_in(key, i), batch_size,
                               ensemble_size, b)
        return (perm, start), (idx, mask)

    init = (_shuffle(key, count, capacity, ensemble_size, b), jnp.zeros((), jnp.int32))
    return lax.scan(step, init, jnp.arange(num_iters))[1]


# ------------------------------------------------------------------ the update
def train_reward_surf(params: Params, opt_state: Any, store: PreferenceStore, pool: PreferenceStore,
                      key: jax.Array, num_iters, *, tx: optax.GradientTransformation,
                      reward_cfg: RewardConfig, batch_size: int = 128, mu: int = 1,
                      segment_len: int, window: int = 5, crop_range: int = 5,
                      threshold_u: float = 0.95, lambda_u: float = 1.0,
                      label_margin: float = 0.0):
    """SURF's reward update for one query round: exactly `num_iters` (traced int) Adam steps.

    store: labelled pairs, pool: unlabelled pairs (its labels are ignored); both with segments of
    S = segment_len + 2 * window steps. -> (params, opt_state, metrics) with "reward/train_acc"
    (mean over members of correct / labelled rows seen, all iterations), "reward/train_acc_member"
    [K], "reward/loss" (last iteration's total), "surf/unlabelled_loss" (last iteration, Σ_k,
    unweighted by λ_u), "surf/confident" (last iteration's fraction of confident unlabelled
    pairs) and "reward/iterations" (int32). With an empty store nothing changes (0 iterations).
    """
    k = reward_cfg.ensemble_size
    ub = batch_size * mu
    b, bu = _batch_rows(batch_size, store.capacity), _batch_rows(ub, pool.capacity)
    k_lab, k_pool, k_crop = jax.random.split(key, 3)
    n_iters = jnp.where(store.count > 0, jnp.asarray(num_iters, jnp.int32), 0)
    loss_fn = jax.value_and_grad(surf_batch_loss, has_aux=True)

    def body(i, c):
        params, opt_state, lperm, lstart, uperm, ustart, correct, total, _, _, _ = c
        lidx, lmask, llast = _rows(lperm, lstart, store.count, b, batch_size)
        uidx, umask, ulast = _rows(uperm, ustart, pool.count, bu, ub)
        lab = PreferenceBatch(obs1=store.obs1[lidx], act1=store.act1[lidx], obs2=store.obs2[lidx],
                              act2=store.act2[lidx], labels=store.labels[lidx])
        (loss, aux), grads = loss_fn(
            params, lab, lmask, pool.obs1[uidx], pool.act1[uidx], pool.obs2[uidx],
            pool.act2[uidx], umask, jax.random.fold_in(k_crop, i), reward_cfg=reward_cfg,
            segment_len=segment_len, window=window, crop_range=crop_range,
            threshold_u=threshold_u, lambda_u=lambda_u, label_margin=label_margin)
        updates, opt_state = tx.update(grads, opt_state, params)
        params = optax.apply_updates(params, updates)
        lperm, lstart = _advance(lperm, lstart, llast, store.count, jax.random.fold_in(k_lab, i),
                                 batch_size, k, b)
        uperm, ustart = _advance(uperm, ustart, ulast, pool.count, jax.random.fold_in(k_pool, i),
                                 ub, k, bu)
        return (params, opt_state, lperm, lstart, uperm, ustart, correct + aux["correct"],
                total + aux["count"], loss, aux["unlabelled_loss"].sum(), aux["confident"])

    zero_i = jnp.zeros((), jnp.int32)
    zero_f = jnp.zeros((), jnp.float32)
    init = (params, opt_state, _shuffle(k_lab, store.count, store.capacity, k, b), zero_i,
            _shuffle(k_pool, pool.count, pool.capacity, k, bu), zero_i,
            jnp.zeros((k,), jnp.float32), jnp.zeros((k,), jnp.float32), zero_f, zero_f, zero_f)
    out = lax.fori_loop(0, n_iters, body, init)
    params, opt_state, correct, total, loss, u_loss, conf = out[:2] + out[6:]
    acc = correct / jnp.maximum(total, 1.0)
    metrics = {"reward/train_acc": acc.mean(), "reward/train_acc_member": acc,
               "reward/loss": loss, "surf/unlabelled_loss": u_loss, "surf/confident": conf,
               "reward/iterations": n_iters}
    return params, opt_state, metrics
