"""Run directories: create, read config.json (today's format and the first one), extend.

Format 1 (before methods were plug-ins) wrote every section (`pebble`, `prior`) into every
run's config.json, chose PRIOR-NRP and RVAR by `prior.variant`, and kept the method's state
under `extra` in checkpoints. `read_config` turns such a file into today's config, and
`legacy_checkpoint_name` maps today's state to the leaf names its checkpoints hold, so a run
written then still resumes.
"""
from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

from hprior_jax.config import RunConfig
from hprior_jax.methods import registry


def prepare_run_dir(cfg: RunConfig) -> Path:
    """Creates the run directory; refuses to write into a non-empty one."""
    out = Path(cfg.out) if cfg.out else Path("runs") / (
        f"{cfg.task}_{cfg.algo}_{time.strftime('%Y%m%d-%H%M%S')}")
    if out.exists() and any(out.iterdir()):
        raise FileExistsError(
            f"output directory {out} exists and is not empty; continue it with "
            f"`hprior train --resume {out}` or choose another --out")
    out.mkdir(parents=True, exist_ok=True)
    (out / "config.json").write_text(cfg.to_json() + "\n")
    return out


def load_run_config(run_dir: Path) -> RunConfig:
    return read_config(_read_json(run_dir))


def read_config(d: dict) -> RunConfig:
    """config.json of either format -> today's RunConfig."""
    if d.get("format", 1) == 1:
        d = registry.from_format_1(d)
    return RunConfig.from_dict(d)


def legacy_checkpoint_name(name: str) -> str | None:
    """A leaf name of today's RunState -> its name in a format-1 checkpoint, or None for a
    leaf those do not hold (λ was a compile-time constant then: the state takes it from
    config.json)."""
    if name.startswith(".method.ext.lam"):
        return None
    return name.replace(".method.ext.", ".extra.").replace(".method.", ".extra.")


def extend_run(run_dir: Path, steps: int) -> tuple[RunConfig, int]:
    """Raises the step budget of an existing run; returns the new config and the replay
    capacity its checkpoints were written with."""
    old = load_run_config(run_dir)
    if steps < old.steps:
        raise ValueError(f"--steps {steps} is below the run's budget {old.steps}; a resumed "
                         "run can only be extended")
    new = dataclasses.replace(old, steps=steps)
    (Path(run_dir) / f"config.steps{old.steps}.json").write_text(
        (Path(run_dir) / "config.json").read_text())
    (Path(run_dir) / "config.json").write_text(new.to_json() + "\n")
    return new, old.capacity


def _read_json(run_dir: Path) -> dict:
    path = Path(run_dir) / "config.json"
    if not path.exists():
        raise FileNotFoundError(f"{path} not found: --resume needs a run directory written "
                                "by `hprior train`")
    return json.loads(path.read_text())
