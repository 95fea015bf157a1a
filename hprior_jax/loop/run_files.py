"""Files of a run directory the loop itself writes besides checkpoints and logs: a pending
extension of the budget (config.extending.json) and its commit, written atomically. Plain
JSON: reading a config into a RunConfig is `hprior_jax.runs.run_dir`'s job."""
from __future__ import annotations

import json
import os
from pathlib import Path

EXTENDING = "config.extending.json"  # an extension's config until its first checkpoint


def commit_extension(run_dir: Path) -> str | None:
    """Makes a pending extension the run's config (the previous one kept as
    config.steps<OLD>.json); called once its first checkpoint exists. -> a line saying so,
    or None when no extension was pending."""
    run_dir = Path(run_dir)
    pending = run_dir / EXTENDING
    if not pending.exists():
        return None
    new = json.loads(pending.read_text())["config"]
    old_text = (run_dir / "config.json").read_text()
    old_steps = json.loads(old_text)["steps"]
    write_atomic(run_dir / f"config.steps{old_steps}.json", old_text)
    write_atomic(run_dir / "config.json", json.dumps(new, indent=2) + "\n")
    pending.unlink()
    return f"the run's budget is now {new['steps']} steps (was {old_steps})"


def settle_extension(run_dir: Path, latest_step: int | None) -> str | None:
    """An extension left pending by a stopped process: committed when a checkpoint past the
    step it started from exists (it checkpointed, then stopped before the commit), otherwise
    rolled back. -> one line saying which, or None when none was pending."""
    pending = Path(run_dir) / EXTENDING
    if not pending.exists():
        return None
    record = json.loads(pending.read_text())
    if latest_step is not None and latest_step > record["from_step"]:
        return "an interrupted extension had checkpointed: " + commit_extension(run_dir)
    pending.unlink()
    return (f"an extension to {record['config']['steps']} steps was interrupted before its "
            f"first checkpoint: rolled back, the run resumes as configured before it")


def latest_checkpoint_step(run_dir: Path) -> int | None:
    """The newest finished checkpoint's step (orbax renames a checkpoint's folder to its step
    only once it is complete), or None."""
    folder = Path(run_dir) / "checkpoints"
    steps = [int(p.name) for p in folder.iterdir() if p.name.isdigit()] if folder.is_dir() else []
    return max(steps, default=None)


def write_atomic(path: Path, text: str) -> None:
    """Writes `text` to a temporary file beside `path`, then renames it over `path`: a kill
    leaves the old file or the new one, never half of one."""
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "w") as f:
        f.write(text)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
