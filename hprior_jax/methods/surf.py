"""SURF (Park et al. 2022; alinlab/SURF `train_PEBBLE_semi_dataaug.py`,
`reward_model_semi_dataaug.py`): PEBBLE whose reward update also learns from pseudo-labelled
unlabelled pairs, with temporal cropping of every pair (hprior_jax.pbrl.surf).

What changes from PEBBLE (everything else, pre-training, relabelling and the critic reset
included, is PEBBLE's):
- stored segments are H + 2w steps (w = `window`); the teacher (labels, skip and equal sums)
  sees only the middle H; query selection scores the whole H + 2w;
- every round also draws `inv_label_ratio` x (this round's queries) uniform pairs into an
  unlabelled pool (a ring like the labelled store);
- the reward update runs ceil(reward_epochs x labels / reward_batch) iterations, each on
  `reward_batch` labelled and `mu` x `reward_batch` unlabelled pairs, with no 97% early stop.

Defaults are alinlab/SURF's config; MRN's copy of it (`RyanLiu112/MRN`,
`config/train_PEBBLE_semi_dataaug.yaml`) uses threshold_u 0.99, mu 4, inv_label_ratio 100:
`--surf.defaults mrn` selects those three.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import jax.numpy as jnp
from flax import struct

from hprior_jax.buffers import preferences
from hprior_jax.envs import task_info
from hprior_jax.methods.pebble import Pebble
from hprior_jax.methods.pebble_family import (EpisodeWindow, Extension, PebbleConfig, PebbleState,
                                             pebble_preset)
from hprior_jax.methods.registry import MethodSpec
from hprior_jax.pbrl.surf import add_unlabelled, surf_iterations, train_reward_surf

MRN_COPY = dict(threshold_u=0.99, mu=4, inv_label_ratio=100)


@dataclass(frozen=True)
class SurfConfig:
    threshold_u: float = 0.95
    """τ: an unlabelled pair is pseudo-labelled when a member's max P >= τ."""
    lambda_u: float = 1.0
    """Weight of the unlabelled (pseudo-label) loss."""
    mu: int = 1
    """Unlabelled pairs per labelled pair in a minibatch."""
    inv_label_ratio: int = 10
    """Unlabelled pairs drawn per query each round."""
    window: int = 5
    """w (`dataaug_window`): stored segments are H + 2w steps."""
    crop_range: int = 5
    """Crop lengths are drawn from H ± crop_range."""
    defaults: Literal["surf", "mrn"] = "surf"
    """`mrn`: MRN's copy of the config (threshold_u 0.99, mu 4, inv_label_ratio 100) for the
    three fields left at SURF's defaults."""

    def __post_init__(self):
        if self.defaults == "mrn":
            ours = SurfConfig()
            for name, value in MRN_COPY.items():
                if getattr(self, name) == getattr(ours, name):
                    object.__setattr__(self, name, value)
        if not 0.5 <= self.threshold_u <= 1.0:
            raise ValueError(f"--surf.threshold-u must be in [0.5, 1], got {self.threshold_u}")
        if self.lambda_u < 0 or self.mu < 1 or self.inv_label_ratio < 1:
            raise ValueError("need --surf.lambda-u >= 0, --surf.mu >= 1, --surf.inv-label-ratio >= 1")
        if self.window < 0 or self.crop_range < 0:
            raise ValueError("need --surf.window >= 0 and --surf.crop-range >= 0")


@struct.dataclass
class SurfState:
    pool: preferences.PreferenceStore  # unlabelled pairs (labels unused)


class Surf(Pebble):
    def __init__(self, cfg, kit):
        self.scfg = cfg.surf
        if cfg.surf.crop_range > 2 * cfg.surf.window:  # a crop of H + c must fit in H + 2w
            raise ValueError(f"--surf.crop-range ({cfg.surf.crop_range}) exceeds 2 x "
                             f"--surf.window ({cfg.surf.window}): crops must fit the stored "
                             f"segment")
        super().__init__(cfg, kit, Extension())

    @property
    def stored_segment_len(self) -> int:
        return self.pcfg.segment_len + 2 * self.scfg.window

    @property
    def pool_capacity(self) -> int:
        """Every unlabelled pair a run draws (the original's ring holds 5e5, never filled)."""
        return sum(q for _, q in self.rounds()) * self.scfg.inv_label_ratio

    def init(self, key):
        ms = super().init(key)
        env = self.kit.env
        pool = preferences.init(self.stored_segment_len, env.obs_size, env.action_size,
                                capacity=max(self.pool_capacity, 1))
        return ms.replace(ext=SurfState(pool=pool))

    @property
    def judged_steps(self) -> slice:
        """The teacher judges (and a person sees) the middle H steps of the stored H + 2w."""
        w = self.scfg.window
        return slice(w, self.stored_segment_len - w)

    def after_labels(self, ms: PebbleState, window: EpisodeWindow, num_queries, key):
        """This round's unlabelled pairs: `inv_label_ratio` x the round's queries, uniform."""
        pool = add_unlabelled(ms.ext.pool, key, window.obs, window.act, window.true_reward,
                              window.count, queries=self.pcfg.queries_per_round,
                              num_queries=num_queries, ratio=self.scfg.inv_label_ratio,
                              segment_len=self.stored_segment_len)
        return ms.replace(ext=ms.ext.replace(pool=pool))

    def _train_reward(self, rs, ms: PebbleState, key):
        s, p = self.scfg, self.pcfg
        iters = surf_iterations(p.reward_epochs, ms.prefs.count, p.reward_batch)
        params, opt, m = train_reward_surf(
            ms.reward, ms.reward_opt, ms.prefs, ms.ext.pool, key, iters, tx=self.reward_tx,
            reward_cfg=self.reward_cfg, batch_size=p.reward_batch, mu=s.mu,
            segment_len=p.segment_len, window=s.window, crop_range=s.crop_range,
            threshold_u=s.threshold_u, lambda_u=s.lambda_u)
        m = {k: v.astype(jnp.float32) for k, v in m.items() if k != "reward/train_acc_member"}
        return ms.replace(reward=params, reward_opt=opt), m


def surf_preset(task: str, preset: str, sac) -> dict:
    """PEBBLE's preset plus SURF's config; the window shrinks only where H + 2w would not fit
    an episode (the smoke preset's short toy episodes)."""
    out = pebble_preset(task, preset, sac)
    room = (task_info(task).episode_length - 1 - out["pebble"].segment_len) // 2
    w = min(SurfConfig.window, room)
    return {**out, "surf": SurfConfig(window=w, crop_range=min(SurfConfig.crop_range, w))}


def spec(name: str) -> MethodSpec:
    return MethodSpec(name=name, build=Surf, sections={"pebble": PebbleConfig, "surf": SurfConfig},
                      preset=surf_preset)
