"""A critical-event probe for the world model's credit α.

Synthetic episodes where the next state at one step can be predicted only from one earlier
action: at a random step t* a gate flag is on; `delay` steps later the observation reveals the
action taken at t*. Everything else is either predictable from the last step (a sinusoid) or
noise-free zero. A world model that learns the reveal must attend to a_{t*}; α of a segment
that ends just before the reveal should then put its mass on t*, not on the last steps.

    obs_t = [gate_t, reveal_t, value_t, sin(ω t + φ)]     act_t ~ U[-1, 1]
    gate_t = 1[t = t*], reveal_t = 1[t = t* + delay], value_t = a_{t*} · reveal_t

With `reveal="every_step"` (a control) every observation from step `delay` on reveals the
action taken `delay` steps before it (reveal_t = 1[t >= delay], value_t = a_{t-delay}, no
gate): the same look-back, but at every step instead of once an episode, so a world model that
fails the probe yet learns this one can attend back and lacks the training signal.

    python -m benchmarks.research.lab_probe --steps 3000 [--delay 30]   # prints the numbers as JSON
    python -m benchmarks.research.lab_probe --order observation_first --prior-set wm_lr=0.001
    python -m benchmarks.research.lab_probe --reveal every_step --delay 5
"""
from __future__ import annotations

import argparse
import json
import time
from dataclasses import asdict, dataclass

import tasks  # noqa: F401  (sets XLA_FLAGS before jax is imported)
import jax
import jax.numpy as jnp
import numpy as np

from hprior_jax.lab.sweep import with_settings
from hprior_jax.methods.prior import REDUCED_WORLD_MODEL, PriorConfig
from hprior_jax.prior import world_model as wm
from hprior_jax.prior.attention import segment_credit

OBS_SIZE, ACT_SIZE = 4, 1
REVEALS = ("once", "every_step")


@dataclass(frozen=True)
class ProbeConfig:
    episodes: int = 400  # training episodes (another quarter as many held out)
    episode_len: int = 100
    delay: int = 30  # steps from the gate to the reveal
    segment_len: int = 50  # α's segment: the reduced preset's query length
    steps: int = 3000  # world-model updates (observation and dynamics models together)
    order: str = "joint"  # or "observation_first": `steps` of each model, one after the other
    settings: tuple[str, ...] = ()  # FIELD=VALUE over the reduced preset's PriorConfig
    reveal: str = "once"  # or "every_step": a_{t-delay} shown at every step (the control)

    def __post_init__(self):
        if self.reveal not in REVEALS:
            raise ValueError(f"reveal must be one of {REVEALS}, got {self.reveal!r}")


def probe_episodes(key: jax.Array, n: int, cfg: ProbeConfig):
    """obs[n, L, 4], act[n, L, 1], t_star[n]; t* leaves room for a full segment before the
    reveal (t* + delay >= segment_len) and for the reveal inside the episode. Every step:
    t* is only where the evaluation reads, obs[t* + delay] shows a_{t*} either way."""
    k_t, k_a, k_p = jax.random.split(key, 3)
    L, d = cfg.episode_len, cfg.delay
    t_star = jax.random.randint(k_t, (n,), cfg.segment_len - d, L - d)
    act = jax.random.uniform(k_a, (n, L, ACT_SIZE), minval=-1.0, maxval=1.0)
    t = jnp.arange(L)
    if cfg.reveal == "every_step":
        gate = jnp.zeros((n, L))
        reveal = jnp.broadcast_to((t >= d).astype(jnp.float32), (n, L))
        value = reveal * jnp.roll(act[..., 0], d, axis=1)  # a_{t-d}; the wrapped steps are 0
    else:
        gate = (t[None] == t_star[:, None]).astype(jnp.float32)
        reveal = (t[None] == (t_star + d)[:, None]).astype(jnp.float32)
        value = reveal * act[jnp.arange(n), t_star, 0][:, None]
    phase = jax.random.uniform(k_p, (n, 1), maxval=2 * jnp.pi)
    wave = jnp.sin(0.3 * t[None] + phase)
    return jnp.stack([gate, reveal, value, wave], -1), act, t_star


def world_model_config(segment_len: int, settings=()) -> wm.WorldModelConfig:
    """The reduced preset's world model (hprior_jax.methods.prior.REDUCED_WORLD_MODEL), with
    `settings` (FIELD=VALUE of PriorConfig, e.g. wm_layers=4, wm_lr=0.001)."""
    sizes = {k: v for k, v in REDUCED_WORLD_MODEL.items() if not k.endswith("_steps")}
    prior = with_settings(PriorConfig(**sizes), list(settings))
    return prior.world_model(OBS_SIZE, ACT_SIZE, segment_len)


