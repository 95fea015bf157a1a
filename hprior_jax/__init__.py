"""hprior_jax: Hindsight PRIOR and PbRL baselines in JAX/Flax on MJX tasks.

The Python API (`hprior_jax.make_env`, `train`, `load_policy`, ...) is imported on first use,
so `import hprior_jax.<module>` (every `hprior` command) does not load jax for it."""
from tasks import _xla_flags  # noqa: F401  (sets XLA_FLAGS before jax is imported)

from hprior_jax._version import __version__  # noqa: F401

_API = {"Env": "api", "Evaluation": "api", "evaluate_policy": "api", "make_env": "api",
        "train": "api", "export_seed": "export", "load_policy": "export",
        "load_reward": "export"}
__all__ = sorted(_API)


def __getattr__(name: str):
    if name not in _API:
        raise AttributeError(f"module 'hprior_jax' has no attribute {name!r}")
    import importlib

    value = getattr(importlib.import_module(f"hprior_jax.{_API[name]}"), name)
    globals()[name] = value  # the next access is a plain attribute
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_API))
