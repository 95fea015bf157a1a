"""The reward-learning lab's fixed data: episodes of mixed quality with their true rewards.

`build(task, seed)` trains SAC on the true reward for `steps` steps (one seed, the project's
own loop and preset) and keeps its whole replay buffer as episodes: uniform-random episodes
first, then a policy that improves episode by episode, which is the kind of data PbRL's
queries are drawn from in the RL loop. Every `heldout_every`-th episode is held out, so both
sets span the whole learning curve. From the held-out episodes it draws fixed segment pairs
labelled by the oracle (pairs with equal true returns are not kept: they have no answer).
Deterministic from (task, seed, steps, preset) and the code that builds it on one machine:
the cache file's name says all five (`build_code_digest`).
Another machine may build other episodes (window_open's did: its float rounding differs and
SAC amplifies it), so a lab run on several machines shares the file (`reward-lab --dataset`).
Built with `physics=True`, it also keeps the physics state of every training step (a person can then
label clips of its segments: `hprior label --from-lab`), under a name of its own.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import jax
import numpy as np

from hprior_jax import presets
from hprior_jax.buffers.episodes import split_column
from hprior_jax.envs import task_info
from hprior_jax.lab import rules
from hprior_jax.lab.npz_files import write_atomically
from hprior_jax.methods import registry
from hprior_jax.runs.build import build_engine, train
from hprior_jax.runs.restore import restore_run
from hprior_jax.runs.run_dir import load_run_config

DEFAULT_STEPS = 50_000  # the reduced RL run's length: PbRL there sees a buffer like this one
HELDOUT_PAIRS = 2000


@dataclass(frozen=True)
class Dataset:
    """obs[E, L, ds], act[E, L, da], reward[E, L] for the training and held-out episodes;
    held-out pairs as (episode, start) of each segment and the oracle label (1 = second
    preferred)."""

    task: str
    segment_len: int
    train_obs: np.ndarray
    train_act: np.ndarray
    train_reward: np.ndarray
    test_obs: np.ndarray
    test_act: np.ndarray
    test_reward: np.ndarray
    pair_index: np.ndarray  # [P, 4] int: episode 1, start 1, episode 2, start 2
    pair_label: np.ndarray  # [P] int32
    info: dict  # how it was made: seed, steps, preset, build seconds, returns
    train_physics: dict | None = None  # {field: [E, L, ...]} the state behind train_obs

    @property
    def episode_length(self) -> int:
        return self.train_reward.shape[1]

    def digest(self) -> str:
        """Names the data the lab learns from and is scored on (the episodes and held-out
        pairs, not how they were made): labs to be merged (seed shards, often built on other
        machines) must share it."""
        h = hashlib.sha256()
        for name in ("train_obs", "train_act", "train_reward", "test_obs", "test_act",
                     "test_reward", "pair_index", "pair_label"):
            h.update(np.ascontiguousarray(getattr(self, name)).tobytes())
        return h.hexdigest()[:20]

    def save(self, path: Path) -> Path:
        arrays = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)
                  if isinstance(getattr(self, f.name), np.ndarray)}
        arrays |= {f"{PHYSICS}{k}": v for k, v in (self.train_physics or {}).items()}
        meta = dict(task=self.task, segment_len=self.segment_len, info=self.info)
        return write_atomically(path, dict(meta=np.asarray(json.dumps(meta)), **arrays),
                                compressed=True)

    @staticmethod
    def load(path: Path) -> "Dataset":
        with np.load(path) as z:
            meta = json.loads(str(z["meta"]))
            arrays = {k: z[k] for k in z.files if k != "meta" and not k.startswith(PHYSICS)}
            physics = {k[len(PHYSICS):]: z[k] for k in z.files if k.startswith(PHYSICS)}
        return Dataset(task=meta["task"], segment_len=meta["segment_len"], info=meta["info"],
                       train_physics=physics or None, **arrays)


def cache_dir() -> Path:
    """$HPRIOR_LAB_CACHE, else ~/.cache/hprior_jax/lab (datasets are not kept in git)."""
    return Path(os.environ.get("HPRIOR_LAB_CACHE", Path.home() / ".cache/hprior_jax/lab"))


PHYSICS = "train_physics."  # the saved name of a physics field of the training episodes


# What a dataset build executes besides the lab's own modules: the SAC run (tasks, loop,
# agent, buffers, networks, presets) and this module's split into episodes and pairs. A change
# to any of it can give other episodes, so the cache key names its bytes.
_NOT_BUILD_CODE = ("lab", "experiments", "commands", "labelling")


def build_code_digest() -> str:
    """Hex digest of the source files a dataset build runs and of jax's, jaxlib's and
    mujoco's versions (conservative: a file the build does not run may be in it too)."""
    package = Path(__file__).resolve().parent.parent
    files = sorted(p for p in package.rglob("*.py")
                   if p.relative_to(package).parts[0] not in _NOT_BUILD_CODE)
    files += sorted((package.parent / "tasks").rglob("*.py")) + [Path(__file__).resolve()]
    h = hashlib.sha256()
    for path in files:
        h.update(path.read_bytes())
    from importlib import metadata

    h.update(" ".join(metadata.version(n) for n in ("jax", "jaxlib", "mujoco")).encode())
    return h.hexdigest()[:8]


