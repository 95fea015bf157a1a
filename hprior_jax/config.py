"""Frozen run configuration. Validation raises with a message that names the fix.

`RunConfig` holds what every run has (task, seeds, budget, cadence, SAC, replay); each
method adds its own sections (PEBBLE's `pebble`, PRIOR's `prior`, ...). `config_class(algo)`
is RunConfig plus the sections of that method, so a run's config.json records only what the
run uses, and `--<section>.<field>` flags exist only for the method that reads them.
"""
from __future__ import annotations

import dataclasses
import functools
import json
import typing
from dataclasses import dataclass, field
from typing import Literal

from hprior_jax import envs
from hprior_jax.agents.sac import SACConfig
from hprior_jax.methods import registry

PRESETS = ("paper", "reduced", "smoke")
DEFAULT_PRESET = "paper"  # of `hprior train` and `hprior grid`: the appendix's budget
# fields every config.json has held since its first format (and RunConfig's own sections):
# read without one, a run would silently become another (a walker run restored as cheetah);
# later fields default to what runs before them did
REQUIRED = ("task", "algo", "preset", "seeds", "steps", "num_seed_steps", "eval_every",
            "num_eval_episodes", "checkpoint_every", "chunk_steps", "replay_capacity", "out")
# what a resumed run may change: the budget and the cadences (they decide when to evaluate
# and save, not what is learned); everything else would make a different run
CHANGEABLE_ON_RESUME = ("steps", "eval_every", "checkpoint_every", "num_eval_episodes",
                        "keep_checkpoints", "capture_video", "video_steps")
# config.json layout: 3 = button_press's `wrist: task` is the faithful wrist (it was the box),
# 2 = per-method sections (1 = every run had pebble and prior)
FORMAT = 3


