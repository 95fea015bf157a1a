"""The only list of method names. Everything else (CLI choices, presets, grid, report columns,
run directories) asks this module.

A method is one module under `hprior_jax.methods` whose `spec(name)` returns its `MethodSpec`:
the configuration sections it reads, how to build its hooks, and its preset values. Adding a
method is that module, one line below, and its test.
"""
from __future__ import annotations

import importlib
from dataclasses import dataclass, field
from typing import Callable

# (name, module under hprior_jax.methods, one-line description), in the column order of the
# paper's tables (the reference first)
_METHODS = (
    ("sac", "sac", "SAC on the true reward: the reference every score is normalised by"),
    ("prior", "prior", "Hindsight PRIOR: PEBBLE + world-model attention credit as a reward prior"),
    ("pebble", "pebble", "PEBBLE: unsupervised pre-training, preference queries, relabelling"),
    ("prior_nrp", "prior", "PRIOR-NRP: PRIOR with min-max normalised, softmaxed credit (eq. 9)"),
    ("rvar", "rvar", "RVAR: PEBBLE + a prior of the return spread uniformly over the segment"),
    ("surf", "surf", "SURF: PEBBLE + pseudo-labelled unlabelled pairs and temporal cropping"),
    ("rune", "rune", "RUNE: PEBBLE + the reward ensemble's disagreement as a critic bonus"),
    ("mrn", "mrn", "MRN: PEBBLE + a bi-level meta step that fits the reward to the critic"),
    ("bisim", "bisim", "BISIM: PEBBLE + a bisimulation loss on the reward model's embedding"),
)
REFERENCE = "sac"  # the normaliser of Tables 6-7
PROPOSED = "prior"  # the method the paired t-tests compare every other one with
DEFAULT = "sac"  # `hprior train` without --algo
GRID_DEFAULT = ("sac", "pebble", "prior")  # `hprior grid` without --algos


@dataclass(frozen=True)
class MethodSpec:
    name: str
    build: Callable  # (cfg: RunConfig, kit) -> Method (hprior_jax.methods.base)
    sections: dict[str, type] = field(default_factory=dict)
    """Configuration sections the method reads, by name: `--<section>.<field>` on the CLI,
    `config.json["<section>"]` in a run directory. SAC has none."""
    preset: Callable = lambda task, preset, sac: {}
    """(task, preset name, the preset's SACConfig) -> RunConfig field overrides."""
    has_world_model: bool = False  # attention maps need one


def names() -> list[str]:
    return [name for name, _, _ in _METHODS]


def describe() -> str:
    width = max(len(n) for n in names())
    return "\n".join(f"  {name:<{width}}  {text}" for name, _, text in _METHODS)


def get(name: str) -> MethodSpec:
    for method, module, _ in _METHODS:
        if method == name:
            spec = importlib.import_module(f"hprior_jax.methods.{module}").spec(name)
            assert spec.name == name
            return spec
    raise ValueError(f"unknown algorithm {name!r}; available: {', '.join(names())}")


def table_order(methods) -> list[str]:
    """`methods` in the registry's order; unregistered names (old run directories) last."""
    known = names()
    return sorted(methods, key=lambda m: (known.index(m) if m in known else len(known), m))


def from_format_1(d: dict) -> dict:
    """A config.json of format 1 (every run carried the `pebble` and `prior` sections, and
    `--algo prior` chose PRIOR-NRP and RVAR by `prior.variant`) as today's dict."""
    d = dict(d)
    pebble, prior = d.pop("pebble", None), dict(d.pop("prior", None) or {})
    algo = d.get("algo", "sac")
    if algo == "sac":
        return d
    d["pebble"] = pebble
    if algo == "prior":
        algo = d["algo"] = {"prior": "prior", "nrp": "prior_nrp", "rvar": "rvar"}[
            prior.pop("variant", "prior")]
        if algo == "rvar":
            d["rvar"] = {"lam": prior["lam"]}
        else:
            d["prior"] = prior
    return d
