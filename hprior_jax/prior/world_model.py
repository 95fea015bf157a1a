"""TWM-style world model for vector states and continuous actions (appendix C; TWM, Robine et al. 2023).

Observation model (appendix C.1): MLP encoder obs -> 512 -> 512 -> 32 (SiLU), decoder
32 -> 512 -> 512 -> obs_size. The latent is a deterministic continuous 32-vector: the appendix
says "output layer of size (32,)"; TWM's 32x32 categorical latent would be "(32, 32)".
Loss: -log N(o; dec(enc(o)), I) up to a constant = 0.5·Σ_dims (o - recon)², mean over samples
(TWM's decoder loss; its entropy/consistency terms exist only for categorical latents).

Dynamics (appendix C.2): Transformer-XL (hprior_jax.networks.transformer_xl, TWM defaults) over
interleaved tokens s_0, a_0, s_1, a_1, ...: state token = SiLU(Linear(z_t)) with z_t = sg(enc(s_t))
(TWM detaches z), action token = SiLU(Linear(a_t)) (TWM's MLP embed with post-activation,
replacing nn.Embedding for continuous actions). No reward/discount tokens or heads. The only head
(TWM's z head: pre-activation SiLU MLP 4 x 512, dropout) reads the output at the action token of
step t and predicts z_{t+1}.

Next-state target -- both, and why: the loss is
    latent_coef · 0.5·Σ (ẑ_{t+1} - sg(enc(s_{t+1})))²  +  next_obs_coef · 0.5·Σ (dec(ẑ_{t+1}) - s_{t+1})²
The latent term is TWM's (its dynamics loss lives in latent space). The decoded term measures
the error in state units through the (not updated) decoder: a continuous autoencoder latent has
arbitrary per-direction scale, so a latent-only MSE can under-weight state features that the
encoder squeezed into small directions. Both are masked to the T-1 steps whose next state is
inside the segment (next obs = obs[:, 1:]).

Sequence and memory length = segment length (appendix Table 5): training and credit use one
causal pass over a whole segment without XL memory (TWM also trains without memory); the
attention window (TWM: (memory_length + 1) · modalities tokens) then covers the whole segment.

Training schedule hooks (appendix C.3): `update_observation_model` and `update_dynamics` have
separate Adam optimisers (TWM: lr 1e-4, eps 1e-5, L2 1e-6, grad-norm clip 100) so the loop can
train the observation model once on the pre-training data and afterwards only the dynamics.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import partial
from typing import Any, Literal, get_args

import flax.linen as nn
import flax.struct
import jax
import jax.numpy as jnp
import optax

from hprior_jax.buffers.episodes import segment_rows
from hprior_jax.networks.elementwise import Dropout, DropoutBits, silu_tanh
from hprior_jax.networks.transformer_xl import TransformerXL, TransformerXLConfig
from hprior_jax.prior.obs_scaler import MIN_OBS_STD, ObsScaler, fit_obs_scaler, scaled  # noqa: F401

Params = Any

# TWM init (nets.py): kaiming-uniform with ReLU gain for SiLU layers, gain 1 for a final linear
# layer, zero biases.
_relu_gain_init = nn.initializers.variance_scaling(2.0, "fan_in", "uniform")
_linear_init = nn.initializers.variance_scaling(1.0, "fan_in", "uniform")


Prediction = Literal["state", "delta"]
PREDICTIONS = get_args(Prediction)
DropoutRng = Literal["hash", "rbg", "threefry"]
DROPOUT_RNGS = get_args(DropoutRng)
# fold_in tag of the world model's random stream (its init, updates and dropout), kept apart
# from the run's stream so that λ = 0 draws exactly PEBBLE's numbers
RANDOM_STREAM = 0x574D


def dropout_key(key: jax.Array, impl: str) -> jax.Array:
    """The dropout key in the PRNG implementation `impl` ("rbg": seeded from `key`'s bits;
    "hash" hashes bits drawn from `key` itself)."""
    if impl in ("threefry", "hash"):
        return key
    return jax.random.wrap_key_data(jax.random.bits(key, (4,), jnp.uint32), impl=impl)


@dataclass(frozen=True)
class WorldModelConfig:
    """Architecture, data and optimiser settings. Defaults: appendix C / Table 5 and TWM's config
    (the transformer's sizes are TransformerXLConfig's, which holds them)."""

    obs_size: int
    act_size: int
    latent_dim: int = 32
    obs_hidden: tuple[int, ...] = (512, 512)
    embed_dim: int = TransformerXLConfig.embed_dim
    num_heads: int = TransformerXLConfig.num_heads
    head_dim: int = TransformerXLConfig.head_dim
    num_layers: int = TransformerXLConfig.num_layers
    ff_dim: int = TransformerXLConfig.ff_dim
    dropout: float = TransformerXLConfig.dropout
    head_hidden: tuple[int, ...] = (512, 512, 512, 512)  # TWM dyn_z_dims
    segment_len: int = 50  # world-model sequence length = query segment length (Table 5)
    memory_len: int = 50  # steps (Table 5)
    batch_size: int = 100  # Table 5
    scale_by_model_dim: bool = True  # TWM's 1/sqrt(embed_dim) attention scale
    obs_lr: float = 1e-4
    obs_wd: float = 1e-6
    obs_eps: float = 1e-5
    obs_grad_clip: float = 100.0
    dyn_lr: float = 1e-4
    dyn_wd: float = 1e-6
    dyn_eps: float = 1e-5
    dyn_grad_clip: float = 100.0
    latent_coef: float = 1.0
    next_obs_coef: float = 1.0
    # Unrolled layers: a dynamics update measured 1.27x faster than under the layer scan at
    # the paper size and 1.13x at the reduced one
    # (benchmarks/results/updates/world_model_update.csv); compiling takes about twice as long
    # at the paper size.
    unroll_layers: bool = True
    # Where dropout's random bits come from (the same Bernoulli masks in distribution; each a
    # different random stream): "hash" (networks.elementwise.Dropout) fuses them into the op
    # that applies the mask; "rbg" (XLA's RngBitGenerator) and "threefry" (the key itself)
    # write them to memory first. benchmarks/results/updates/world_model_update.csv times all three.
    dropout_rng: DropoutRng = "hash"
    # What the head predicts (`predict_next`): "state" (TWM and the paper: ẑ_{t+1} itself) or
    # "delta", an option neither has: the change from z_t, decoded as the change from s_t.
    predict: Prediction = "state"

    def __post_init__(self):
        if self.obs_size < 1 or self.act_size < 1:
            raise ValueError("obs_size and act_size must be >= 1")
        if self.memory_len + 1 < self.segment_len:
            raise ValueError(f"memory_len={self.memory_len} < segment_len-1: the last step could not "
                             "see the first; set memory_len = segment_len (appendix Table 5)")
        if self.predict not in PREDICTIONS:
            raise ValueError(f"predict={self.predict!r}; choose one of {PREDICTIONS}")
        if self.dropout_rng not in DROPOUT_RNGS:
            raise ValueError(f"dropout_rng={self.dropout_rng!r}; choose one of {DROPOUT_RNGS}")

    def transformer(self) -> TransformerXLConfig:
        # TWM PredictionNet with modalities (z, a), num_current = 2.
        return TransformerXLConfig(
            embed_dim=self.embed_dim, num_heads=self.num_heads, head_dim=self.head_dim,
            num_layers=self.num_layers, ff_dim=self.ff_dim, dropout=self.dropout,
            activation="silu", mem_len=2 * self.memory_len + 2,
            window=2 * (self.memory_len + 1), norm_first=False,
            scale_by_model_dim=self.scale_by_model_dim, unroll_layers=self.unroll_layers,
            dropout_bits=self.dropout_bits)

    @property
    def dropout_bits(self) -> DropoutBits:
        return "hash" if self.dropout_rng == "hash" else "key"


class MLP(nn.Module):
    """TWM `MLP`: hidden Dense -> SiLU (-> dropout); optional SiLU before the first layer."""

    hidden: tuple[int, ...]
    out_dim: int
    pre_activation: bool = False
    dropout: float = 0.0
    dropout_bits: DropoutBits = "hash"
    out_init: Any = _linear_init

    @nn.compact
    def __call__(self, x, deterministic: bool = True):
        if self.pre_activation:
            x = silu_tanh(x)
        for w in self.hidden:
            x = silu_tanh(nn.Dense(w, kernel_init=_relu_gain_init, bias_init=nn.initializers.zeros)(x))
            if self.dropout > 0:
                x = Dropout(self.dropout, self.dropout_bits)(x, deterministic)
        return nn.Dense(self.out_dim, kernel_init=self.out_init, bias_init=nn.initializers.zeros)(x)


class ObservationModel(nn.Module):
    cfg: WorldModelConfig

    def setup(self):
        self.encoder = MLP(self.cfg.obs_hidden, self.cfg.latent_dim)
        self.decoder = MLP(self.cfg.obs_hidden, self.cfg.obs_size)

    def encode(self, obs):
        return self.encoder(obs)

    def decode(self, z):
        return self.decoder(z)

    def __call__(self, obs):
        return self.decode(self.encode(obs))


class DynamicsModel(nn.Module):
    """z[B, T, dz], act[B, T, da] -> (ẑ_next[B, T, dz], new_mems, attn[B, L, H, 2T, M + 2T]).

    Token 2t is s_t, token 2t+1 is a_t; ẑ_next[:, t] is read at token 2t+1 and predicts z_{t+1}.
    """

    cfg: WorldModelConfig

    @nn.compact
    def __call__(self, z, act, mems=None, key_mask=None, deterministic: bool = True):
        c = self.cfg
        b, t, _ = z.shape
        ez = silu_tanh(nn.Dense(c.embed_dim, kernel_init=_relu_gain_init, name="z_embed")(z))
        ea = silu_tanh(nn.Dense(c.embed_dim, kernel_init=_relu_gain_init, name="a_embed")(act))
        tokens = jnp.stack([ez, ea], axis=2).reshape(b, 2 * t, c.embed_dim)
        h, new_mems, attn = TransformerXL(c.transformer(), name="transformer")(
            tokens, mems, key_mask, deterministic)
        # a change model starts as persistence: its output layer from zero
        out_init = nn.initializers.zeros if c.predict == "delta" else _linear_init
        head = MLP(c.head_hidden, c.latent_dim, pre_activation=True, dropout=c.dropout,
                   dropout_bits=c.dropout_bits, out_init=out_init, name="z_head")
        return head(h[:, 1::2], deterministic), new_mems, attn


@flax.struct.dataclass
class WorldModelParams:
    obs: Params
    dyn: Params


@flax.struct.dataclass
class WorldModelState:
    params: WorldModelParams
    obs_opt: Any
    dyn_opt: Any
    obs_steps: jax.Array  # int32[] gradient steps taken by each part
    dyn_steps: jax.Array


def make_optimizer(lr: float, wd: float, eps: float, clip: float) -> optax.GradientTransformation:
    """torch Adam(weight_decay=wd) after clip_grad_norm_: clip, add wd·θ to the gradient, Adam."""
    return optax.chain(optax.clip_by_global_norm(clip), optax.add_decayed_weights(wd),
                       optax.adam(lr, b1=0.9, b2=0.999, eps=eps))


def _obs_tx(cfg: WorldModelConfig):
    return make_optimizer(cfg.obs_lr, cfg.obs_wd, cfg.obs_eps, cfg.obs_grad_clip)


def _dyn_tx(cfg: WorldModelConfig):
    return make_optimizer(cfg.dyn_lr, cfg.dyn_wd, cfg.dyn_eps, cfg.dyn_grad_clip)


def init(key: jax.Array, cfg: WorldModelConfig) -> WorldModelState:
    k_obs, k_dyn = jax.random.split(key)
    obs_p = ObservationModel(cfg).init(k_obs, jnp.zeros((1, cfg.obs_size)))
    dyn_p = DynamicsModel(cfg).init(k_dyn, jnp.zeros((1, 2, cfg.latent_dim)),
                                    jnp.zeros((1, 2, cfg.act_size)))
    params = WorldModelParams(obs=obs_p, dyn=dyn_p)
    return WorldModelState(params=params, obs_opt=_obs_tx(cfg).init(obs_p),
                           dyn_opt=_dyn_tx(cfg).init(dyn_p),
                           obs_steps=jnp.zeros((), jnp.int32), dyn_steps=jnp.zeros((), jnp.int32))


def encode(obs_params: Params, obs: jax.Array, cfg: WorldModelConfig) -> jax.Array:
    """obs[..., ds] -> z[..., latent_dim]."""
    return ObservationModel(cfg).apply(obs_params, obs, method=ObservationModel.encode)


def decode(obs_params: Params, z: jax.Array, cfg: WorldModelConfig) -> jax.Array:
    """z[..., latent_dim] -> obs[..., ds]."""
    return ObservationModel(cfg).apply(obs_params, z, method=ObservationModel.decode)


def observation_loss(obs_params: Params, obs: jax.Array, cfg: WorldModelConfig):
    """Reconstruction NLL (unit Gaussian, constant dropped) on every state in obs[..., ds]."""
    recon = ObservationModel(cfg).apply(obs_params, obs)
    loss = 0.5 * jnp.sum((recon - obs) ** 2, axis=-1).mean()
    return loss, {"prior/wm_obs_loss": loss}


def dynamics(params: WorldModelParams, obs: jax.Array, act: jax.Array, cfg: WorldModelConfig, *,
             deterministic: bool = True, key: jax.Array | None = None,
             mems: jax.Array | None = None, key_mask: jax.Array | None = None):
    """Run the dynamics model on segments obs[B, T, ds], act[B, T, da].

    Returns (ẑ_next[B, T, dz], new_mems[L, B, M', D], attn[B, L, H, 2T, M + 2T]); the encoder output
    enters under stop_gradient (TWM). `key` is the dropout key (needed iff not deterministic).
    """
    z = jax.lax.stop_gradient(encode(params.obs, obs, cfg))
    rngs = None if deterministic else {"dropout": dropout_key(key, cfg.dropout_rng)}
    z_next, mems, attn = DynamicsModel(cfg).apply(params.dyn, z, act, mems, key_mask,
                                                  deterministic, rngs=rngs)
    return (z + z_next if cfg.predict == "delta" else z_next), mems, attn


def predict_next(params: WorldModelParams, obs: jax.Array, act: jax.Array, cfg: WorldModelConfig,
                 *, deterministic: bool = True, key: jax.Array | None = None):
    """(ẑ_{t+1}[B, T-1, dz], ŝ_{t+1}[B, T-1, ds]) for steps 0..T-2 of segments obs[B, T, ds],
    act[B, T, da]; ŝ through the decoder (under stop_gradient). With predict="delta" the
    decoded change is added to s_t, ŝ = s_t + dec(ẑ_{t+1}) - dec(z_t), so the observation
    model's reconstruction error cancels to first order: on MetaWorld's slowly moving 39-dim
    states it is about 30x persistence's error and would hide any dynamics learned."""
    z_pred = dynamics(params, obs, act, cfg, deterministic=deterministic, key=key)[0][:, :-1]
    dec_params = jax.lax.stop_gradient(params.obs)
    obs_pred = decode(dec_params, z_pred, cfg)
    if cfg.predict == "delta":
        # the same expression as dynamics' own z: XLA computes it once
        z_now = jax.lax.stop_gradient(encode(params.obs, obs, cfg))[:, :-1]
        obs_pred = obs[:, :-1] + obs_pred - decode(dec_params, z_now, cfg)
    return z_pred, obs_pred


def dynamics_loss(dyn_params: Params, obs_params: Params, obs: jax.Array, act: jax.Array,
                  key: jax.Array | None, cfg: WorldModelConfig, deterministic: bool = False):
    """Next-state loss on obs[B, T, ds], act[B, T, da]: steps 0..T-2 predict obs[:, 1:]."""
    params = WorldModelParams(obs=obs_params, dyn=dyn_params)
    z_pred, obs_pred = predict_next(params, obs, act, cfg, deterministic=deterministic, key=key)
    z_next = jax.lax.stop_gradient(encode(obs_params, obs[:, 1:], cfg))
    latent = 0.5 * jnp.sum((z_pred - z_next) ** 2, axis=-1).mean()
    next_obs = 0.5 * jnp.sum((obs_pred - obs[:, 1:]) ** 2, axis=-1).mean()
    loss = cfg.latent_coef * latent + cfg.next_obs_coef * next_obs
    return loss, {"prior/wm_dyn_loss": loss, "prior/wm_latent_loss": latent,
                  "prior/wm_next_obs_loss": next_obs}


def update_observation_model(state: WorldModelState, obs: jax.Array, cfg: WorldModelConfig):
    """One Adam step of the observation model on obs[..., ds]. -> (state, metrics)."""
    tx = _obs_tx(cfg)
    (_, m), g = jax.value_and_grad(observation_loss, has_aux=True)(state.params.obs, obs, cfg)
    updates, opt = tx.update(g, state.obs_opt, state.params.obs)
    p = optax.apply_updates(state.params.obs, updates)
    m = {**m, "prior/wm_obs_grad_norm": optax.global_norm(g)}
    return state.replace(params=state.params.replace(obs=p), obs_opt=opt,
                         obs_steps=state.obs_steps + 1), m


def update_dynamics(state: WorldModelState, obs: jax.Array, act: jax.Array, key: jax.Array,
                    cfg: WorldModelConfig):
    """One Adam step of the dynamics model (observation model fixed) on segments
    obs[B, T, ds], act[B, T, da], dropout on. -> (state, metrics)."""
    tx = _dyn_tx(cfg)
    (_, m), g = jax.value_and_grad(dynamics_loss, has_aux=True)(
        state.params.dyn, state.params.obs, obs, act, key, cfg, False)
    updates, opt = tx.update(g, state.dyn_opt, state.params.dyn)
    p = optax.apply_updates(state.params.dyn, updates)
    m = {**m, "prior/wm_dyn_grad_norm": optax.global_norm(g)}
    return state.replace(params=state.params.replace(dyn=p), dyn_opt=opt,
                         dyn_steps=state.dyn_steps + 1), m


PretrainOrder = Literal["joint", "observation_first"]
PRETRAIN_ORDERS = get_args(PretrainOrder)


def pretrain(state: WorldModelState, key: jax.Array, obs_buf: jax.Array, act_buf: jax.Array,
             size: jax.Array, *, cfg: WorldModelConfig, episode_len: int, num_steps: int,
             order: PretrainOrder = "joint", obs_scaler: ObsScaler | None = None):
    """The pre-training at the first feedback round. "joint": `num_steps` steps of both
    models together (appendix C.3 trains both then). "observation_first" (TWM's order, an
    ablation): the observation model alone for `num_steps`, then the dynamics model alone for
    `num_steps` on the encodings it then gives (frozen). -> (state, metrics of both parts)."""
    if order not in PRETRAIN_ORDERS:
        raise ValueError(f"order={order!r}; choose one of {PRETRAIN_ORDERS}")
    run = partial(train, obs_buf=obs_buf, act_buf=act_buf, size=size, cfg=cfg,
                  episode_len=episode_len, num_steps=num_steps, obs_scaler=obs_scaler)
    if order == "joint":
        return run(state, key, observation_model=True, dynamics_model=True)
    k_obs, k_dyn = jax.random.split(key)
    state, m_obs = run(state, k_obs, observation_model=True, dynamics_model=False)
    state, m_dyn = run(state, k_dyn, observation_model=False, dynamics_model=True)
    return state, {**m_obs, **m_dyn}


def sample_segments(key: jax.Array, obs: jax.Array, act: jax.Array, size: jax.Array, *,
                    episode_len: int, batch_size: int, segment_len: int):
    """Uniform training segments from a replay buffer obs[C, ds], act[C, da]
    (`segment_rows`). Returns obs[B, T, ds], act[B, T, da]."""
    idx = segment_rows(key, size, episode_len=episode_len, batch_size=batch_size,
                       segment_len=segment_len)
    return obs[idx], act[idx]


def train(state: WorldModelState, key: jax.Array, obs_buf: jax.Array, act_buf: jax.Array,
          size: jax.Array, *, cfg: WorldModelConfig, episode_len: int, num_steps: int,
          observation_model: bool, dynamics_model: bool, obs_scaler: ObsScaler | None = None):
    """`num_steps` world-model steps on fresh segments from the replay buffer (lax.scan),
    their observations standardised by `obs_scaler` when given.

    Static flags pick the parts (appendix C.3: both after pre-training, then dynamics only every
    j steps). Returns (state, metrics averaged over the steps).
    """
    if not (observation_model or dynamics_model):
        raise ValueError("train at least one of observation_model / dynamics_model")

    def step(st, k):
        k_seg, k_drop = jax.random.split(k)
        obs, act = sample_segments(k_seg, obs_buf, act_buf, size, episode_len=episode_len,
                                   batch_size=cfg.batch_size, segment_len=cfg.segment_len)
        obs = scaled(obs_scaler, obs)
        m = {}
        if observation_model:
            st, mo = update_observation_model(st, obs, cfg)
            m.update(mo)
        if dynamics_model:
            st, md = update_dynamics(st, obs, act, k_drop, cfg)
            m.update(md)
        return st, m

    state, ms = jax.lax.scan(step, state, jax.random.split(key, num_steps))
    return state, jax.tree.map(lambda x: x.mean(0), ms)
