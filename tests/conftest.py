"""Test configuration: XLA flag before jax, persistent compilation cache, small shapes."""
import os

from tasks import _xla_flags  # noqa: E402,F401  (XLA_FLAGS before jax; see that module)
os.environ.setdefault("MUJOCO_GL", "disable")

import jax  # noqa: E402

from hprior_jax.setup_jax import enable_compilation_cache  # noqa: E402

enable_compilation_cache()

from tests.toy_task import ensure_registered  # noqa: E402

ensure_registered()
