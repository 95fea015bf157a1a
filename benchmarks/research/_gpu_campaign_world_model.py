"""Part 1 of `benchmarks/research/gpu_campaign.py`: the lab's world model trained on a lab dataset,
several seeds vmapped, in chunks (so the campaign can time it, stop between chunks and read
diagnostics at checkpoints), and the seeds' contexts that the lab's rounds read (part 3).

Training is the lab's (`lab.seed_world_model.train_seed_context`): per seed, the key folded
with the world model's stream and split into (init, pre-training, dynamics, profile) keys;
`pretrain_steps` joint steps (observation and dynamics models, `wm.train`'s joint step),
then dynamics-only steps. Here each chunk of `chunk` steps draws its step keys from
`fold_in(phase key, chunk index)` instead of one scan's split: the same schedule and
sampling, another random stream. One
compiled program serves both phases (a `lax.cond` on an unbatched flag around the
observation-model step), so the paper-size update compiles once, not twice.

Diagnostics at a checkpoint, per seed, on the lab's fixed held-out segments
(`held_out_segments`, as the lab's own): `world_model_diagnostics` (skill over persistence,
α's position R², the time-shuffle TVs, α's correlation with the reward's within-segment
deviation) and what it lacks:

  alpha/residual_abs_dr_corr         Pearson, over every (segment, step t >= 1), of α_t minus
                                     the positional profile at t against |r_t - r_{t-1}|
  alpha/residual_abs_dr_corr_within  the same correlation within each segment, mean over the
                                     segments where both vary

The positional profile is the lab's: mean α per position over `profile_segments` training
segments drawn with the seed's profile key (`SeedContext.profile`).
"""
from __future__ import annotations

import time
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from hprior_jax.lab.seed_world_model import SeedContext, held_out_segments
from hprior_jax.prior import world_model as wm
from hprior_jax.prior.attention import segment_credit
from hprior_jax.prior.diagnostics import world_model_diagnostics


def residual_vs_reward_change(alpha: jax.Array, profile: jax.Array,
                              reward: jax.Array) -> dict[str, jax.Array]:
    """α[B, T] minus profile[T] against |Δr| of reward[B, T] (steps 1..T-1): the pooled and
    the mean within-segment Pearson correlation (module docstring)."""
    res = alpha[:, 1:] - profile[1:]
    dr = jnp.abs(reward[:, 1:] - reward[:, :-1])

    def pearson(x, y, axis):
        x = x - x.mean(axis, keepdims=True)
        y = y - y.mean(axis, keepdims=True)
        norm = jnp.sqrt(jnp.sum(x ** 2, axis) * jnp.sum(y ** 2, axis))
        return jnp.sum(x * y, axis) / jnp.maximum(norm, 1e-20), norm > 1e-12

    pooled, _ = pearson(res.ravel(), dr.ravel(), 0)
    within, varies = pearson(res, dr, 1)
    within = jnp.sum(jnp.where(varies, within, 0.0)) / jnp.maximum(varies.sum(), 1)
    return {"alpha/residual_abs_dr_corr": pooled,
            "alpha/residual_abs_dr_corr_within": within}


