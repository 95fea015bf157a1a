"""Run directories: create one, check an --out, extend a run's budget on resume (config.json
of today's format and the first one is read back by `config_file`).

Format 1 (before methods were plug-ins) wrote every section (`pebble`, `prior`) into every
run's config.json, chose PRIOR-NRP and RVAR by `prior.variant`, and kept the method's state
under `extra` in checkpoints. `read_config` turns such a file into today's config (and
`loop.checkpoints.legacy_checkpoint_name` maps today's state to the leaf names its checkpoints
hold), so a run written then still resumes.
"""
from __future__ import annotations

import dataclasses
import json
import os
import shutil
import time
from dataclasses import dataclass
from pathlib import Path

from hprior_jax.config import CHANGEABLE_ON_RESUME, RunConfig, differing_fields, field_value
from hprior_jax.loop.run_files import EXTENDING, latest_checkpoint_step, write_atomic
from hprior_jax.runs.config_file import (  # noqa: F401  (read here by the commands)
    load_run_config, read_config, read_json)


class RunDirError(ValueError):
    """A run directory that cannot be used; the message names the path and the fix."""


@dataclass(frozen=True)
class Wording:
    """How a message names what the user gave: the command line's flags (`hprior train`) or
    the Python API's config fields (`hprior_jax.train`)."""

    python: bool = False

    def field(self, name: str) -> str:
        return f"config.{name}" if self.python else "--" + name.replace("_", "-")

    @property
    def resuming(self) -> str:
        return "resume=True" if self.python else "--resume"

    def resume(self, out: Path) -> str:
        return ("hprior_jax.train(config, resume=True)" if self.python
                else f"`hprior train --resume {out}`")


COMMAND_LINE, PYTHON = Wording(), Wording(python=True)


def run_dir_path(cfg: RunConfig) -> Path:
    return Path(cfg.out) if cfg.out else Path("runs") / (
        f"{cfg.task}_{cfg.algo}_{time.strftime('%Y%m%d-%H%M%S')}")


def check_out_dir(out: Path, wording: Wording = COMMAND_LINE) -> Path:
    """Refuses, without writing anything, an --out that is not empty or cannot be written."""
    out, flag = Path(out), wording.field("out")
    if out.exists() and not out.is_dir():
        raise RunDirError(f"{flag} {out} is a file, not a directory; choose another {flag}")
    if out.is_dir() and any(out.iterdir()):
        fix = (f"continue it with {wording.resume(out)} or choose another {flag}"
               if (out / "config.json").exists() else
               f"it is not a run directory (no config.json): choose another {flag}")
        raise RunDirError(f"output directory {out} exists and is not empty; {fix}")
    parent = next(p for p in (out, *out.absolute().parents) if p.exists())
    if not parent.is_dir():
        raise RunDirError(f"{flag} {out}: {parent} is a file, so no directory can be made "
                          f"under it; choose another {flag}")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise RunDirError(f"{flag} {out}: no permission to write in {parent}; choose a "
                          "directory you can write to")
    return out


def prepare_run_dir(cfg: RunConfig, run_info: dict | None = None,
                    wording: Wording = COMMAND_LINE) -> Path:
    """Creates the run directory and its config.json; refuses a non-empty or unwritable one.
    `run_info` (what produced the run: `hprior_jax.provenance.run_info()`) is stored beside
    the configuration."""
    out, flag = check_out_dir(run_dir_path(cfg), wording), wording.field("out")
    try:
        out.mkdir(parents=True, exist_ok=True)
        write_config(out, cfg, run_info)
    except OSError as e:
        raise RunDirError(f"{flag} {out}: {e.strerror or e}; choose another {flag}") from None
    return out


def discard_unstarted(run_dir: Path, made: bool) -> None:
    """Undoes prepare_run_dir for a run stopped before it trained anything (Ctrl-C while it
    was checked or compiled): the directory as it was found, gone if prepare_run_dir made it,
    else empty again, so the command can be run again as it was typed."""
    if not made:
        for p in Path(run_dir).iterdir():  # check_out_dir found it empty: all of it is ours
            shutil.rmtree(p) if p.is_dir() else p.unlink()
    else:
        shutil.rmtree(run_dir, ignore_errors=True)


def write_config(run_dir: Path, cfg: RunConfig, run_info: dict | None) -> None:
    d = json.loads(cfg.to_json())
    if run_info is not None:
        d["run_info"] = run_info
    write_atomic(Path(run_dir) / "config.json", json.dumps(d, indent=2) + "\n")


def run_info_of(run_dir: Path) -> dict | None:
    return read_json(run_dir).get("run_info")


def resume_config(run_dir: Path, requested: RunConfig,
                  wording: Wording = COMMAND_LINE) -> tuple[RunConfig, int | None]:
    """The run's config with the changes `requested` may make on resume (other changes are
    refused, naming them). A change is not yet the run's: it waits in config.extending.json
    until the resumed run writes its first checkpoint (`commit_extension`), so a run stopped
    before that still resumes as it was. Returns the config and the replay capacity of the
    run's checkpoints when it changes."""
    old = load_run_config(run_dir)
    changed = [k for k in differing_fields(old, requested) if k != "out"]
    refused = [k for k in changed if k not in CHANGEABLE_ON_RESUME]
    if refused:
        flags = ", ".join(f"{wording.field(k)} ({field_value(old, k)!r} -> "
                          f"{field_value(requested, k)!r})" for k in refused)
        raise ValueError(
            f"{wording.resuming} continues {run_dir} as it was configured; these cannot "
            f"change: {flags}. A resumed run may change only "
            f"{', '.join(map(wording.field, CHANGEABLE_ON_RESUME))}; start a new run (another "
            f"{wording.field('out')}) for the rest")
    if not changed:
        return old, None
    checkpoint_step = latest_checkpoint_step(run_dir)
    new = requested
    if new.steps < old.steps and not old.replay_capacity:
        new = dataclasses.replace(new, replay_capacity=old.capacity)  # keep the buffer's size
    if checkpoint_step is not None and new.steps < checkpoint_step:
        raise ValueError(f"{wording.field('steps')} {new.steps} is below step "
                         f"{checkpoint_step} of the run's latest checkpoint")
    new = dataclasses.replace(new, out=old.out)
    pending = json.loads(new.to_json())
    pending["run_info"] = run_info_of(run_dir)
    write_atomic(Path(run_dir) / EXTENDING, json.dumps(
        {"from_step": checkpoint_step or 0, "config": pending}, indent=2) + "\n")
    return new, old.capacity if new.capacity != old.capacity else None
