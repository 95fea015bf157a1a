"""Saving and restoring a run's checkpoints: the newest readable one, a damaged one set
aside, and the leaf names of the first checkpoint format (before methods were plug-ins, a
method's state was kept under `extra`)."""
from __future__ import annotations

import re
from pathlib import Path

from hprior_jax.checkpoint import leaves_by_name
from hprior_jax.loop import devices
from hprior_jax.loop.run_files import commit_extension
from hprior_jax.loop.state import RunState


# the physics fields a replay buffer records for rendering (a person's clips): a field added
# later (e.g. the MetaWorld object's placement) is absent from older checkpoints
RECORDED = ".replay.physics"


class CheckpointUnreadable(ValueError):
    """No checkpoint of a run could be restored; the message names the newest and why."""


class CheckpointMismatch(ValueError):
    """A readable checkpoint whose arrays are not those of the state the run's configuration
    builds (its config.json changed since): not damage, so nothing is set aside."""

    def __init__(self, directory: Path, step: int, differences: list[str]):
        self.step, self.differences = step, differences
        more = f" (and {len(differences) - 2} more)" if len(differences) > 2 else ""
        super().__init__(f"the checkpoint at step {step} in {directory} does not fit the "
                         f"run's configuration ({'; '.join(differences[:2])}{more}): was "
                         f"{Path(directory).parent / 'config.json'} edited? Put its values "
                         "back to resume the run, or start a new run (another --out)")


def save(ckpt, step: int, rs: RunState, run_dir: Path, say, config: dict | None = None) -> None:
    """A checkpoint (with `config`, the configuration it was written under), then a pending
    extension of the run's budget becomes its config (it now has a checkpoint it can resume
    from)."""
    ckpt.save(step, rs, metadata=None if config is None else {"config": config})
    if devices.is_primary():
        note = commit_extension(run_dir)
        if note:
            say(note)


def restore_latest(ckpt, like: RunState, step: int | None = None, on_unreadable=None):
    """The checkpoint at `step`, or by default the newest one that restores (written by
    today's state layout or the first one). A newer one that does not (a truncated or
    missing file) is passed to `on_unreadable(step, error)` and the next older is tried;
    without `on_unreadable`, or when none restores, CheckpointUnreadable names it."""
    candidates = [step] if step is not None else sorted(ckpt.all_steps(), reverse=True)
    for i, candidate in enumerate(candidates):
        try:
            stored = ckpt.stored_names(candidate)
            legacy = any(name.startswith(".extra") for name in stored)

            def rename(name: str) -> str | None:
                old = legacy_checkpoint_name(name) if legacy else name
                if old is not None and old not in stored and name.startswith(RECORDED):
                    return None  # a field recorded since it was written: `like`'s zeros
                return old
            _check_fits(ckpt, like, candidate, rename)
            return ckpt.restore(like, candidate, rename=rename)
        except CheckpointMismatch:
            raise  # the configuration changed, not the checkpoint: an older one fits no better
        except Exception as e:  # orbax raises many kinds for a damaged checkpoint
            if on_unreadable is None or i + 1 == len(candidates):
                raise CheckpointUnreadable(
                    f"the checkpoint at step {candidate} in {ckpt.directory} cannot be "
                    f"restored: {first_line(e)}") from e
            on_unreadable(candidate, e)
    raise CheckpointUnreadable(f"{ckpt.directory} holds no checkpoint")


def _check_fits(ckpt, like: RunState, step: int, rename) -> None:
    """Raises CheckpointMismatch when the checkpoint's leaves (names and shapes, from its
    metadata) are not those `like` asks for."""
    stored = ckpt.stored_shapes(step)
    wanted = {rename(name): tuple(x.shape) for name, x in leaves_by_name(like).items()}
    wanted.pop(None, None)
    differences = [f"{name} is {stored[name]} in the checkpoint, {shape} in this run"
                   for name, shape in wanted.items()
                   if name in stored and stored[name] != shape]
    differences += [f"{name} is not in the checkpoint" for name in wanted if name not in stored]
    differences += [f"{name} is not in this run's state" for name in stored
                    if name not in wanted]
    if differences:
        raise CheckpointMismatch(ckpt.directory, step, differences)


def legacy_checkpoint_name(name: str) -> str | None:
    """A leaf name of today's RunState -> its name in a format-1 checkpoint, or None for a
    leaf those do not hold (λ was a compile-time constant then: the state takes it from
    config.json)."""
    if name.startswith(".method.ext.lam"):
        return None
    return name.replace(".method.ext.", ".extra.").replace(".method.", ".extra.")


def first_line(error: BaseException, limit: int = 100) -> str:
    """`Type: message` of `error`, short: its first line without the object reprs and the
    bracketed source locations and specs that orbax and TensorStore add."""
    text = (str(error).strip().splitlines() or [""])[0]
    text = re.sub(r"<[^<>]* at 0x[0-9a-fA-F]+>", "an object", text)
    text = re.sub(r"\s*\[[a-z_ ]+=.*$", "", text).strip()
    text = f"{type(error).__name__}: {text}" if text else type(error).__name__
    return text if len(text) <= limit else text[:limit - 3].rstrip() + "..."


def set_aside(run_dir: Path, step: int) -> Path:
    """Moves the unreadable checkpoint of `step` to RUN/broken_checkpoints/ (kept for a
    post-mortem, out of the way of the next save at that step)."""
    src = Path(run_dir) / "checkpoints" / str(step)
    dest = Path(run_dir) / "broken_checkpoints" / str(step)
    n = 1
    while dest.exists():
        dest, n = Path(run_dir) / "broken_checkpoints" / f"{step}.{n}", n + 1
    dest.parent.mkdir(exist_ok=True)
    src.rename(dest)
    return dest


def set_aside_line(step: int, error: BaseException, dest: Path, resumed: int) -> str:
    """What a resume says of a checkpoint it set aside, once it has restored an older one."""
    return (f"the checkpoint at step {step} cannot be restored ({first_line(error)}); moved "
            f"to {dest}, resuming from step {resumed}")
