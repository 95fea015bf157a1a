"""SURF as a rule of the lab (`hprior reward-lab --rules surf`): its cells and its round, in a
program of its own (its stored segments are H + 2w steps and it trains on a pool, so its cells
cannot share the other rules' shapes). SURF itself is `hprior_jax.methods.surf`."""
from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import optax
from flax import struct

from hprior_jax.buffers import preferences
from hprior_jax.methods.surf import SurfConfig
from hprior_jax.networks.reward_ensemble import init_reward_ensemble
from hprior_jax.pbrl.preference import make_optimizer
from hprior_jax.pbrl.query import round_queries
from hprior_jax.pbrl.surf import add_unlabelled, surf_iterations, train_reward_surf
from hprior_jax.pbrl.teacher import compute_thresholds, teacher_labels


@struct.dataclass
class SurfLabCell:
    """One seed's SURF in the reward-learning lab: its ensemble, labelled store and pool."""

    reward: dict
    opt: optax.OptState
    prefs: preferences.PreferenceStore
    pool: preferences.PreferenceStore
    key: jax.Array


@dataclass(frozen=True)
class SurfLabRule:
    """A round does what `Surf`'s does on the lab's episodes: queries of H + 2w steps (the
    first round uniform, then the lab's `feed`), the teacher on the middle H,
    `inv_label_ratio` x queries uniform pairs into the pool, then `train_reward_surf` for
    ceil(epochs x labels / batch) iterations. Its initial weights are the other rules' of the
    same seed; its queries are its own draws (other lengths)."""

    cfg: SurfConfig
    segment_len: int  # H, the steps the teacher judges

    @property
    def stored_len(self) -> int:
        return self.segment_len + 2 * self.cfg.window

    def init(self, key, capacity: int, obs_size: int, act_size: int, lab) -> SurfLabCell:
        params = init_reward_ensemble(key, obs_size, act_size, lab.reward)
        store = lambda n: preferences.init(self.stored_len, obs_size, act_size, capacity=n)
        return SurfLabCell(reward=params, opt=make_optimizer(lab.preference).init(params),
                           prefs=store(capacity), pool=store(capacity * self.cfg.inv_label_ratio),
                           key=key)

    def round(self, cell: SurfLabCell, num_queries, first, train, mean_return, *, lab,
              queries: int, feed: str, episode_length: int):
        key, k_query, k_teacher, k_pool, k_train = jax.random.split(cell.key, 5)
        episodes = jnp.int32(train.obs.shape[0])
        pairs = round_queries(
            k_query, cell.reward, train.obs, train.act, train.reward, episodes, first=first,
            feed=feed, mb_size=queries, segment_len=self.stored_len,
            large_batch=lab.large_batch, num_queries=num_queries, reward_cfg=lab.reward)
        judged = slice(self.cfg.window, self.stored_len - self.cfg.window)
        thresholds = compute_thresholds(lab.teacher, mean_return, self.segment_len,
                                        episode_length, first_round=first)
        out = teacher_labels(k_teacher, pairs.true_r1[:, judged], pairs.true_r2[:, judged],
                             lab.teacher, thresholds)
        prefs = preferences.add(cell.prefs, preferences.PreferenceBatch(
            pairs.obs1, pairs.act1, pairs.obs2, pairs.act2, out.labels), out.valid & pairs.mask)
        pool = add_unlabelled(cell.pool, k_pool, train.obs, train.act, train.reward, episodes,
                              queries=queries, num_queries=num_queries,
                              ratio=self.cfg.inv_label_ratio, segment_len=self.stored_len)
        p, s = lab.preference, self.cfg
        params, opt, m = train_reward_surf(
            cell.reward, cell.opt, prefs, pool, k_train,
            surf_iterations(p.max_epochs, prefs.count, p.batch_size), tx=make_optimizer(p),
            reward_cfg=lab.reward, batch_size=p.batch_size, mu=s.mu,
            segment_len=self.segment_len, window=s.window, crop_range=s.crop_range,
            threshold_u=s.threshold_u, lambda_u=s.lambda_u)
        metrics = {"labels": prefs.count, "epochs": m["reward/iterations"],
                   "train_acc": m["reward/train_acc"], "ce": m["reward/loss"],
                   "unlabelled_loss": m["surf/unlabelled_loss"],
                   "confident": m["surf/confident"]}
        return SurfLabCell(reward=params, opt=opt, prefs=prefs, pool=pool, key=key), metrics


def rule(rl) -> SurfLabRule:
    """The lab's SURF at the settings of `rl`, the RunConfig of `hprior train --algo surf` at
    the lab's preset (the agent's settings do not enter)."""
    return SurfLabRule(cfg=rl.surf, segment_len=rl.pebble.segment_len)
