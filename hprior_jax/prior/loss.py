"""PRIOR's auxiliary reward loss (appendix C.3, G.1, G.3, Table 4).

    r_target,t(σ) = sg(α_t(σ)) · sg(R̂_k(σ)),   R̂_k(σ) = Σ_t r̂_k(s_t, a_t)        (member k)
    L_prior,k     = mean over real pairs, both segments and t of (r̂_k(s_t, a_t) - r_target,t)²
    L             = Σ_k [ CE_k + λ · L_prior,k ]      λ = 5 (DMC), 1000 (MetaWorld)

Decisions (one reason each):
- Per-member R̂_k, shared α: each member is a separate reward model with its own CE; its own
  return keeps Σ_t r_target = R̂_k, so the prior reshapes a member's allocation without moving its
  BT logits. A mean-return target would also pull members together and shrink the ensemble
  disagreement that query selection uses.
- Stop-gradient on R̂ and α: the target is a regression target (the world model is frozen during
  reward learning); the prior gradient then only moves per-step rewards toward α·R̂ and never the
  return itself. The authors' WiseRL code does not detach R̂; not reproduced.
- Reduction: mean over steps, both segments and the real pairs of the minibatch, summed over
  members like the CE in hprior_jax.pbrl.preference (so λ weighs each member's own terms and
  does not scale with K). Mean over t, not sum: the choice sets what λ means (a sum over a
  50-step segment would weigh the prior 50 times more).
- Undiscounted R̂: the BT logits and the teacher use γ = 1.
- Variants of α: "raw" = the world model's credit (PRIOR); "nrp" = softmax over steps of the
  min-max normalised α (appendix eq. 9, PRIOR-NRP; masked steps excluded; a constant α gives
  uniform); "uniform" = 1/|σ| whatever α is (appendix G.1, RVAR: target G/|τ|).
  Note for NRP: min-max values lie in [0, 1], so the softmax ratio between any two steps is at most
  e — as written, eq. 9 flattens a peaked α rather than sharpening it.
- Target form (the paper is silent on the reward head's sign): "raw", the paper's α_t·R̂, is
  the default. Bradley-Terry sees only differences of returns, so R̂ of a segment can be
  negative under a tanh head, and then α ≥ 0 pushes the most-credited steps *down*.
  "shifted" redistributes the return measured from the head's floor -c (c = 1 for tanh):
  target_t = α_t·(R̂ + T·c) − c. Σ_t target = R̂ still, and with uniform α it is R̂/T, RVAR's
  target: the two forms differ only where α does.
"""
from __future__ import annotations

import flax.struct
import jax
import jax.numpy as jnp

from hprior_jax.pbrl.preference import RewardTerm

VARIANTS = ("raw", "nrp", "uniform")
TARGETS = ("raw", "shifted")
# the floor of each reward head's range: "shifted" measures the return from it
_FLOOR = {"tanh": 1.0, "sig": 0.0, "relu": 0.0, "none": 0.0}


def target_shift(target: str, output_activation: str) -> float:
    """c of the target form `target` under the reward head `output_activation`: the floor's
    magnitude for "shifted" (1 for tanh; 0 for heads whose floor is 0 or that have none,
    where both forms coincide), 0 for "raw"."""
    if target not in TARGETS:
        raise ValueError(f"target={target!r}; choose one of {TARGETS}")
    return _FLOOR[output_activation] if target == "shifted" else 0.0


@flax.struct.dataclass
class PairCredit:
    """α for both segments of every row of a PreferenceStore: alpha1[C, T], alpha2[C, T]."""

    alpha1: jax.Array
    alpha2: jax.Array

    @staticmethod
    def uniform(capacity: int, segment_len: int) -> "PairCredit":
        a = jnp.full((capacity, segment_len), 1.0 / segment_len, jnp.float32)
        return PairCredit(alpha1=a, alpha2=a)


def nrp_alpha(alpha: jax.Array, step_mask: jax.Array | None = None) -> jax.Array:
    """Appendix eq. 9 over the last axis: softmax((α - α_min) / (α_max - α_min)), masked steps -> 0."""
    mask = jnp.ones(alpha.shape, bool) if step_mask is None else jnp.broadcast_to(step_mask, alpha.shape)
    lo = jnp.min(jnp.where(mask, alpha, jnp.inf), axis=-1, keepdims=True)
    hi = jnp.max(jnp.where(mask, alpha, -jnp.inf), axis=-1, keepdims=True)
    rng = hi - lo
    x = jnp.where(rng > 0, (alpha - lo) / jnp.where(rng > 0, rng, 1.0), 0.0)
    return jax.nn.softmax(jnp.where(mask, x, -jnp.inf), axis=-1)


