"""hprior_jax: Hindsight PRIOR and PbRL baselines in JAX/Flax on MJX tasks.

The Python API (`hprior_jax.make_env`, `train`, `load_policy`, ...) is imported on first use,
so `import hprior_jax.<module>` (every `hprior` command) does not load jax for it."""
import os as _os
import signal as _signal
import sys as _sys


def _quit_on_ctrl_c(signum, frame):
    """Ctrl-C while the `hprior` command imports: nothing is written yet, so one line and
    130, not a traceback from whichever import was running."""
    _sys.stderr.write("interrupted\n")
    _sys.stderr.flush()
    _os._exit(130)


def _quiet_ctrl_c_while_importing() -> None:
    """In the `hprior` command only (never in a notebook or a program importing the
    library): Ctrl-C ends quietly until `hprior_jax.cli.main` hands it to the command."""
    if _signal.getsignal(_signal.SIGINT) is _signal.default_int_handler:
        try:
            _signal.signal(_signal.SIGINT, _quit_on_ctrl_c)
        except ValueError:  # not the main thread: signals are not ours to set
            pass


if _os.path.basename(getattr(_sys.modules.get("__main__"), "__file__", None) or "") == "hprior":
    _quiet_ctrl_c_while_importing()  # the console script, before anything else is imported

from tasks import _xla_flags  # noqa: F401,E402  (sets XLA_FLAGS before jax is imported)

from hprior_jax._version import __version__  # noqa: F401,E402

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
