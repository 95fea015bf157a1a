"""Query generation and selection (BPref `reward_model.py#L168-L195, L312-L347, L424-L599`).

Trajectory store layout (the caller's ring of the last N complete episodes, BPref `max_size=100`):
obs[N, L, ds], act[N, L, da], true_reward[N, L], and `num_episodes` = how many rows are valid.
Rows 0..num_episodes-1 must be the valid ones (a ring that fills from row 0 and, once full, has
every row valid). The unfinished current episode must not be in the store (BPref drops it).

Pairs: two episodes drawn independently and uniformly *with replacement* (both segments may
come from the same episode), each segment with its own start. BPref draws the start with
`np.random.choice(L - H)`, i.e. from {0, ..., L-H-1}, so the last step of an episode is never
in a segment; we keep that off-by-one by default (`include_last_step=False`).

Selection rules (`feed_type`): "uniform" (0) draws `mb_size` pairs; "disagreement" (1) and
"entropy" (2) draw `mb_size * large_batch` pairs and keep the top `mb_size` by the std over
members of P_i[σ1 ≻ σ2] (numpy std, ddof 0) or by the mean over members of the binary entropy.
PEBBLE's first round is always uniform; that choice belongs to the caller.
"""
from __future__ import annotations

from functools import partial

import flax.struct
import jax
import jax.numpy as jnp

from hprior_jax.networks.reward_ensemble import Params, RewardConfig
from hprior_jax.pbrl.preference import preference_probs, segment_returns

RULES = ("uniform", "disagreement", "entropy")


@flax.struct.dataclass
class SegmentPairs:
    """B candidate pairs: obs*[B, H, ds], act*[B, H, da], true_r*[B, H] (teacher only).

    `mask` [B] is True for pairs inside this round's feedback budget (see `select_queries`).
    `origin` int32[B, 4]: (episode, start) of segment 1, then of segment 2, in the store (to
    fetch what else the store keeps of them: the physics states a person's clips show)."""

    obs1: jax.Array
    act1: jax.Array
    true_r1: jax.Array
    obs2: jax.Array
    act2: jax.Array
    true_r2: jax.Array
    mask: jax.Array
    origin: jax.Array | None = None


def sample_segment_pairs(key: jax.Array, obs: jax.Array, act: jax.Array, true_reward: jax.Array,
                         num_episodes: jax.Array, num_pairs: int, segment_len: int,
                         include_last_step: bool = False) -> SegmentPairs:
    """Draw `num_pairs` (static) candidate pairs of length `segment_len` (static) from the store."""
    n_store, ep_len = true_reward.shape
    if segment_len > ep_len - (0 if include_last_step else 1):
        raise ValueError(f"segment_len={segment_len} does not fit in episodes of length {ep_len}; "
                         "use a shorter segment")
    n_starts = ep_len - segment_len + (1 if include_last_step else 0)
    k_e1, k_e2, k_s1, k_s2 = jax.random.split(key, 4)
    n_valid = jnp.maximum(num_episodes, 1)  # an empty store would index row 0; caller must not query it
    ep1 = jax.random.randint(k_e1, (num_pairs,), 0, n_valid)
    ep2 = jax.random.randint(k_e2, (num_pairs,), 0, n_valid)
    st1 = jax.random.randint(k_s1, (num_pairs,), 0, n_starts)
    st2 = jax.random.randint(k_s2, (num_pairs,), 0, n_starts)
    return pairs_at(obs, act, true_reward, jnp.stack([ep1, st1, ep2, st2], axis=-1),
                    segment_len)


def pairs_at(obs: jax.Array, act: jax.Array, true_reward: jax.Array, origin: jax.Array,
             segment_len: int) -> SegmentPairs:
    """The pairs at `origin` int[B, 4] (episode, start of segment 1, then of segment 2) of
    the store, all inside the budget."""
    origin = jnp.asarray(origin, jnp.int32)
    cut = lambda x, side: cut_segments(x, origin[:, 2 * side - 2], origin[:, 2 * side - 1],
                                       segment_len)
    return SegmentPairs(obs1=cut(obs, 1), act1=cut(act, 1), true_r1=cut(true_reward, 1),
                        obs2=cut(obs, 2), act2=cut(act, 2), true_r2=cut(true_reward, 2),
                        mask=jnp.ones((origin.shape[0],), bool), origin=origin)


def cut_segments(x: jax.Array, episodes: jax.Array, starts: jax.Array, segment_len: int):
    """x[N, L, ...] -> [B, H, ...]: the segments of `segment_len` steps at (episode, start)."""
    t = jnp.arange(segment_len)
    return x[episodes[:, None], starts[:, None] + t[None, :]]


