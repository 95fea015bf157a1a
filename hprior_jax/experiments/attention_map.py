"""Attention maps of a trained run's world model (appendix Figure 8: layers x time, state and
action tokens) for the segments in its preference store.

    hprior attention --run runs/cheetah_run_prior_... [--pair 0] [--seed 12345] [--out map.png]
"""
from __future__ import annotations

from pathlib import Path

import jax
import numpy as np

from hprior_jax.methods import registry
from hprior_jax.plotting import save_figure, wrapped
from hprior_jax.prior import world_model as wm
from hprior_jax.prior.attention import _QUERY_OFFSET, credit_from_attention
from hprior_jax.runs.restore import restore_run
from hprior_jax.runs.run_dir import load_run_config


def final_step_attention(params: wm.WorldModelParams, obs: jax.Array, act: jax.Array,
                         cfg: wm.WorldModelConfig, query: str = "action") -> tuple[jax.Array, jax.Array]:
    """One segment obs[T, ds], act[T, da] -> (rows[L, 2T], α[T]): per layer, the final step's
    attention over the segment's tokens s_0, a_0, ..., averaged over heads; α as the credit
    used in training (mean over layers, state + action entries)."""
    _, _, attn = wm.dynamics(params, obs[None], act[None], cfg, deterministic=True)
    attn = attn[0]  # [L, H, 2T, 2T]
    t = obs.shape[0]
    rows = attn[:, :, 2 * (t - 1) + _QUERY_OFFSET[query], -2 * t:].mean(axis=1)
    return rows, credit_from_attention(attn, t, query=query)


def plot_attention_map(rows: np.ndarray, alpha: np.ndarray, out_png: Path, title: str = "",
                       true_reward: np.ndarray | None = None) -> Path:
    """rows[L, 2T] as a layers x tokens heat map (states and actions in separate panels),
    α[T] (and the true per-step reward, when given) underneath."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows, alpha = np.asarray(rows), np.asarray(alpha)
    layers, t = rows.shape[0], rows.shape[1] // 2
    fig, axes = plt.subplots(3, 1, figsize=(max(6, t * 0.18), 2 + 0.5 * layers * 2 + 2),
                             gridspec_kw={"height_ratios": [layers, layers, 3]}, sharex=True)
    vmax = rows.max()
    for ax, name, part in ((axes[0], "state tokens", rows[:, 0::2]),
                           (axes[1], "action tokens", rows[:, 1::2])):
        im = ax.imshow(part, aspect="auto", cmap="viridis", vmin=0, vmax=vmax,
                       extent=(-0.5, t - 0.5, layers - 0.5, -0.5))
        ax.set_yticks(range(layers))
        ax.set_ylabel(f"layer\n({name})")
    # The colorbar takes its width from all three panels so that the heat maps and
    # the α bars keep one time axis.
    # above the panels: the right side holds the true reward's axis
    fig.colorbar(im, ax=axes.tolist(), location="top", shrink=0.6, aspect=40, pad=0.02,
                 label="attention of the final step")
    axes[2].bar(np.arange(t), alpha, color="tab:orange", label="α (mean over layers)")
    handles = axes[2].get_legend_handles_labels()
    if true_reward is not None:
        ax2 = axes[2].twinx()
        ax2.plot(np.arange(t), true_reward, color="k", lw=1, label="true reward")
        ax2.set_ylabel("true reward")
        more = ax2.get_legend_handles_labels()
        handles = (handles[0] + more[0], handles[1] + more[1])
    axes[2].legend(*handles, fontsize=7, loc="upper left")
    axes[2].set_xlabel("time step in segment")
    axes[2].set_ylabel("α")
    fig.suptitle(wrapped(title, 70))
    out_png = save_figure(fig, Path(out_png), bbox_inches="tight")
    plt.close(fig)
    return out_png


def attention_maps_for_run(run_dir: Path, pair: int = 0, seed: int | None = None,
                           out: Path | None = None) -> list[Path]:
    """Restores the latest checkpoint of a run with a world model (PRIOR, PRIOR-NRP) and draws both segments of stored
    preference pair `pair` for `seed` (default: the run's first). Returns the PNG paths."""
    run_dir = Path(run_dir)
    cfg = load_run_config(run_dir)
    if not registry.get(cfg.algo).has_world_model:
        raise ValueError(f"{run_dir} is a --algo {cfg.algo} run; attention maps need a "
                         "method with a world model")
    if seed is not None and seed not in cfg.seeds:
        raise ValueError(f"seed {seed} is not in this run; its seeds are {list(cfg.seeds)}")
    restored = restore_run(run_dir)
    cfg, engine, step = restored.cfg, restored.engine, restored.step
    seed = cfg.seeds[0] if seed is None else seed
    state = restored.of_seed(seed)
    ms = state.method
    prefs, wm_params = ms.prefs, ms.ext.wm.params
    count = int(prefs.count)
    if not 0 <= pair < count:
        raise ValueError(f"--pair {pair}: the run has {count} labelled pairs at step {step}; "
                         f"choose 0..{count - 1}")
    fn = jax.jit(lambda p, o, a: final_step_attention(p, o, a, engine.method.ext.wm_cfg,
                                                      cfg.prior.attention_query))
    scaler = engine.method.ext.obs_scaler(state.replay)  # as the world model read them
    out = Path(out) if out else run_dir / "attention"
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for side, (obs, act) in enumerate(((prefs.obs1, prefs.act1), (prefs.obs2, prefs.act2)),
                                      start=1):
        rows, alpha = fn(wm_params, wm.scaled(scaler, obs[pair]), act[pair])
        verdict = _verdict(int(prefs.labels[pair]), side)
        title = (f"{cfg.task} seed {seed} step {step}: pair {pair}, segment {side} "
                 f"({verdict})")
        true_reward = segment_true_reward(state.replay, np.asarray(obs[pair]))
        paths.append(plot_attention_map(np.asarray(rows), np.asarray(alpha),
                                        out / f"seed{seed}_pair{pair}_seg{side}.png", title,
                                        true_reward=true_reward))
    return paths


def _verdict(label: int, side: int) -> str:
    """The teacher's answer (B-Pref: 0 the first segment, 1 the second, -1 equal) as seen
    from segment `side`."""
    if label == -1:
        return "teacher: equally good"
    return "preferred by the teacher" if label == side - 1 else "not preferred by the teacher"


def segment_true_reward(replay, seg_obs: np.ndarray) -> np.ndarray | None:
    """The true per-step reward of a stored segment, found in the replay buffer by its
    observations (the preference store keeps none: only the teacher reads the true reward);
    None if the segment is not there (an overwritten row)."""
    obs = np.asarray(replay.obs)[:int(replay.size)]
    t = len(seg_obs)
    for start in np.flatnonzero(np.all(obs == seg_obs[0], axis=-1)):
        if start + t <= len(obs) and np.array_equal(obs[start:start + t], seg_obs):
            return np.asarray(replay.true_reward)[start:start + t]
    return None