def run_probe(cfg: ProbeConfig, seed: int = 0) -> dict:
    """Trains the world model on probe episodes; returns α's mass on t* for segments ending
    just before the reveal (and on the last 8 steps, and uniform's share), and the error of
    the predicted reveal value against predicting 0."""
    wcfg = world_model_config(cfg.segment_len, cfg.settings)
    k_data, k_test, k_init, k_train = jax.random.split(jax.random.PRNGKey(seed), 4)
    obs, act, _ = probe_episodes(k_data, cfg.episodes, cfg)
    flat = lambda x: x.reshape((-1,) + x.shape[2:])

    @jax.jit
    def train(key):
        state = wm.init(k_init, wcfg)
        return wm.pretrain(state, key, flat(obs), flat(act),
                           jnp.int32(obs.shape[0] * obs.shape[1]), cfg=wcfg,
                           episode_len=cfg.episode_len, num_steps=cfg.steps, order=cfg.order)

    t0 = time.perf_counter()
    state, metrics = jax.block_until_ready(train(k_train))
    train_s = time.perf_counter() - t0

    # held-out segments that end one step before the reveal: t* sits at T - 1 - (delay - 1)
    n_test = max(cfg.episodes // 4, 8)
    obs_t, act_t, t_star = probe_episodes(k_test, n_test, cfg)
    T = cfg.segment_len
    start = t_star + cfg.delay - T
    window = jax.vmap(lambda x, s: jax.lax.dynamic_slice_in_dim(x, s, T, axis=0))
    seg_obs, seg_act = window(obs_t, start), window(act_t, start)
    alpha = np.asarray(jax.jit(lambda o, a: segment_credit(state.params, o, a, wcfg))(
        seg_obs, seg_act))
    at = T - cfg.delay  # t*'s index in the segment
    # the reveal predicted from the segment (the last step's prediction) vs its true value
    z_pred, _, _ = wm.dynamics(state.params, seg_obs, seg_act, wcfg, deterministic=True)
    pred = np.asarray(wm.decode(state.params.obs, z_pred[:, -1], wcfg))
    truth = np.asarray(act_t[jnp.arange(n_test), t_star, 0])
    # can the observation model carry the value at all? its reconstruction of the reveal step
    reveal_obs = obs_t[jnp.arange(n_test), t_star + cfg.delay]
    recon = np.asarray(wm.decode(state.params.obs, wm.encode(state.params.obs, reveal_obs, wcfg),
                                 wcfg))
    return {
        "config": asdict(cfg), "world_model": {"layers": wcfg.num_layers,
                                               "embed": wcfg.embed_dim, "lr": wcfg.dyn_lr},
        "train_seconds": round(train_s, 1), "segments": n_test,
        "final_dyn_loss": float(metrics["prior/wm_dyn_loss"]),
        "alpha_at_t_star": _mean_ci(alpha[:, at]),
        "alpha_last_8": _mean_ci(alpha[:, -8:].sum(1)),
        "uniform": 1.0 / T,
        "t_star_rank_1_share": float(np.mean(alpha.argmax(1) == at)),
        "reveal_mse": float(np.mean((pred[:, 2] - truth) ** 2)),
        "reveal_mse_predict_zero": float(np.mean(truth ** 2)),
        "reveal_reconstruction_mse": float(np.mean((recon[:, 2] - truth) ** 2)),
    }


def _mean_ci(x: np.ndarray) -> dict:
    from scipy import stats

    x = np.asarray(x, np.float64)
    half = stats.t.ppf(0.975, len(x) - 1) * x.std(ddof=1) / np.sqrt(len(x))
    return {"mean": float(x.mean()), "ci95": [float(x.mean() - half), float(x.mean() + half)]}


def main() -> None:

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=ProbeConfig.steps)
    parser.add_argument("--episodes", type=int, default=ProbeConfig.episodes)
    parser.add_argument("--delay", type=int, default=ProbeConfig.delay)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--order", default="joint", choices=wm.PRETRAIN_ORDERS)
    parser.add_argument("--reveal", default="once", choices=REVEALS,
                        help="every_step: the control with the look-back at every step")
    parser.add_argument("--prior-set", nargs="+", default=(), metavar="FIELD=VALUE",
                        help="the world model's settings, e.g. wm_layers=4 wm_lr=0.001")
    args = parser.parse_args()
    out = run_probe(ProbeConfig(episodes=args.episodes, steps=args.steps, delay=args.delay,
                                order=args.order, settings=tuple(args.prior_set),
                                reveal=args.reveal), args.seed)
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