def disagreement_scores(params: Params, pairs: SegmentPairs,
                        reward_cfg: RewardConfig = RewardConfig()) -> jax.Array:
    """[B] std over members of P_i[σ1 ≻ σ2] (BPref `get_rank_probability`, np.std, ddof 0)."""
    p = preference_probs(params, pairs.obs1, pairs.act1, pairs.obs2, pairs.act2, reward_cfg)
    return p.std(axis=0)


def entropy_scores(params: Params, pairs: SegmentPairs,
                   reward_cfg: RewardConfig = RewardConfig()) -> jax.Array:
    """[B] mean over members of the binary entropy of P_i (BPref `get_entropy`/`p_hat_entropy`)."""
    d = (segment_returns(params, pairs.obs1, pairs.act1, reward_cfg)
         - segment_returns(params, pairs.obs2, pairs.act2, reward_cfg))  # logit of P_i, [K, B]
    # -(p log p + (1-p) log(1-p)) from log-sigmoids: stable when the summed logits saturate.
    p = jax.nn.sigmoid(d)
    ent = -(p * jax.nn.log_sigmoid(d) + (1.0 - p) * jax.nn.log_sigmoid(-d))
    return ent.mean(axis=0)


def take_pairs(pairs: SegmentPairs, idx: jax.Array) -> SegmentPairs:
    return jax.tree_util.tree_map(lambda x: x[idx], pairs)


def select_from_pool(params: Params, pool: SegmentPairs, *, rule: str, mb_size: int,
                     reward_cfg: RewardConfig = RewardConfig()) -> SegmentPairs:
    """Keep the `mb_size` (static) highest-scoring pairs of `pool`, best first
    ("disagreement" or "entropy"; BPref `(-score).argsort()[:mb_size]`)."""
    if rule == "disagreement":
        scores = disagreement_scores(params, pool, reward_cfg)
    elif rule == "entropy":
        scores = entropy_scores(params, pool, reward_cfg)
    else:
        raise ValueError(f"select_from_pool needs rule 'disagreement' or 'entropy', got {rule!r}")
    _, top = jax.lax.top_k(scores, mb_size)
    return take_pairs(pool, top)


def select_queries(key: jax.Array, params: Params, obs: jax.Array, act: jax.Array,
                   true_reward: jax.Array, num_episodes: jax.Array, *, rule: str, mb_size: int,
                   segment_len: int, large_batch: int = 10,
                   num_queries: jax.Array | None = None,
                   reward_cfg: RewardConfig = RewardConfig(),
                   include_last_step: bool = False) -> SegmentPairs:
    """The `mb_size` (static) pairs to show the teacher this round, best first.

    `num_queries` (dynamic, <= mb_size) clips the round at the end of the feedback budget (BPref
    `mb_size = max_feedback - total_feedback`): `mask` is True on the first `num_queries` pairs,
    which for the uncertainty rules are the `num_queries` highest-scoring ones.
    """
    if rule not in RULES:
        raise ValueError(f"rule={rule!r}; choose one of {RULES}")
    k_pool, _ = jax.random.split(key)
    if rule == "uniform":
        pairs = sample_segment_pairs(k_pool, obs, act, true_reward, num_episodes, mb_size,
                                     segment_len, include_last_step)
    else:
        pool = sample_segment_pairs(k_pool, obs, act, true_reward, num_episodes,
                                    mb_size * large_batch, segment_len, include_last_step)
        pairs = select_from_pool(params, pool, rule=rule, mb_size=mb_size, reward_cfg=reward_cfg)
    if num_queries is not None:
        pairs = pairs.replace(mask=jnp.arange(mb_size) < num_queries)
    return pairs


def round_queries(key: jax.Array, params: Params, obs: jax.Array, act: jax.Array,
                  true_reward: jax.Array, num_episodes: jax.Array, *, first: jax.Array,
                  feed: str, **kw) -> SegmentPairs:
    """`select_queries` of a round whose being the first is traced (`first`): uniform on the
    first round (as BPref), `feed` after. Both are drawn and `first` picks, so every round
    runs one compiled program. `kw`: select_queries' other arguments."""
    select = partial(select_queries, key, params, obs, act, true_reward, num_episodes, **kw)
    pairs = select(rule="uniform")
    if feed == "uniform":
        return pairs
    return jax.tree.map(partial(jnp.where, first), pairs, select(rule=feed))
