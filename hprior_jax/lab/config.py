"""The lab's configuration and the data types its programs take. A rule's credit α:

  none           PEBBLE: cross-entropy only (λ = 0)
  attention      PRIOR: the world model's attention credit (the RL loop's α)
  attention_nrp  PRIOR-NRP: the same α min-max normalised and softmaxed (appendix eq. 9)
  attention_no_own_step  ablation: attention α without the query's own (last) step
  bisimulation   BISIM: no α (λ = 0); its bisimulation term instead (weight `bisim_lam`), on
                 transitions drawn from the training episodes, as the RL loop draws them from
                 the replay buffer
  uniform        RVAR: 1/|σ|
  positional     control: the mean attention α at each position, the same for every segment
                 (what is left of α without state information)
  oracle         control: each step's share of the segment's true return, r_t / Σ r (an upper
                 bound for any credit rule; the only rule that reads true rewards)
  state_importance, pref_attention
                 α of a credit model trained on the cell's labels each round (state
                 importance's |w|, Preference Transformer's attention: `lab.credit_models`),
                 recomputed for every stored pair each round (`lab.learned_credit`)
  state_importance_positional, pref_attention_positional
                 control: that model's mean α at each position, the same for every segment

A rule may also take the shifted target form α_t·(R̂ + T·c) − c (`shifts`, RULE~shift), clip
its targets, fit the prior on unlabelled segments too and have its own λ: ablations and a λ
sweep run side by side as rules of one program. A method whose update has other shapes (SURF)
runs in a program of its own (`OWN_PROGRAM`), same seeds. Which rules exist and which credit
each has: the rule table, `lab.rules`.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import jax
import numpy as np
from flax import struct

from hprior_jax.lab.credit_models import KINDS as CREDIT_MODELS
from hprior_jax.lab.credit_models import CreditModelConfig
from hprior_jax.lab.rules import OWN_PROGRAM
from hprior_jax.networks.reward_ensemble import RewardConfig
from hprior_jax.pbrl.preference import PreferenceConfig
from hprior_jax.pbrl.teacher import TeacherConfig
from hprior_jax.prior import world_model as wm

CREDITS = ("none", "attention", "attention_nrp", "uniform", "positional", "oracle",
           "attention_no_own_step", "bisimulation", "state_importance",
           "state_importance_positional", "pref_attention", "pref_attention_positional")
# {credit: (its credit model, whether it is the model's positional control)}
LEARNED_CREDITS = {"state_importance": ("state_importance", False),
                   "state_importance_positional": ("state_importance", True),
                   "pref_attention": ("pref_attention", False),
                   "pref_attention_positional": ("pref_attention", True)}
WORLD_MODEL_CREDITS = ("attention", "attention_nrp", "attention_no_own_step", "positional")
NO_PRIOR = ("none", "bisimulation")  # credits whose rule trains no prior term (λ = 0)
BISIM_STREAM = 0xB151  # folded off a round's key: the transitions leave the other draws alone
UNLABELLED_SEGMENTS = 64  # the prior_unlabelled rule's N unless --prior-set sets it


@dataclass(frozen=True)
class LabConfig:
    rules: tuple[str, ...]  # rule names, in report order
    credits: tuple[str, ...]  # the credit of each rule (CREDITS)
    lam: float  # λ of every rule with a credit (the RL presets': 5 DMC, 1000 MetaWorld)
    clips: tuple[bool, ...] = ()  # per rule: targets clipped to [-1, 1] (empty: none)
    shifts: tuple[bool, ...] = ()  # per rule: the shifted target form (empty: all raw)
    unlabelled: tuple[bool, ...] = ()  # per rule: the prior also on unlabelled segments
    unlabelled_segments: int = UNLABELLED_SEGMENTS  # drawn afresh each round (prior.unlabelled)
    rule_lams: tuple[float | None, ...] = ()  # per rule: its own λ instead of `lam` (None: lam)
    bisim_lam: float = 0.5  # λ_bisim of the bisim rule (BISIM's default)
    bisim_transitions: int = 4  # transitions per stored-pair row (BISIM's default)
    discount: float = 0.99  # γ of the bisimulation target (SAC's, as in BISIM)
    own_rules: tuple = ()  # (rule, lab.rules.own_rule's object) of every OWN_PROGRAM rule
    budgets: tuple[int, ...] = (25, 100, 400)
    queries_per_round: int = 10
    feed_type: str = "disagreement"
    large_batch: int = 10
    one_shot: bool = False
    """Train once on all of a budget's labels (uniform queries) instead of round by round."""
    seeds: tuple[int, ...] = tuple(range(20))
    reward: RewardConfig = field(default_factory=RewardConfig)
    preference: PreferenceConfig = field(default_factory=PreferenceConfig)
    teacher: TeacherConfig = field(default_factory=TeacherConfig)
    world_model: wm.WorldModelConfig | None = None
    wm_pretrain_steps: int = 300
    wm_steps: int = 600  # dynamics-only steps after the pre-training
    wm_order: str = "joint"  # the pre-training's order (wm.pretrain)
    wm_normalize_obs: bool = False  # standardised world-model inputs (an ablation)
    attention_query: str = "action"
    profile_segments: int = 256  # training segments the positional profile averages
    credit_model: CreditModelConfig = field(default_factory=CreditModelConfig)

    def __post_init__(self):
        if len(self.rules) != len(self.credits) or not self.rules:
            raise ValueError("give one credit per rule")
        own = [r for r, c in zip(self.rules, self.credits) if c == OWN_PROGRAM]
        if own != [r for r, _ in self.own_rules]:
            raise ValueError(f"give the lab rule object of every own-program rule {own}")
        for name in ("clips", "shifts", "rule_lams", "unlabelled"):
            if len(getattr(self, name)) not in (0, len(self.rules)):
                raise ValueError(f"give one of {name} per rule, or none")
        bad = set(self.credits) - set(CREDITS) - {OWN_PROGRAM}
        if bad:
            raise ValueError(f"unknown credit {sorted(bad)}; available: {', '.join(CREDITS)}")
        check_budgets(self.budgets)
        if not self.seeds:
            raise ValueError("give at least one seed")
        if self.needs_world_model and self.world_model is None:
            raise ValueError("a rule with attention or positional credit needs a world model")
        if self.needs_bisim and not self.reward.next_embedding_head:
            raise ValueError("the bisim rule needs RewardConfig(next_embedding_head=True)")

    @property
    def shared_rules(self) -> list[int]:
        """Indices of the rules that share the main program (all but OWN_PROGRAM ones)."""
        return [i for i, c in enumerate(self.credits) if c != OWN_PROGRAM]

    @property
    def needs_bisim(self) -> bool:
        return "bisimulation" in self.credits

    @property
    def needs_unlabelled(self) -> bool:
        return any(self.unlabelled)

    @property
    def learned_kinds(self) -> tuple[str, ...]:
        """The credit models the lab's rules learn (every cell trains them: rules are
        vmapped, so a cell cannot skip what another computes)."""
        kinds = {LEARNED_CREDITS[c][0] for c in self.credits if c in LEARNED_CREDITS}
        return tuple(k for k in CREDIT_MODELS if k in kinds)

    @property
    def needs_world_model(self) -> bool:
        return bool(set(WORLD_MODEL_CREDITS) & set(self.credits))

    def rounds(self) -> list[tuple[int, int | None]]:
        """(queries, budget reached after it or None) of every round, round by round."""
        out, labels = [], 0
        for budget in self.budgets:
            while labels < budget:
                n = min(self.queries_per_round, budget - labels)
                labels += n
                out.append((n, budget if labels == budget else None))
        return out


