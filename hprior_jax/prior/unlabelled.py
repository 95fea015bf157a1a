"""PRIOR's prior on unlabelled segments: an ablation, one reading of appendix G.2 ("we reuse
the trajectory buffer (as used by Hindsight PRIOR)"); the paper's prior, the default, is on
the labelled pairs only. RVAR takes it too, with uniform credit (its control: in the walker
lab the segments, not α, carried the gain).

The prior's target α_t · R̂_k(σ) needs no label, only the world model's α and the member's
own return, so it can also shape the reward on segments nobody labelled. Each feedback round
draws `num` segments afresh from the trajectory data, computes their α once, and pairs stored
row r with segment r mod num: every reward minibatch of b labelled rows then also fits the
prior on b unlabelled segments, with the prior's λ.
"""
from __future__ import annotations

import flax.struct
import jax
import jax.numpy as jnp

from hprior_jax.buffers.episodes import segment_rows
from hprior_jax.networks.reward_ensemble import RewardConfig, per_member_rewards
from hprior_jax.pbrl.preference import RewardTerm
from hprior_jax.prior.loss import prior_loss

STREAM = 0x756E  # folded off a round's key: the draw leaves the round's other draws alone


@flax.struct.dataclass
class UnlabelledSegments:
    """Per stored-pair row: an unlabelled segment obs[C, T, ds], act[C, T, da] and its credit
    alpha[C, T] (the rule's variant already applied)."""

    obs: jax.Array
    act: jax.Array
    alpha: jax.Array


def replay_segments(run_key: jax.Array, replay, num: int, *, segment_len: int,
                    episode_len: int) -> tuple[jax.Array, jax.Array]:
    """`num` segments of the replay buffer that stay inside one episode, drawn afresh each
    round off the run's key: obs[num, T, ds], act[num, T, da]."""
    idx = segment_rows(jax.random.fold_in(run_key, STREAM), replay.size,
                       episode_len=episode_len, batch_size=num, segment_len=segment_len)
    return replay.obs[idx], replay.action[idx]


def rows_of_pool(obs: jax.Array, act: jax.Array, alpha: jax.Array,
                 capacity: int) -> UnlabelledSegments:
    """A pool of N segments (obs[N, T, ds], act[N, T, da], alpha[N, T]) as rows of the
    preference store: row r holds segment r mod N."""
    take = jnp.arange(capacity) % obs.shape[0]
    return UnlabelledSegments(obs=obs[take], act=act[take], alpha=alpha[take])


def unlabelled_prior_loss(params, rows: UnlabelledSegments, mask: jax.Array, *,
                          reward_cfg: RewardConfig, clip=False, shift=0.0) -> jax.Array:
    """rows leaves [K, b, ...] (each member its own rows), mask [b] (real minibatch rows) ->
    Σ_k of the prior loss on the rows' segments (`prior.loss.prior_loss`)."""
    step_r = per_member_rewards(params, rows.obs, rows.act, reward_cfg)  # [K, b, T]
    return prior_loss(step_r, rows.alpha, mask, clip, shift)[0]


def unlabelled_prior_term(lam, segments: UnlabelledSegments, *, reward_cfg: RewardConfig,
                          clip=False, shift=0.0) -> RewardTerm:
    """The prior on unlabelled segments as a reward term: "prior/unlabelled_loss", weight λ
    (a float or a traced scalar), data = `segments` (leaves [C, ...]); `clip` and `shift`
    as in `prior.loss.prior_targets`."""

    def loss(step_r1, step_r2, rows: UnlabelledSegments, mask, params):
        return unlabelled_prior_loss(params, rows, mask, reward_cfg=reward_cfg, clip=clip,
                                     shift=shift)

    return RewardTerm(name="prior/unlabelled_loss", weight=lam, loss=loss, data=segments)