@dataclass(frozen=True)
class RunConfig:
    """One training run: a task, a method, and seeds run vmapped in one process."""

    task: str = "cheetah_run"
    algo: str = registry.DEFAULT
    """The method (`hprior train --algo`): see `hprior methods`."""
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
    keep_checkpoints: int = 2
    """Checkpoints kept (the newest); 0 keeps every one (with --checkpoint-every equal to
    --eval-every, `hprior eval --step` then reaches every evaluation)."""
    capture_video: int = 0
    """Every how many evaluations each seed's first evaluation episode is also written as
    RUN/videos/step<N>_seed<S>.mp4 (its first `video_steps` env steps, at real time); 0:
    never. Rendering is counted in the evaluation's share of the progress bar."""
    video_steps: int = 250
    chunk_steps: int = 1000
    """Env steps per compiled chunk (one host round-trip per chunk)."""
    replay_capacity: int = 0
    """0 means `steps` (BPref: the buffer never wraps)."""
    out: str = ""
    """Run directory (default: runs/<task>_<algo>_<time>)."""
    contacts: Literal["floor", "all"] = "floor"
    """DM Control tasks: `floor` simulates only the body's contacts with the floor (C MuJoCo
    made no other contact in 20 episodes of random, bang-bang or trained actions; quadruped
    steps 2.9x faster, cheetah 2.2x), `all` also dm_control's self-collision pairs. Runs
    written before this option restore with `all`, the physics they were trained on."""
    contact_cap: Literal["task", "none"] = "task"
    """`task` gives MJX contact slots for the port's cap only (each port's `max_contacts`:
    cheetah and quadruped keep their 8 deepest contacts, above the 6 C MuJoCo held at once in
    60 episodes of random, bang-bang and held actions; five MetaWorld ports 8-72 per condim
    group, above what metaworld's scripted policy made active; walker and door_unlock have no
    cap): the same dynamics up to rounding while no more are active, and faster steps
    (cheetah 1.7x, quadruped 2.1x at batch 128; MetaWorld see benchmarks/README); `none` a
    slot for every candidate contact. Runs written before this option restore with `none`."""
    hand: Literal["arm", "free"] = "arm"
    """MetaWorld tasks: `arm` keeps metaworld's Sawyer arm (its joints, inertias and damping
    under the mocap weld; the scene that moves like metaworld's, see tasks/metaworld/sawyer.py),
    `free` the free-floating hand of the first ports. Runs written before this option restore
    with `free`, the scene they were trained on."""
    wrist: Literal["task", "box"] = "task"
    """MetaWorld tasks: `task` the port's registered wrist collider, the one with which the
    port moves like metaworld's; `box` the wrist's bounding box, a faster scene offered where
    the registered wrist is another (button_press: x1.30 of metaworld's return under its
    scripted policy against the registered wrist's x1.025, at 5.6x its env steps/s; see
    docs/ports/metaworld.md). Runs of button_press's arm scene written before format 3 with
    `task` trained on `box`."""
    compile_level: Literal["task", "xla", "0", "1", "2", "3"] = "task"
    """XLA's backend optimisation level for the run's programs: `task` the task's
    (`tasks.TaskInfo.compile_level`: 1 where it measured a sooner first env step at the same
    step speed, XLA's own elsewhere; a level in XLA_FLAGS wins), `xla` XLA's own (or
    XLA_FLAGS'), or a level. Levels round differently, so the same seed gives other episodes
    at another level. Runs written before this option restore with `xla`."""
    sac: SACConfig = field(default_factory=SACConfig)

    def __post_init__(self):
        if self.algo not in registry.names():
            raise ValueError(f"unknown algorithm {self.algo!r}; available: "
                             f"{', '.join(registry.names())}")
        if not self.seeds:
            raise ValueError("give at least one seed, e.g. --seeds 12345")
        if len(set(self.seeds)) != len(self.seeds):
            raise ValueError(f"--seeds has duplicates: {self.seeds}; give distinct seeds")
        for name in ("steps", "eval_every", "num_eval_episodes", "checkpoint_every",
                     "chunk_steps"):
            if getattr(self, name) <= 0:
                raise ValueError(f"--{name.replace('_', '-')} must be positive, "
                                 f"got {getattr(self, name)}")
        if self.capture_video < 0 or self.video_steps <= 0:
            raise ValueError("--capture-video must be >= 0 (0: no videos) and --video-steps "
                             "positive")
        if self.keep_checkpoints < 0:
            raise ValueError(f"--keep-checkpoints must be >= 0 (0 keeps all), got "
                             f"{self.keep_checkpoints}")
        if not 0 <= self.num_seed_steps <= self.steps:
            raise ValueError(f"--num-seed-steps ({self.num_seed_steps}) must be between 0 "
                             f"and --steps ({self.steps})")
        if self.contacts not in ("floor", "all"):
            raise ValueError(f"--contacts {self.contacts!r}: floor or all")
        if self.contact_cap not in ("task", "none"):
            raise ValueError(f"--contact-cap {self.contact_cap!r}: task or none")
        if self.hand not in ("arm", "free"):
            raise ValueError(f"--hand {self.hand!r}: arm or free")
        if self.wrist not in ("task", "box"):
            raise ValueError(f"--wrist {self.wrist!r}: task or box")
        if self.wrist == "box" and self.hand == "free":
            raise ValueError("--hand free has the box wrist already; --wrist box is an option "
                             "of the arm scene")
        if self.compile_level not in ("task", "xla", "0", "1", "2", "3"):
            raise ValueError(f"--compile-level {self.compile_level!r}: task, xla or 0-3")
        if self.replay_capacity < 0:
            raise ValueError("--replay-capacity must be >= 0 (0 means --steps)")
        if self.sac.batch_size > self.steps:
            raise ValueError(f"--sac.batch-size ({self.sac.batch_size}) exceeds --steps "
                             f"({self.steps}); lower the batch size or train longer")

    @property
    def capacity(self) -> int:
        return self.replay_capacity or self.steps

    def to_json(self) -> str:
        return json.dumps({"format": FORMAT, **dataclasses.asdict(self)}, indent=2)

    @staticmethod
    def from_dict(d: dict) -> "RunConfig":
        """The inverse of `to_json` (formats 2 and 3; `runs.config_file` reads format 1)."""
        d = _wrist_of_format_2(d)
        d = {k: v for k, v in d.items() if k != "format"}
        sections = [k for k, t in typing.get_type_hints(RunConfig).items()
                    if dataclasses.is_dataclass(t)]
        missing = [k for k in (*REQUIRED, *sections) if k not in d]
        if missing:
            raise ValueError(f"field(s) {', '.join(map(repr, missing))} missing (a run's own "
                             "settings have no default to fall back on)")
        # written before a physics option existed: the physics the run was trained on
        domain = envs.task_info(d["task"]).domain if "task" in d else None
        for name, option in envs.PHYSICS_OPTIONS.items():
            d.setdefault(name, option.before if domain in option.domains else option.default)
        d.setdefault("compile_level", "xla")  # what runs before the option compiled at
        return _dataclass_from_dict(config_class(d.get("algo", registry.DEFAULT)), d)


