"""A seed's world model for the lab: trained once per seed on the training episodes, before
any round, and fixed after (the RL loop keeps training it; here the data does not change);
with the held-out segments its diagnostics read.

The trained world models are kept on disk so that another lab of the same dataset, seeds and
world-model settings (a λ sweep, PRIOR's ablations, another label budget or query rule) loads
them instead of training them again: on cheetah_run the world model is about half of a
10-seed lab's time. A world model is a deterministic function of what the cache key names:
the dataset's training episodes, the seeds, the world-model config, its training schedule
(pre-training steps, dynamics steps, order), whether its observations are standardised, the
credit settings of the positional profile, the code that trains and reads it (its source
files' bytes, this module's included) and the jax version. Anything else that changed it
would be a bug in this list; `--no-world-model-cache` trains afresh.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from hprior_jax.lab.config import Episodes, LabConfig
from hprior_jax.lab.dataset import Dataset, cache_dir
from hprior_jax.prior import world_model as wm
from hprior_jax.prior.attention import segment_credit


@struct.dataclass
class SeedContext:
    """What a seed's rules share: the world model, its mean α per position and the
    standardisation of its observations (None: raw, the paper's)."""

    wm_params: wm.WorldModelParams | None
    profile: jax.Array  # [T]
    obs_scaler: wm.ObsScaler | None = None


def train_seed_context(cfg: LabConfig, segment_len: int, key: jax.Array,
                       train: Episodes) -> SeedContext:
    """A seed's world model trained on the training episodes (pre-training, then dynamics),
    and its mean α per position on `profile_segments` training segments; without a rule
that reads a world model, none and a uniform profile."""
    if not cfg.needs_world_model:
        return SeedContext(wm_params=None, profile=jnp.full((segment_len,), 1.0 / segment_len))
    k_init, k_pre, k_dyn, k_seg = jax.random.split(jax.random.fold_in(key, wm.RANDOM_STREAM), 4)
    obs, act = train.obs, train.act
    flat = lambda x: x.reshape((-1,) + x.shape[2:])
    size = jnp.int32(obs.shape[0] * obs.shape[1])
    scaler = wm.fit_obs_scaler(flat(obs), size) if cfg.wm_normalize_obs else None
    data = dict(obs_buf=flat(obs), act_buf=flat(act), size=size, cfg=cfg.world_model,
                episode_len=obs.shape[1], obs_scaler=scaler)
    state = wm.init(k_init, cfg.world_model)
    state, _ = wm.pretrain(state, k_pre, num_steps=cfg.wm_pretrain_steps,
                           order=cfg.wm_order, **data)
    if cfg.wm_steps:
        state, _ = wm.train(state, k_dyn, num_steps=cfg.wm_steps, observation_model=False,
                            dynamics_model=True, **data)
    seg_obs, seg_act = wm.sample_segments(
        k_seg, flat(obs), flat(act), size, episode_len=obs.shape[1],
        batch_size=cfg.profile_segments, segment_len=segment_len)
    alpha = segment_credit(state.params, wm.scaled(scaler, seg_obs), seg_act,
                           cfg.world_model, query=cfg.attention_query)
    return SeedContext(wm_params=state.params, profile=alpha.mean(0), obs_scaler=scaler)


def held_out_segments(data: Dataset, segment_len: int, num: int, seed: int = 0):
    """`num` fixed segments of the held-out episodes and a random step order for each:
    (obs, act, true reward, perm), the inputs of prior.diagnostics."""
    rng = np.random.default_rng(seed)
    ep = rng.integers(0, data.test_obs.shape[0], num)
    start = rng.integers(0, data.episode_length - segment_len + 1, num)
    steps = start[:, None] + np.arange(segment_len)
    cut = lambda x: jnp.asarray(x[ep[:, None], steps])
    perm = jnp.asarray(np.stack([rng.permutation(segment_len) for _ in range(num)]))
    return cut(data.test_obs), cut(data.test_act), cut(data.test_reward), perm


# the modules whose code decides the trained world model and the profile read from it
_CODE = ("prior/world_model.py", "prior/attention.py", "networks/transformer_xl.py")


def _code_digest() -> str:
    """Of the modules above and of this one (the lab's training of a seed's world model)."""
    root = Path(__file__).resolve().parent.parent
    h = hashlib.sha256()
    for name in _CODE + ("lab/seed_world_model.py",):
        h.update((root / name).read_bytes())
    return h.hexdigest()


def cache_key(cfg, data: Dataset) -> str:
    """Hex digest naming the world models of lab config `cfg` (a LabConfig) on `data`."""
    h = hashlib.sha256()
    for array in (data.train_obs, data.train_act):
        h.update(np.ascontiguousarray(array).tobytes())
    settings = dict(
        task=data.task, segment_len=data.segment_len, seeds=list(cfg.seeds),
        world_model=dataclasses.asdict(cfg.world_model), wm_pretrain_steps=cfg.wm_pretrain_steps,
        wm_steps=cfg.wm_steps, wm_order=cfg.wm_order, wm_normalize_obs=cfg.wm_normalize_obs,
        attention_query=cfg.attention_query,
        profile_segments=cfg.profile_segments, jax=jax.__version__, code=_code_digest())
    h.update(json.dumps(settings, sort_keys=True, default=str).encode())
    return h.hexdigest()[:20]


def cache_path(cfg, data: Dataset, folder: Path | None = None) -> Path:
    """Where the world models of `cfg` on `data` are kept: FOLDER/world_models/TASK_KEY.npz
    (FOLDER: the lab's dataset cache)."""
    return Path(folder or cache_dir()) / "world_models" / f"{data.task}_{cache_key(cfg, data)}.npz"


def save(path: Path, tree) -> Path:
    """Every leaf of `tree` (arrays), in order, to an .npz written atomically."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    leaves = jax.tree.leaves(jax.device_get(tree))
    tmp = path.with_suffix(".tmp.npz")
    np.savez(tmp, **{f"leaf_{i}": np.asarray(x) for i, x in enumerate(leaves)})
    tmp.replace(path)
    return path


def load(path: Path, like):
    """The tree saved at `path`, shaped as `like` (a tree of arrays or ShapeDtypeStructs);
    None when the file is missing or its leaves do not match `like`'s shapes and dtypes."""
    path = Path(path)
    if not path.exists():
        return None
    leaves, treedef = jax.tree.flatten(like)
    with np.load(path) as stored:
        arrays = [stored[f"leaf_{i}"] for i in range(len(stored.files))]
    if len(arrays) != len(leaves) or any(
            a.shape != tuple(x.shape) or a.dtype != x.dtype for a, x in zip(arrays, leaves)):
        return None
    return jax.tree.unflatten(treedef, [jax.numpy.asarray(a) for a in arrays])
