"""PEBBLE's run configuration (reference/pbrl_spec.md §2, appendix Table 3)."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from hprior_jax.pebble.teacher import TeacherConfig


@dataclass(frozen=True)
class PebbleConfig:
    num_unsup_steps: int = 9000
    """State-entropy pre-training steps after the seed steps (BPref scripts: 9000)."""
    num_interact: int = 20_000
    """Env steps between feedback rounds (appendix Table 3: 20k walker/cheetah, 30k quadruped,
    500 MetaWorld)."""
    max_feedback: int = 1000
    """Total queries shown to the teacher (`--feedback`)."""
    queries_per_round: int = 100
    """Queries per round (`--queries-per-round`); the last round is clipped to the budget."""
    segment_len: int = 50
    feed_type: Literal["uniform", "disagreement", "entropy"] = "disagreement"
    """Query selection after the first round (which is always uniform, as BPref).
    Disagreement is what SURF, RUNE, MRN and PRIOR's baselines run with."""
    large_batch: int = 10
    """Candidate pool = queries_per_round * large_batch for disagreement/entropy."""
    trajectory_episodes: int = 100
    """Queries come from the last N complete episodes (BPref `max_size`)."""
    reset_update: int = 100
    """SAC gradient steps right after the critic reset that ends pre-training."""
    knn_k: int = 5
    reward_lr: float = 3e-4
    reward_epochs: int = 50
    """Max epochs per round (BPref scripts: 50 DMC, 10 MetaWorld); early stop at 97% acc."""
    reward_batch: int = 128
    reward_hidden: int = 256
    reward_depth: int = 3
    ensemble_size: int = 3
    teacher: TeacherConfig = field(default_factory=TeacherConfig)
    bpref_entropy_mean_bug: bool = False
    """Reproduce BPref's running-mean bug in the state-entropy normaliser (utils.py#L240)."""

    def __post_init__(self):
        for name in ("num_interact", "max_feedback", "queries_per_round", "segment_len",
                     "large_batch", "trajectory_episodes", "knn_k", "reward_epochs",
                     "reward_batch", "reward_hidden", "ensemble_size"):
            if getattr(self, name) <= 0:
                raise ValueError(f"--pebble.{name.replace('_', '-')} must be positive, "
                                 f"got {getattr(self, name)}")
        if self.num_unsup_steps < 0 or self.reset_update < 0:
            raise ValueError("--pebble.num-unsup-steps and --pebble.reset-update must be >= 0")
        if self.queries_per_round > self.max_feedback:
            raise ValueError(f"--queries-per-round ({self.queries_per_round}) exceeds "
                             f"--feedback ({self.max_feedback}); lower it or raise the budget")

    @property
    def num_rounds(self) -> int:
        return -(-self.max_feedback // self.queries_per_round)
