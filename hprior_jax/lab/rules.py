"""The lab's rule table: every rule `hprior reward-lab --rules` knows and the credit α it
trains with (`lab.config.CREDITS`, or `OWN_PROGRAM`). The methods know nothing of the lab:
this table says which registered methods are lab rules, and builds the rule of a method whose
update runs in a program of its own."""
from __future__ import annotations

import importlib

from hprior_jax.methods import registry

REFERENCE = "pebble"  # the rule every other one is compared with
OWN_PROGRAM = "own_program"  # the credit of a rule that runs in a program of its own

# {method: its credit α}: the registered methods that learn a reward from preferences. Not
# rules: sac learns no reward; rune learns PEBBLE's reward and changes only the agent's; mrn's
# meta step needs the agent's critic.
METHODS = {"pebble": "none", "prior": "attention", "prior_nrp": "attention_nrp",
           "rvar": "uniform", "surf": OWN_PROGRAM, "bisim": "bisimulation"}
# {method: the lab module whose `rule(RunConfig)` builds its rule} of the OWN_PROGRAM
# methods, imported on first use as the registry's methods are (the table, and the report that
# reads REFERENCE, need no jax). A rule is a hashable object with `init(key, capacity,
# obs_size, act_size, lab_cfg) -> cell` (a pytree whose `reward` field is the ensemble's
# parameters) and `round(cell, num_queries, first, train, mean_return, *, lab, queries, feed,
# episode_length) -> (cell, metrics)`; lab.learn vmaps or maps it over seeds.
OWN_PROGRAMS = {"surf": "surf_round"}
CONTROLS = {"positional": "positional", "oracle": "oracle"}  # lab rules that are no method
# lab rules asked for by name, no method (yet): credit learned from the labels instead of from
# dynamics (lab.credit_models), each with its positional control
LEARNED = {name: name for name in ("state_importance", "state_importance_positional",
                                   "pref_attention", "pref_attention_positional")}
# lab rules asked for by name: (credit, targets clipped, prior also on unlabelled segments).
# The prior_* ones are `--algo prior` with a flag; the other two are prior_unlabelled's
# controls, the same unlabelled segments under uniform credit (`--algo rvar
# --rvar.unlabelled-segments N`) or positional credit (no method).
ABLATIONS = {"prior_no_own_step": ("attention_no_own_step", False, False),  # exclude-own-step
             "prior_clipped": ("attention", True, False),  # --prior.clip-targets
             "prior_unlabelled": ("attention", False, True),  # --prior.unlabelled-segments N
             "rvar_unlabelled": ("uniform", False, True),  # --rvar.unlabelled-segments N
             "positional_unlabelled": ("positional", False, True)}


def rules() -> dict[str, str]:
    """{rule: credit}: the methods that are lab rules, in the registry's order, then the
    lab's controls, then PRIOR's ablations, then the learned credits."""
    methods = {n: METHODS[n] for n in registry.names() if n in METHODS}
    return {**methods, **CONTROLS, **{n: credit for n, (credit, *_) in ABLATIONS.items()},
            **LEARNED}


def default_rules() -> list[str]:
    """The default sweep: every rule but the ablations and the learned credits."""
    return [r for r in rules() if r not in ABLATIONS and r not in LEARNED]


def own_rule(name: str, rl):
    """The rule object of the OWN_PROGRAM method `name` at the settings of `rl`, its
    RunConfig at the lab's preset."""
    return importlib.import_module(f"hprior_jax.lab.{OWN_PROGRAMS[name]}").rule(rl)