class WorldModels:
    """`seeds` world models of config `cfg` on `data`'s training episodes, vmapped."""

    def __init__(self, data, cfg: wm.WorldModelConfig, seeds: tuple[int, ...], *,
                 pretrain_steps: int, chunk: int, query: str = "action",
                 profile_segments: int = 256, diagnostic_segments: int = 256):
        if pretrain_steps % chunk:
            raise ValueError(f"pretrain_steps={pretrain_steps} is not a multiple of the "
                             f"chunk ({chunk}): a chunk would straddle the two phases")
        self.cfg, self.seeds, self.chunk = cfg, tuple(seeds), chunk
        self.pretrain_steps, self.query = pretrain_steps, query
        self.profile_segments = profile_segments
        self.episode_len = data.train_obs.shape[1]
        flat = lambda x: jnp.asarray(x.reshape((-1,) + x.shape[2:]))
        self.obs_buf, self.act_buf = flat(data.train_obs), flat(data.train_act)
        self.size = jnp.int32(self.obs_buf.shape[0])
        self.held = held_out_segments(data, data.segment_len, diagnostic_segments)
        keys = jnp.stack([jax.random.PRNGKey(s) for s in self.seeds])
        streams = jax.vmap(lambda k: jax.random.split(jax.random.fold_in(k, wm.RANDOM_STREAM), 4))
        self.k_init, self.k_pre, self.k_dyn, self.k_seg = jnp.moveaxis(streams(keys), 1, 0)
        self.updates = 0
        self.state = None
        self.last_loss = None  # [S] the mean dynamics loss of the last chunk
        self.compile_seconds: dict[str, float] = {}
        self._chunk = self._diagnose = None

    # -- programs ---------------------------------------------------------------------
    def _one_chunk(self, state, key, joint, obs_buf, act_buf, size):
        cfg = self.cfg

        def step(st, k):
            k_seg, k_drop = jax.random.split(k)
            obs, act = wm.sample_segments(k_seg, obs_buf, act_buf, size,
                                          episode_len=self.episode_len,
                                          batch_size=cfg.batch_size, segment_len=cfg.segment_len)
            st = jax.lax.cond(joint, lambda s: wm.update_observation_model(s, obs, cfg)[0],
                              lambda s: s, st)
            st, m = wm.update_dynamics(st, obs, act, k_drop, cfg)
            return st, m["prior/wm_dyn_loss"]

        state, losses = jax.lax.scan(step, state, jax.random.split(key, self.chunk))
        return state, losses.mean()

    def _one_diagnosis(self, params, k_seg, obs, act, reward, perm, obs_buf, act_buf, size):
        out = world_model_diagnostics(params, obs, act, reward, perm, self.cfg, query=self.query)
        seg_obs, seg_act = wm.sample_segments(k_seg, obs_buf, act_buf, size,
                                              episode_len=self.episode_len,
                                              batch_size=self.profile_segments,
                                              segment_len=self.cfg.segment_len)
        credit = partial(segment_credit, cfg=self.cfg, query=self.query)
        profile = credit(params, seg_obs, seg_act).mean(0)
        out |= residual_vs_reward_change(credit(params, obs, act), profile, reward)
        return out, profile

    def compile(self) -> float:
        """Initial states and the chunk program, compiled ahead. -> seconds."""
        t0 = time.perf_counter()
        self.state = jax.block_until_ready(
            jax.jit(jax.vmap(lambda k: wm.init(k, self.cfg)))(self.k_init))
        fn = jax.jit(jax.vmap(self._one_chunk, (0, 0, None, None, None, None)),
                     donate_argnums=0)
        args = (self.state, self.k_pre, jnp.asarray(True), self.obs_buf, self.act_buf, self.size)
        self._chunk = fn.lower(*args).compile()
        self.compile_seconds["train"] = time.perf_counter() - t0
        return self.compile_seconds["train"]

    # -- running ----------------------------------------------------------------------
    def train(self, steps: int, stop=lambda: False) -> dict:
        """`steps` more updates (a multiple of the chunk), chunk by chunk; `stop()` is asked
        between chunks. -> {"updates", "seconds"} of this call."""
        if steps % self.chunk:
            raise ValueError(f"{steps} updates is not a multiple of the chunk ({self.chunk})")
        if self._chunk is None:
            self.compile()
        t0, done = time.perf_counter(), 0
        while done < steps and not (done and stop()):
            joint = self.updates < self.pretrain_steps
            index = (self.updates if joint else self.updates - self.pretrain_steps) // self.chunk
            keys = jax.vmap(jax.random.fold_in, (0, None))(self.k_pre if joint else self.k_dyn,
                                                            index)
            self.state, loss = self._chunk(self.state, keys, jnp.asarray(joint), self.obs_buf,
                                           self.act_buf, self.size)
            done += self.chunk
            self.updates += self.chunk
            self.last_loss = np.asarray(loss)  # waits for the chunk
        return {"updates": done, "seconds": time.perf_counter() - t0}

    def diagnose(self) -> tuple[list[dict], np.ndarray, float]:
        """Diagnostics of every seed at the current update count. -> (one row per seed,
        profiles [S, T], seconds, its compile included the first time)."""
        t0 = time.perf_counter()
        args = (self.state.params, self.k_seg, *self.held, self.obs_buf, self.act_buf, self.size)
        if self._diagnose is None:
            in_axes = (0, 0) + (None,) * 7
            self._diagnose = jax.jit(jax.vmap(self._one_diagnosis, in_axes)).lower(
                *args).compile()
            self.compile_seconds["diagnostics"] = time.perf_counter() - t0
        out, profile = jax.device_get(self._diagnose(*args))
        rows = [dict(seed=seed, updates=self.updates, train_dyn_loss=float(self.last_loss[i]),
                     **{k: float(v[i]) for k, v in out.items()})
                for i, seed in enumerate(self.seeds)]
        return rows, np.asarray(profile), time.perf_counter() - t0

    def seed_contexts(self, seeds: int, profiles: np.ndarray) -> SeedContext:
        """The lab's contexts [seeds, ...] for seeds 0..seeds-1 from these world models: seed
        i reads world model i mod S (and its profile)."""
        pick = jnp.arange(seeds) % len(self.seeds)
        params = jax.tree.map(lambda x: x[pick], self.state.params)
        return SeedContext(wm_params=params, profile=jnp.asarray(profiles)[pick])
