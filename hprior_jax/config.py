"""Frozen run configuration. Validation raises with a message that names the fix."""
from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from typing import Literal

from hprior_jax.agents.sac import SACConfig
from hprior_jax.pebble.config import PebbleConfig
from hprior_jax.pebble.teacher import TeacherConfig
from hprior_jax.prior.config import PriorRunConfig

ALGORITHMS = ("sac", "pebble", "prior")  # grows with the PbRL baselines (surf, rune, ...)
PRESETS = ("paper", "reduced", "smoke")


@dataclass(frozen=True)
class TrainConfig:
    """One training run: a task, an algorithm, and seeds run vmapped in one process."""

    task: str = "cheetah_run"
    algo: str = "sac"
    preset: Literal["paper", "reduced", "smoke"] = "paper"
    """Budget and network sizes: `paper` (appendix Table 2), `reduced` (smaller nets and
    steps for a 2-core CPU) or `smoke` (a few minutes: the README's first run)."""
    seeds: tuple[int, ...] = (12345,)
    steps: int = 500_000
    """Total environment steps per seed."""
    num_seed_steps: int = 5000
    """Uniform-random actions before learning starts (BPref train_SAC: 5000)."""
    eval_every: int = 10_000
    num_eval_episodes: int = 10
    checkpoint_every: int = 50_000
    chunk_steps: int = 1000
    """Env steps per compiled chunk (one host round-trip per chunk)."""
    replay_capacity: int = 0
    """0 means `steps` (BPref: the buffer never wraps)."""
    out: str = ""
    """Run directory (default: runs/<task>_<algo>_<time>)."""
    sac: SACConfig = field(default_factory=SACConfig)
    pebble: PebbleConfig = field(default_factory=PebbleConfig)
    """Preference learning (used by --algo pebble and the methods built on it)."""
    prior: PriorRunConfig = field(default_factory=PriorRunConfig)
    """Hindsight PRIOR's world model and prior loss (used by --algo prior)."""

    def __post_init__(self):
        if self.algo not in ALGORITHMS:
            raise ValueError(
                f"unknown algorithm {self.algo!r}; available: {', '.join(ALGORITHMS)}")
        if not self.seeds:
            raise ValueError("give at least one seed, e.g. --seeds 12345")
        if len(set(self.seeds)) != len(self.seeds):
            raise ValueError(f"--seeds has duplicates: {self.seeds}; give distinct seeds")
        for name in ("steps", "eval_every", "num_eval_episodes", "checkpoint_every",
                     "chunk_steps"):
            if getattr(self, name) <= 0:
                raise ValueError(f"--{name.replace('_', '-')} must be positive, "
                                 f"got {getattr(self, name)}")
        if not 0 <= self.num_seed_steps <= self.steps:
            raise ValueError(f"--num-seed-steps ({self.num_seed_steps}) must be between 0 "
                             f"and --steps ({self.steps})")
        if self.replay_capacity < 0:
            raise ValueError("--replay-capacity must be >= 0 (0 means --steps)")
        if self.sac.batch_size > self.steps:
            raise ValueError(f"--sac.batch-size ({self.sac.batch_size}) exceeds --steps "
                             f"({self.steps}); lower the batch size or train longer")

    @property
    def capacity(self) -> int:
        return self.replay_capacity or self.steps

    def to_json(self) -> str:
        return json.dumps(dataclasses.asdict(self), indent=2)

    @staticmethod
    def from_dict(d: dict) -> "TrainConfig":
        d = dict(d)
        d["sac"] = SACConfig(**d["sac"])
        pebble = dict(d.get("pebble", {}))
        pebble["teacher"] = TeacherConfig(**pebble.get("teacher", {}))
        d["pebble"] = PebbleConfig(**pebble)
        d["prior"] = PriorRunConfig(**d.get("prior", {}))
        d["seeds"] = tuple(d["seeds"])
        return TrainConfig(**d)
