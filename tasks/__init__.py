"""MJX task ports and their registry.

    import tasks
    task = tasks.make("cheetah_run")
    state = task.reset(jax.random.key(0))
    state = task.step(state, action)

This package imports nothing from `hprior_jax`; `hprior_jax.envs` is its only client.
"""
from __future__ import annotations

from tasks import _xla_flags  # noqa: F401  (must run before jax is imported)

from typing import TYPE_CHECKING, Callable, NamedTuple

if TYPE_CHECKING:
    from tasks.base import Task

_REGISTRY: dict[str, Callable[..., Task]] = {}
_INFO: dict[str, "TaskInfo"] = {}
_CACHE: dict[tuple, Task] = {}


class TaskInfo(NamedTuple):
    """What presets and checks need to know of a task without building its model."""

    domain: str  # "dm_control" or "metaworld"
    episode_length: int
    has_success: bool
    # XLA's backend optimisation level a run of the task compiles at unless told otherwise
    # (`hprior train --compile-level`); None: XLA's own
    compile_level: int | None = None


def register(name: str, factory: Callable[[], Task], info: TaskInfo | None = None) -> None:
    """Adds a task factory under `name` (e.g. "walker_walk"). `info` may be left out when
    `factory` is a Task class (its class attributes are read)."""
    if name in _REGISTRY:
        raise ValueError(f"task {name!r} is already registered")
    if info is None:
        from tasks.base import Task

        if not (isinstance(factory, type) and issubclass(factory, Task)):
            raise ValueError(f"register {name!r} with its TaskInfo (domain, episode length)")
        info = TaskInfo(factory.domain, factory.episode_length, factory.has_success)
    _REGISTRY[name] = factory
    _INFO[name] = info


def info(name: str) -> TaskInfo:
    """Domain, episode length and success flag of `name`, without building it."""
    if name not in _INFO:
        raise ValueError(f"unknown task {name!r}; available tasks: {', '.join(names())}")
    return _INFO[name]


def names() -> list[str]:
    return sorted(_REGISTRY)


def make(name: str, **options) -> Task:
    """The task registered under `name`, built with the port's keyword `options` (e.g.
    `contacts="all"` for a DM Control port); built once per process and options (models
    are immutable)."""
    if name not in _REGISTRY:
        raise ValueError(f"unknown task {name!r}; available tasks: {', '.join(names())}")
    key = (name, *sorted(options.items()))
    if key not in _CACHE:
        _CACHE[key] = _REGISTRY[name](**options)
    return _CACHE[key]


class _Port:
    """The factory of a port in `tasks/`, which imports the port's module on first use:
    `import tasks` stays free of jax, and a scene is built only when asked for (a MetaWorld
    scene takes seconds)."""

    def __init__(self, module: str, cls: str):
        self.module, self.cls = module, cls

    def task_class(self) -> type[Task]:
        import importlib

        return getattr(importlib.import_module(f"tasks.{self.module}"), self.cls)

    def __call__(self, **options) -> Task:
        return self.task_class()(**options)


def task_class(name: str) -> type[Task]:
    """The class of the task registered under `name`, imported but not built. Its class
    attributes are the task's own facts: its goal line, and for a port the reference it is
    checked against (`suite` of a DM Control port; `metaworld_env`, `scripted_policy` and
    `object_joint` of a MetaWorld port)."""
    info(name)  # an unknown name stops here, with the registered ones
    factory = _REGISTRY[name]
    if isinstance(factory, _Port):
        return factory.task_class()
    if isinstance(factory, type):
        return factory
    raise ValueError(f"task {name!r} was registered with a factory function, not a class")


# XLA level 1 instead of XLA's own (3) where it measured a gain (benchmarks/README.md,
# "compile_level"; benchmarks/results/runs/compile_level.csv): cheetah_run's and quadruped_walk's
# first env step comes sooner, their chunks at the same speed. Not walker_walk (its evaluation
# runs slower at level 1) nor MetaWorld (its steps run slower).
_DMC_LEVELS = {"cheetah_run": 1, "quadruped_walk": 1}

# DM Control ports (tasks/dm_control/): 1000 control steps each (a test checks the built tasks)
for _name, _module, _cls in (("cheetah_run", "cheetah", "CheetahRun"),
                             ("walker_walk", "walker", "WalkerWalk"),
                             ("quadruped_walk", "quadruped", "QuadrupedWalk")):
    register(_name, _Port(f"dm_control.{_module}", _cls),
             TaskInfo("dm_control", 1000, False, _DMC_LEVELS.get(_name)))

# MetaWorld v3 ports (tasks/metaworld/): max_path_length 500
for _name, _cls in (("drawer_open", "DrawerOpen"), ("button_press", "ButtonPress"),
                    ("door_open", "DoorOpen"), ("window_open", "WindowOpen"),
                    ("door_unlock", "DoorUnlock"), ("sweep_into", "SweepInto")):
    register(_name, _Port(f"metaworld.{_name}", _cls), TaskInfo("metaworld", 500, True))

__all__ = ["Task", "TaskInfo", "TaskState", "info", "make", "names", "register", "task_class"]


def __getattr__(name: str):
    """`tasks.Task` and `tasks.TaskState` on first use: the registry itself needs no jax, so
    listing tasks (`hprior tasks`, `--help`) does not import it."""
    if name in ("Task", "TaskState"):
        from tasks import base

        return getattr(base, name)
    raise AttributeError(f"module 'tasks' has no attribute {name!r}")
