"""Test configuration: XLA flag before jax, persistent compilation cache, small shapes."""
import os

from tests import xla_opt  # noqa: E402,F401  (before jax: the suite compiles at -O0)
from tasks import _xla_flags  # noqa: E402,F401  (XLA_FLAGS before jax; see that module)
os.environ.setdefault("MUJOCO_GL", "disable")

import jax  # noqa: E402

from hprior_jax.setup_jax import enable_compilation_cache  # noqa: E402

enable_compilation_cache()

from tests.toy_task import ensure_registered  # noqa: E402

ensure_registered()


# The fast suite's longest files by worker time (measured 2026-12-03, `--junitxml`), run first:
# with `--dist loadfile` a long file collected last would run alone at the end while the
# other worker idles (CI has 25 minutes on 2 cores). The rest keep their order.
LONGEST_FIRST = ("tests/test_prior_loop.py", "tests/test_devices.py",
                 "tests/tasks/test_metaworld_tasks.py", "tests/tasks/test_metaworld_dynamics.py",
                 "tests/test_benchmark_helpers.py", "tests/test_pebble_loop.py",
                 "tests/tasks/test_dm_control_tasks.py", "tests/test_human_teacher.py",
                 "tests/test_life_cycle.py", "tests/test_torch_world_model.py",
                 "tests/test_train.py", "tests/test_world_model.py")


def pytest_collection_modifyitems(config, items):
    rank = {path: i for i, path in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.nodeid.split("::")[0], len(rank)))  # stable