def rvar_alpha(alpha: jax.Array, step_mask: jax.Array | None = None) -> jax.Array:
    """Uniform 1/|σ| over the (valid) steps, shaped like `alpha` (its values are ignored)."""
    mask = jnp.ones(alpha.shape, bool) if step_mask is None else jnp.broadcast_to(step_mask, alpha.shape)
    w = mask.astype(jnp.float32)
    return w / jnp.maximum(w.sum(-1, keepdims=True), 1.0)


def variant_alpha(alpha: jax.Array, variant: str, step_mask: jax.Array | None = None) -> jax.Array:
    if variant == "raw":
        return alpha
    if variant == "nrp":
        return nrp_alpha(alpha, step_mask)
    if variant == "uniform":
        return rvar_alpha(alpha, step_mask)
    raise ValueError(f"variant={variant!r}; choose one of {VARIANTS}")


def prior_targets(step_rewards: jax.Array, alpha: jax.Array, clip=False,
                  shift=0.0) -> jax.Array:
    """step_rewards[K, ..., T], alpha[..., T] or [K, ..., T] -> targets[K, ..., T] =
    sg(α)·(sg(R̂_k) + T·c) − c with c = `shift` (a float or traced; 0: the paper's α·R̂,
    `target_shift` gives the "shifted" form's). `clip` (a bool, traced or not; an ablation,
    off in the paper): targets clipped to [-1, 1], the range of the tanh reward, which 1-12%
    of them left in the reduced cheetah runs."""
    ret = jax.lax.stop_gradient(step_rewards.sum(-1, keepdims=True))
    length = step_rewards.shape[-1]
    targets = jax.lax.stop_gradient(alpha) * (ret + length * shift) - shift
    return jnp.where(clip, jnp.clip(targets, -1.0, 1.0), targets)


def prior_loss(step_rewards: jax.Array, alpha: jax.Array, mask: jax.Array | None = None,
               clip=False, shift=0.0):
    """step_rewards[K, B, T], alpha[B, T] or [K, B, T], mask[B] or [K, B] (True = real segment).
    -> (Σ_k L_prior,k, per-member L_prior [K]); each L_prior,k is a mean over real segments and t."""
    targets = prior_targets(step_rewards, alpha, clip, shift)
    err = jnp.mean((step_rewards - targets) ** 2, axis=-1)  # [K, B]
    w = jnp.ones(err.shape, jnp.float32) if mask is None else jnp.broadcast_to(mask, err.shape).astype(jnp.float32)
    per_member = (err * w).sum(-1) / jnp.maximum(w.sum(-1), 1.0)
    return per_member.sum(), per_member


def pair_prior_loss(step_r1: jax.Array, step_r2: jax.Array, alpha1: jax.Array, alpha2: jax.Array,
                    mask: jax.Array | None = None, variant: str = "raw", clip=False,
                    shift=0.0):
    """Prior loss on both segments of every pair: step_r*[K, B, T], alpha*[(K,) B, T], mask[B].
    -> (Σ_k L_prior,k, per-member [K])."""
    r = jnp.concatenate([step_r1, step_r2], axis=-2)
    a = jnp.concatenate([variant_alpha(alpha1, variant), variant_alpha(alpha2, variant)], axis=-2)
    m = None if mask is None else jnp.concatenate([mask, mask], axis=-1)
    return prior_loss(r, a, m, clip, shift)


def target_saturation(step_rewards: jax.Array, alpha: jax.Array, shift=0.0) -> jax.Array:
    """Fraction of targets with |r_target| > 1, unreachable by a tanh reward."""
    return jnp.mean(jnp.abs(prior_targets(step_rewards, alpha, shift=shift)) > 1.0)


def prior_term(lam, credit: PairCredit, variant: str = "raw", clip=False,
               shift=0.0) -> RewardTerm:
    """The prior loss as a reward term of `train_reward`: weight λ (a float or a traced
    scalar), `credit` = α of every stored pair (any credit for "uniform"), `clip` the targets
    to the reward's range and `shift` their form (prior_targets)."""
    if variant not in VARIANTS:
        raise ValueError(f"variant={variant!r}; choose one of {VARIANTS}")

    def loss(step_r1, step_r2, rows: PairCredit, mask, params):
        return pair_prior_loss(step_r1, step_r2, rows.alpha1, rows.alpha2, mask, variant,
                               clip, shift)[0]

    return RewardTerm(name="prior/loss", weight=lam, loss=loss, data=credit)