def check_budgets(budgets) -> None:
    if not budgets or list(budgets) != sorted(set(budgets)) or budgets[0] < 1:
        raise ValueError(f"budgets must be increasing positive label counts, got "
                         f"{list(budgets)}")


@struct.dataclass
class GivenLabels:
    """Labels given beforehand instead of the teacher's (a person's: `hprior label
    --from-lab`): pairs of the training episodes at `pair_index` [N, 4] (episode, start of
    each segment), B-Pref labels [N] (0 first, 1 second, -1 equal) and `valid` [N] (False:
    can't tell). Every cell trains once on all of them (one-shot)."""

    pair_index: np.ndarray
    labels: np.ndarray
    valid: np.ndarray

    def __len__(self) -> int:
        return len(self.labels)


@struct.dataclass
class RuleArgs:
    """What tells one rule from another inside the program (arrays, vmapped over rules):
    its credit (an index into CREDITS), λ of the prior term, whether its targets are clipped,
    their form's shift c (prior.loss.prior_targets: 0 raw), the weight of the bisimulation
    term and whether its prior also fits unlabelled segments."""

    credit: jax.Array
    lam: jax.Array
    clip: jax.Array
    shift: jax.Array
    bisim_lam: jax.Array
    unlabelled: jax.Array


@struct.dataclass
class Episodes:
    """obs[E, L, ds], act[E, L, da], reward[E, L] (true rewards: the teacher's and the
    oracle credit's only)."""

    obs: jax.Array
    act: jax.Array
    reward: jax.Array
