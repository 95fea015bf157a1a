"""Hindsight PRIOR's run configuration (appendix C.3, Tables 4-5; reference/prior_spec.md §3, §5).

The reward side (λ, variant) and the world model's schedule and size. Network defaults are TWM's
(Robine et al. 2023) with the appendix Table 5 changes; `hprior_jax.presets` shrinks them for the
reduced and smoke budgets.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from hprior_jax.prior.loss import VARIANTS, PriorConfig
from hprior_jax.prior.world_model import DropoutRng, WorldModelConfig


@dataclass(frozen=True)
class PriorRunConfig:
    lam: float = 5.0
    """λ, the prior loss weight: appendix Table 4 gives 5 for DMC and 1000 for MetaWorld (the
    presets pick the task's). 0 trains exactly PEBBLE's reward."""
    variant: Literal["prior", "nrp", "rvar"] = "prior"
    """`nrp` = PRIOR-NRP (appendix eq. 9); `rvar` = uniform redistribution (appendix G.1)."""
    wm_every: int = 2000
    """j: env steps between dynamics-model updates after pre-training (appendix C.3)."""
    wm_pretrain_steps: int = 1000
    """Gradient steps on observation + dynamics model at the end of pre-training. The paper does
    not give this number; ours, with `wm_update_steps`, keeps ~1 world-model step per 20 env steps."""
    wm_update_steps: int = 100
    """Dynamics-model gradient steps every `wm_every` env steps (not given by the paper)."""
    attention_query: Literal["action", "state"] = "action"
    """Which final-step token's attention row is read (see prior/attention.py for why action)."""
    # world model sizes (TWM defaults; appendix Table 5 sets sequence = memory = segment length)
    wm_batch: int = 100
    wm_latent: int = 32
    wm_obs_hidden: int = 512
    wm_obs_depth: int = 2
    wm_embed: int = 256
    wm_layers: int = 10
    wm_heads: int = 4
    wm_head_dim: int = 64
    wm_ff: int = 1024
    wm_head_hidden: int = 512
    wm_head_depth: int = 4
    wm_dropout: float = 0.1
    wm_dropout_rng: DropoutRng = "rbg"
    """PRNG of the world model's dropout masks: rbg is faster on CPU (see WorldModelConfig)."""
    wm_lr: float = 1e-4

    def __post_init__(self):
        if self.variant not in VARIANTS:
            raise ValueError(f"--prior.variant {self.variant!r}; choose one of {VARIANTS}")
        if self.lam < 0:
            raise ValueError(f"--prior.lam must be >= 0, got {self.lam}")
        for name in ("wm_every", "wm_batch", "wm_latent", "wm_obs_hidden", "wm_embed",
                     "wm_layers", "wm_heads", "wm_head_dim", "wm_ff", "wm_head_hidden"):
            if getattr(self, name) <= 0:
                raise ValueError(f"--prior.{name.replace('_', '-')} must be positive, "
                                 f"got {getattr(self, name)}")
        if self.wm_pretrain_steps < 1 and self.variant != "rvar":
            raise ValueError("--prior.wm-pretrain-steps must be >= 1: attention from an untrained "
                             "world model is noise (use --prior.variant rvar for no world model)")
        if self.wm_update_steps < 0:
            raise ValueError("--prior.wm-update-steps must be >= 0")
        if not 0.0 <= self.wm_dropout < 1.0:
            raise ValueError(f"--prior.wm-dropout must be in [0, 1), got {self.wm_dropout}")

    def loss(self) -> PriorConfig:
        return PriorConfig(lam=self.lam, variant=self.variant)

    def world_model(self, obs_size: int, act_size: int, segment_len: int) -> WorldModelConfig:
        return WorldModelConfig(
            obs_size=obs_size, act_size=act_size, latent_dim=self.wm_latent,
            obs_hidden=(self.wm_obs_hidden,) * self.wm_obs_depth, embed_dim=self.wm_embed,
            num_heads=self.wm_heads, head_dim=self.wm_head_dim, num_layers=self.wm_layers,
            ff_dim=self.wm_ff, dropout=self.wm_dropout, dropout_rng=self.wm_dropout_rng,
            head_hidden=(self.wm_head_hidden,) * self.wm_head_depth, segment_len=segment_len,
            memory_len=segment_len, batch_size=self.wm_batch, obs_lr=self.wm_lr, dyn_lr=self.wm_lr)
