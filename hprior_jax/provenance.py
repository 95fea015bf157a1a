"""What produced a run: command line, git commit, package versions, device (host side)."""
from __future__ import annotations

import platform
import shlex
import subprocess
import sys
import time
from importlib import metadata
from pathlib import Path

from hprior_jax._version import __version__

PACKAGES = ("jax", "jaxlib", "mujoco", "mujoco-mjx", "flax", "optax", "orbax-checkpoint",
            "numpy", "dm-control", "metaworld")


def git_commit() -> str | None:
    """The checkout's commit, suffixed `-dirty` when tracked files differ; None outside git."""
    root = Path(__file__).resolve().parent.parent
    try:
        commit = subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True,
                                text=True, timeout=10, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"],
                               cwd=root, capture_output=True, text=True, timeout=10).stdout
    except (OSError, subprocess.SubprocessError):
        return None
    return commit + ("-dirty" if dirty.strip() else "")


def versions() -> dict[str, str]:
    out = {"python": platform.python_version(), "hprior_jax": __version__}
    for name in PACKAGES:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = "not installed"
    return out


def device() -> str:
    import jax

    d = jax.devices()[0]
    return f"{jax.device_count()} x {d.platform}: {getattr(d, 'device_kind', d)}"


def run_info(command: list[str] | None = None) -> dict:
    """Recorded in config.json under `run_info` when a run starts; `command` is the `hprior`
    command's arguments (default: this process's command line)."""
    return {"command": shlex.join(["hprior", *command] if command is not None else sys.argv),
            "git_commit": git_commit(), "versions": versions(), "device": device(),
            "host": platform.node(), "started": time.strftime("%Y-%m-%dT%H:%M:%S%z")}


def version_string() -> str:
    commit = git_commit()
    return f"hprior_jax {__version__}" + (f" (git {commit})" if commit else "")
