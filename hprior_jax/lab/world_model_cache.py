"""Where the lab keeps its seeds' trained world models, so that another lab of the same
dataset, seeds and world-model settings (a λ sweep, PRIOR's ablations, another label budget
or query rule) loads them instead of training them again: on cheetah_run the world model is
about half of a 10-seed lab's time.

A world model is a deterministic function of what the cache key names: the dataset's
training episodes, the seeds, the world-model config, its training schedule (pre-training
steps, dynamics steps, order), whether its observations are standardised, the credit
settings of the positional profile, the code that trains and reads it (its source files'
bytes, `lab/seed_world_model.py` included; not this module's, which only stores the result)
and the jax version. Anything else that changed it would be a bug in this list;
`--no-world-model-cache` trains afresh.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
from pathlib import Path

import jax
import numpy as np

from hprior_jax.lab.dataset import Dataset, cache_dir
from hprior_jax.lab.npz_files import tree_of, write_atomically

# the modules whose code decides the trained world model and the profile read from it
_CODE = ("prior/world_model.py", "prior/attention.py", "networks/transformer_xl.py",
         "lab/seed_world_model.py")


def _code_digest() -> str:
    root = Path(__file__).resolve().parent.parent
    h = hashlib.sha256()
    for name in _CODE:
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
    leaves = jax.tree.leaves(jax.device_get(tree))
    return write_atomically(path, {f"leaf_{i}": np.asarray(x) for i, x in enumerate(leaves)})


def load(path: Path, like):
    """The tree saved at `path`, shaped as `like` (a tree of arrays or ShapeDtypeStructs);
    None when the file is missing or its leaves do not match `like`'s shapes and dtypes."""
    path = Path(path)
    if not path.exists():
        return None
    with np.load(path) as stored:
        return tree_of(like, [stored[f"leaf_{i}"] for i in range(len(stored.files))])
