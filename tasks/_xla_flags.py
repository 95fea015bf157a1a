"""Sets the XLA flag MJX needs on CPU before jax is first imported.

Without `--xla_cpu_use_fusion_emitters=false`, XLA's CPU fusion emitter makes the cost of
MJX kinematics grow exponentially with kinematic-tree depth (MetaWorld's Sawyer scene:
0.5-2 s per physics substep instead of ~0.3 ms, measured on a 2-core x86 CPU with jax 0.10.2);
a test fails if `jit(mjx.kinematics)` on a MetaWorld scene gets slow again.
This module must be imported before jax: `tasks/__init__.py` and `hprior_jax/__init__.py`
import it first. Importing it after jax is already imported is too late for the flag to
take effect, so we warn loudly in that case.
"""
import os
import sys
import warnings
from importlib import metadata

FLAG = "--xla_cpu_use_fusion_emitters=false"
# Single-threaded Eigen inside XLA CPU. Added while chasing a hang of 2-seed training runs
# whose real cause was batched LAPACK QR in the vmapped orthogonal init (fixed in
# hprior_jax/networks/mlp.py; this flag did not prevent it). Kept because every test and
# measurement ran with it. It costs nothing measurable on jaxlib 0.10.2: XLA's CPU dots still
# use both cores with it (a 2048^2 matmul chain runs on 1.94 cores either way), and the SAC
# update takes the same time with =false and =true (`python -m benchmarks.updates.sac_update`,
# results/updates/sac_update.csv, column xla_eigen).
NO_EIGEN_THREADS = "--xla_cpu_multi_thread_eigen=false"


def jaxlib_needs_fusion_flag() -> bool:
    """Whether the installed jaxlib knows FLAG and needs it. jaxlib 0.11 removed the flag
    (an unknown flag in XLA_FLAGS aborts the process) and the slowdown with it: on jax 0.11.2
    without any flag, jit(mjx.kinematics) on metaworld's drawer scene takes 3.8 ms (median,
    this project's 2-core CPU). The project pins 0.10.2; a GPU machine's own newer jax (its
    CUDA build) runs the code unpinned."""
    try:
        major, minor = (int(x) for x in metadata.version("jaxlib").split(".")[:2])
    except (metadata.PackageNotFoundError, ValueError):
        return True
    return (major, minor) < (0, 11)


def ensure_xla_flags() -> None:
    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_cpu_multi_thread_eigen" not in flags:
        flags = (flags + " " + NO_EIGEN_THREADS).strip()
        os.environ["XLA_FLAGS"] = flags
    if "xla_cpu_use_fusion_emitters" not in flags and jaxlib_needs_fusion_flag():
        if "jax" in sys.modules and "jax._src.xla_bridge" in sys.modules:
            warnings.warn(
                "jax was imported before hprior_jax/tasks could set "
                f"XLA_FLAGS={FLAG}; MJX on CPU may be up to 1000x slower. "
                f"Export XLA_FLAGS={FLAG} before starting Python.",
                stacklevel=3,
            )
        os.environ["XLA_FLAGS"] = (flags + " " + FLAG).strip()
    # mujoco.mjx prints a line when the optional `warp` backend is missing; we never use it.
    os.environ.setdefault("MUJOCO_GL", "disable")


ensure_xla_flags()