def _wrist_of_format_2(d: dict) -> dict:
    """Before format 3, button_press's registered arm scene had the box wrist and the
    faithful one was `wrist: faithful`: the same scenes under today's names."""
    if d.get("format", 1) >= 3:
        return d
    old = d.get("wrist", "task")
    if old == "faithful":
        return {**d, "wrist": "task"}
    if d.get("task") == "button_press" and d.get("hand") == "arm" and old == "task":
        return {**d, "wrist": "box"}
    return d


@functools.cache
def config_class(algo: str) -> type[RunConfig]:
    """RunConfig plus the configuration sections of method `algo` (one class per method)."""
    spec = registry.get(algo)
    if not spec.sections:
        return RunConfig
    fields = [(name, typ, field(default_factory=typ)) for name, typ in spec.sections.items()]
    cls = dataclasses.make_dataclass(f"RunConfig_{algo}", fields, bases=(RunConfig,),
                                     frozen=True)
    cls.__doc__ = f"{RunConfig.__doc__}\n\n{algo}: {', '.join(spec.sections) or 'no sections'}"
    return cls


def differing_fields(a: RunConfig, b: RunConfig) -> list[str]:
    """Dotted names of the fields (sections' included) whose values differ."""
    return _differing(dataclasses.asdict(a), dataclasses.asdict(b))


def field_value(cfg, dotted: str):
    """The value of dotted field name `dotted` (as `differing_fields` names it) in a config
    or its JSON form; a tuple reads as a list, so both forms print alike in a message."""
    for part in dotted.split("."):
        cfg = cfg.get(part) if isinstance(cfg, dict) else getattr(cfg, part)
    return list(cfg) if isinstance(cfg, tuple) else cfg


def _differing(a: dict, b: dict, prefix: str = "") -> list[str]:
    out = []
    for k in sorted(set(a) | set(b)):
        x, y = a.get(k), b.get(k)
        if isinstance(x, dict) and isinstance(y, dict):
            out += _differing(x, y, f"{prefix}{k}.")
        elif (list(x) if isinstance(x, (list, tuple)) else x) != (
                list(y) if isinstance(y, (list, tuple)) else y):
            out.append(prefix + k)
    return out


def _dataclass_from_dict(cls, d: dict, prefix: str = ""):
    """A (nested) frozen dataclass from its `dataclasses.asdict` form; a field of the wrong
    type or an unknown one raises a ValueError that names it (a hand-edited config.json)."""
    hints = typing.get_type_hints(cls)
    kwargs = {}
    for k, v in d.items():
        name = prefix + k
        if k not in hints:
            raise ValueError(f"unknown field {name!r}")
        if dataclasses.is_dataclass(hints[k]) and not isinstance(v, hints[k]):
            if not isinstance(v, dict):
                raise ValueError(f"field {name!r} is {json.dumps(v)}, expected an object of "
                                 "fields")
            v = _dataclass_from_dict(hints[k], v, f"{name}.")
        else:
            _check_type(name, v, hints[k])
        kwargs[k] = tuple(v) if isinstance(v, list) else v
    return cls(**kwargs)


_TYPE_NAMES = {bool: "true or false", int: "an integer", float: "a number", str: "a string"}


def _check_type(name: str, value, hint) -> None:
    if typing.get_origin(hint) is Literal:
        ok, expected = value in typing.get_args(hint), " or ".join(
            repr(a) for a in typing.get_args(hint))
    elif typing.get_origin(hint) is tuple:  # tuple[int, ...]: the seeds
        ok = isinstance(value, (list, tuple)) and all(
            isinstance(x, int) and not isinstance(x, bool) for x in value)
        expected = "a list of integers"
    elif hint in _TYPE_NAMES:
        kinds = (int, float) if hint is float else hint
        ok = isinstance(value, kinds) and (hint is bool or not isinstance(value, bool))
        expected = _TYPE_NAMES[hint]
    else:
        return
    if not ok:
        raise ValueError(f"field {name!r} is {json.dumps(value)}, expected {expected}")