def dataset_path(task: str, seed: int, steps: int, preset: str, physics: bool = False) -> Path:
    """The cache file of a build: named by what decides its episodes (task, seed, steps,
    preset, physics recorded or not, the build's code)."""
    return cache_dir() / (f"{task}_sac-{preset}_{steps}steps_seed{seed}"
                          + ("_physics" if physics else "") + f"_code{build_code_digest()}.npz")


def split_episodes(obs, act, reward, episode_length: int, heldout_every: int = 3):
    """Replay rows (one env, never wrapped) -> (train, held-out) episode arrays; episode e
    is held out when e % heldout_every == heldout_every - 1."""
    return [split_column(x, episode_length, heldout_every) for x in (obs, act, reward)]


def heldout_pairs(reward: np.ndarray, segment_len: int, num_pairs: int,
                  rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """`num_pairs` random segment pairs of the held-out episodes with distinct true returns,
    and their oracle labels (1 when the second segment's true return is higher)."""
    e, length = reward.shape
    cum = np.concatenate([np.zeros((e, 1)), np.cumsum(reward, axis=1, dtype=np.float64)], 1)
    seg_return = lambda ep, st: cum[ep, st + segment_len] - cum[ep, st]
    index, labels, found = [], [], 0
    for _ in range(100):
        cand = random_pairs(rng, e, length, segment_len, num_pairs)
        r1, r2 = seg_return(cand[:, 0], cand[:, 1]), seg_return(cand[:, 2], cand[:, 3])
        keep = r1 != r2
        index.append(cand[keep])
        labels.append((r2 > r1)[keep].astype(np.int32))
        found += int(keep.sum())
        if found >= num_pairs:
            return np.concatenate(index)[:num_pairs], np.concatenate(labels)[:num_pairs]
    raise ValueError(f"found only {found} held-out pairs with distinct true returns")


def random_pairs(rng: np.random.Generator, episodes: int, length: int, segment_len: int,
                 num_pairs: int) -> np.ndarray:
    """int[num_pairs, 4]: (episode, start) of segment 1, then of segment 2, each drawn
    uniformly and independently (every start whose segment fits in the episode)."""
    starts = lambda: rng.integers(0, length - segment_len + 1, num_pairs)
    return np.stack([rng.integers(0, episodes, num_pairs), starts(),
                     rng.integers(0, episodes, num_pairs), starts()], 1)


def build(task: str, seed: int = 0, steps: int = DEFAULT_STEPS, preset: str = "reduced",
          heldout_every: int = 3, num_pairs: int = HELDOUT_PAIRS,
          progress: bool = True, physics: bool = False) -> Dataset:
    """Trains SAC on the true reward (the `preset`'s networks, one seed) and turns its replay
    buffer into a Dataset with the preset's query segment length. Takes minutes: one SAC run
    of `steps` steps. `physics`: keep the training steps' physics states too (the same
    run: recording them changes no number)."""
    length = task_info(task).episode_length
    _check_steps(steps, length, heldout_every)  # before the SAC run
    t0 = time.perf_counter()
    cfg = presets.train_preset(task, registry.REFERENCE, preset, steps=steps, seeds=(seed,),
                               eval_every=steps, checkpoint_every=steps)
    with tempfile.TemporaryDirectory() as tmp:
        cfg = dataclasses.replace(cfg, out=tmp)
        rs = train(cfg, Path(tmp), progress=progress,
                      engine=build_engine(cfg, records_physics=physics))
    replay = jax.tree.map(lambda x: np.asarray(x)[0], rs.replay)
    return _from_replay(task, replay, steps, seed, preset, f"SAC ({preset}) replay buffer",
                        t0, heldout_every, num_pairs)


def from_run(run_dir: Path, seed: int | None = None, heldout_every: int = 3,
             num_pairs: int = HELDOUT_PAIRS) -> Dataset:
    """The Dataset of an existing `hprior train --algo sac` run: its latest checkpoint's
    replay buffer (one seed, default the run's first), as `build` would keep it. Saves the
    SAC run that `build` would repeat; the file it is saved under names the run's seed,
    checkpoint step and preset."""
    t0 = time.perf_counter()
    algo = load_run_config(Path(run_dir)).algo
    if algo != registry.REFERENCE:  # checked before the checkpoint is read
        raise ValueError(f"{run_dir} is a --algo {algo} run; the lab's data comes from "
                         f"{registry.REFERENCE} on the true reward")
    restored = restore_run(Path(run_dir))
    cfg = restored.cfg
    seed = cfg.seeds[restored.seed_index(seed)]
    replay = jax.tree.map(np.asarray, restored.of_seed(seed).replay)
    return _from_replay(cfg.task, replay, restored.step, seed, cfg.preset,
                        f"SAC ({cfg.preset}) replay buffer of {run_dir}", t0, heldout_every,
                        num_pairs)


def _check_steps(steps: int, length: int, heldout_every: int) -> None:
    if steps % length or steps // length < 2 * heldout_every:
        raise ValueError(f"the dataset's steps ({steps}) must be a multiple of the episode "
                         f"length ({length}) and hold at least {2 * heldout_every} episodes")


def _from_replay(task: str, replay, steps: int, seed: int, preset: str, source: str,
                 t0: float, heldout_every: int, num_pairs: int) -> Dataset:
    """One seed's replay buffer (rows in step order, never wrapped) -> Dataset."""
    length = task_info(task).episode_length
    segment_len = presets.train_preset(task, rules.REFERENCE, preset).pebble.segment_len
    _check_steps(steps, length, heldout_every)
    rows = lambda x: np.asarray(x)[:steps]
    (tr_o, te_o), (tr_a, te_a), (tr_r, te_r) = split_episodes(
        rows(replay.obs), rows(replay.action), rows(replay.true_reward), length, heldout_every)
    physics = None
    if replay.physics is not None:
        physics = {k: split_column(rows(v), length, heldout_every)[0]
                   for k, v in replay.physics.items()}
    index, labels = heldout_pairs(te_r, segment_len, num_pairs, np.random.default_rng(seed))
    returns = np.concatenate([tr_r, te_r]).sum(1)
    info = dict(seed=seed, steps=steps, preset=preset, source=source,
                build_seconds=round(time.perf_counter() - t0, 1),
                train_episodes=int(tr_r.shape[0]), test_episodes=int(te_r.shape[0]),
                episode_return_min=float(returns.min()), episode_return_max=float(returns.max()),
                episode_return_median=float(np.median(returns)))
    return Dataset(task=task, segment_len=segment_len, train_obs=tr_o, train_act=tr_a,
                   train_reward=tr_r, test_obs=te_o, test_act=te_a, test_reward=te_r,
                   pair_index=index, pair_label=labels, info=info, train_physics=physics)


def load_or_build(task: str, seed: int = 0, steps: int = DEFAULT_STEPS, preset: str = "reduced",
                  progress: bool = True, physics: bool = False) -> tuple[Dataset, Path]:
    path = dataset_path(task, seed, steps, preset, physics)
    if path.exists():
        return Dataset.load(path), path
    data = build(task, seed, steps, preset, progress=progress, physics=physics)
    return data, data.save(path)
