"""What a PEBBLE-family method is made of besides PEBBLE's round: its configuration and
preset (appendix Table 3), its state, the episodes its queries come from, and the hooks an
`Extension` fills in (PRIOR, RVAR, RUNE, BISIM; SURF and MRN subclass `Pebble` instead)."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, Literal, NamedTuple

import jax
import optax
from flax import struct

from hprior_jax import task_table
from hprior_jax.agents.sac import SACConfig
from hprior_jax.buffers import preferences
from hprior_jax.envs import task_info
from hprior_jax.loop.state import RunState
from hprior_jax.networks.reward_ensemble import RewardConfig
from hprior_jax.pbrl.preference import RewardTerm
from hprior_jax.pbrl.state_entropy import RunningMeanStd
from hprior_jax.pbrl.teacher import TeacherConfig


@dataclass(frozen=True)
class PebbleConfig:
    """Preference learning: schedule, label budget, query selection, reward model, teacher."""

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


@struct.dataclass
class PebbleState:
    reward: dict  # stacked ensemble params, leading axis K
    reward_opt: optax.OptState
    prefs: preferences.PreferenceStore
    entropy_stats: RunningMeanStd
    ext: Any = None  # the state of an `Extension` (PRIOR: world model, credit, λ)


class EpisodeWindow(NamedTuple):
    """The episodes queries are drawn from: obs[N, L, ds], act[N, L, da], true_reward[N, L]
    (teacher only), and `count` valid rows (rows 0..count-1); `physics` {field: [N, L, ...]}
    where the replay buffer records it (a person's clips)."""

    obs: jax.Array
    act: jax.Array
    true_reward: jax.Array
    count: jax.Array
    physics: dict | None = None


class Extension:
    """What a method built on PEBBLE adds to it (PRIOR, RVAR, RUNE, BISIM): its own state
    (`ms.ext`), its own host-side events, reward terms beside the preference cross-entropy
    (with the run state at hand: replay buffer, SAC, keys), the reward the agent trains on
    after pre-training, and the reward ensemble's architecture. The default adds nothing:
    PEBBLE itself. (A method that changes the round itself subclasses `Pebble`: SURF, MRN.)"""

    def init(self, key: jax.Array):
        return None

    def event_steps(self) -> list[int]:
        return []

    def run_event(self, rs: RunState, step: int) -> tuple[RunState, dict]:
        raise NotImplementedError

    def programs(self, rs: RunState) -> list:
        """The programs of its events, to compile ahead (`Method.programs`)."""
        return []

    def reward_terms(self, rs: RunState, ms: PebbleState
                     ) -> tuple[tuple[RewardTerm, ...], PebbleState]:
        """The terms of this round's reward update (called inside the compiled round, before
        it; `ms` holds this round's labels, `rs` the rest of the run); may update `ms.ext`
        (e.g. PRIOR's credit of the stored pairs)."""
        return (), ms

    agent_metrics: tuple[str, ...] = ()  # the `train/` metrics `agent_reward` returns

    def agent_reward(self, rs: RunState, batch, t: jax.Array):
        """The reward of a sampled batch in SAC's update after pre-training at global step
        `t`: (reward [B], rs, metrics). PEBBLE: the relabelled r̂ stored in the buffer."""
        return batch.reward, rs, {}

    def reward_config(self, base: RewardConfig) -> RewardConfig:
        """The reward ensemble's architecture (BISIM adds a next-embedding head)."""
        return base

    def round_metrics(self, ms: PebbleState, reward_cfg: RewardConfig) -> dict:
        """Scalar diagnostics after the round's reward update (inside the compiled round)."""
        return {}


def reward_config(p: PebbleConfig) -> RewardConfig:
    return RewardConfig(hidden_sizes=(p.reward_hidden,) * p.reward_depth,
                        ensemble_size=p.ensemble_size)


def pebble_preset(task: str, preset: str, sac: SACConfig) -> dict:
    """PEBBLE-family settings: BPref's schedule (1000 seed + 9000 unsupervised steps) and the
    appendix Table 3 budgets. Table 3 lists DMC budgets 1000/100 and 100/10 and four MetaWorld
    budgets (10000/50, 4000/20, 2000/25, 400/10) without saying which task used which; we
    default to the first of each (override with --feedback / --queries-per-round)."""
    info = task_info(task)
    dmc = info.domain == "dm_control"
    row = task_table.values(task)
    sac = dataclasses.replace(sac, lr=row.pbrl_sac_lr)
    if preset == "paper":
        pebble = PebbleConfig(
            num_interact=row.pbrl_interact,
            max_feedback=1000 if dmc else 10_000, queries_per_round=100 if dmc else 50,
            reward_epochs=50 if dmc else 10)
        return dict(num_seed_steps=1000, pebble=pebble, sac=sac)
    if preset == "reduced":
        # Table 3's small budgets (DMC 100 labels, 10 per round) spent by step 46k of 50k: a
        # round every 4000 steps instead of 20k; MetaWorld keeps 20 per round, 200 in all
        pebble = PebbleConfig(num_interact=4000, max_feedback=100 if dmc else 200,
                              queries_per_round=10 if dmc else 20,
                              reward_epochs=50 if dmc else 10)
        return dict(num_seed_steps=1000, pebble=pebble, sac=sac)
    # smoke: a round every 2 episodes after 1 random + 1 pre-training episode
    episode = info.episode_length
    pebble = PebbleConfig(num_unsup_steps=episode, num_interact=2 * episode, max_feedback=40,
                          queries_per_round=10, reward_epochs=10, reset_update=20,
                          segment_len=min(50, episode // 2))
    return dict(num_seed_steps=episode, pebble=pebble, sac=sac)
