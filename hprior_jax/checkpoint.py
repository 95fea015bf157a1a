"""Whole-RunState checkpoints with orbax (host side only).

Keys are raw uint32 arrays, so the state restores bit-exactly and resuming continues the
same random streams as an uninterrupted run."""
from __future__ import annotations

import contextlib
import errno
import logging
import os
import sys
import traceback
from pathlib import Path

import jax
import orbax.checkpoint as ocp


class _OrbaxNoise(logging.Filter):
    """Lines orbax logs through absl that say nothing to a user: on every read of a
    checkpoint's leaf metadata, that the item's folder has no _CHECKPOINT_METADATA (the
    manager keeps it one level up); on reading a step's metadata, that it was not told how
    to restore the item (it was not asked to) or could not read the item's metadata (a
    damaged checkpoint, which the run reports in one line of its own); that a save waited
    for the one before it; and, on a resume after a kill, that it removes an unfinished
    save's folder (the run rolls back to its last checkpoint anyway); and a writer thread's
    report that the disk is full, which can come after the save has failed (the run says
    so in one line)."""

    NOISE = ("_CHECKPOINT_METADATA", "Please provide a `CheckpointHandlerRegistry`",
             "Failed to get item metadata from directory",
             "Waiting for previous save to complete took",
             "Removing existing directory since it is not finalized",
             "No space left on device")

    def filter(self, record: logging.LogRecord) -> bool:
        return not any(noise in record.getMessage() for noise in self.NOISE)


logging.getLogger("absl").addFilter(_OrbaxNoise())


class _HeldLogs(logging.Filter):
    """Holds back what orbax logs through absl while a save runs: a full disk makes each of
    its writer threads log a traceback before the save raises. A save that fails for want of
    space drops them (one line says it); otherwise they are logged as they came."""

    def __init__(self):
        super().__init__()
        self.records: list[logging.LogRecord] = []

    def filter(self, record: logging.LogRecord) -> bool:
        self.records.append(record)
        return False

    @contextlib.contextmanager
    def held(self):
        logger = logging.getLogger("absl")
        logger.addFilter(self)
        try:
            yield self
        finally:
            logger.removeFilter(self)
            for record in self.records:
                logger.handle(record)


def _closed_loop_callback(kind, value, tb) -> bool:
    frames = traceback.extract_tb(tb)
    return (kind is RuntimeError and str(value) == "Event loop is closed" and bool(frames)
            and frames[0].name == "call_soon_threadsafe")


def _quiet_late_writes() -> None:
    """When a save fails (a full disk), TensorStore's writes still in flight finish on its own
    threads and call back into the event loop orbax has already closed, which can happen
    before the save's error reaches this module; each such RuntimeError is printed as a
    traceback (through sys.excepthook or sys.unraisablehook), dozens of them. They say
    nothing the error does not: drop them (and only them)."""
    if getattr(sys.excepthook, "quiet_late_writes", False):
        return
    previous_except, previous_unraisable = sys.excepthook, sys.unraisablehook

    def except_hook(kind, value, tb):
        if not _closed_loop_callback(kind, value, tb):
            previous_except(kind, value, tb)

    def unraisable_hook(unraisable):
        if not _closed_loop_callback(unraisable.exc_type, unraisable.exc_value,
                                     unraisable.exc_traceback):
            previous_unraisable(unraisable)

    except_hook.quiet_late_writes = True
    sys.excepthook, sys.unraisablehook = except_hook, unraisable_hook
    logging.getLogger("asyncio").addFilter(_UnretrievedNoSpace())


class _UnretrievedNoSpace(logging.Filter):
    """asyncio logs each of orbax's writer tasks that failed for want of space and was never
    awaited ("Task exception was never retrieved") when the task is collected: drop those
    records, keep every other."""

    def filter(self, record: logging.LogRecord) -> bool:
        error = record.exc_info[1] if record.exc_info else None
        return not (error is not None and _no_space(error))


def _no_space(error: BaseException) -> bool:
    """Whether `error` (orbax's or TensorStore's, often not an OSError) says the disk is
    full."""
    while error is not None:
        text = str(error)
        if (isinstance(error, OSError) and error.errno == errno.ENOSPC
                or "No space left on device" in text or "os_error_code='28'" in text):
            return True
        error = error.__cause__ or error.__context__
    return False


_quiet_late_writes()


def _with_path(tree):
    return jax.tree_util.tree_flatten_with_path(tree)[0]


def _name(path) -> str:
    return jax.tree_util.keystr(path)


def leaves_by_name(tree) -> dict:
    """{leaf name: leaf} as a checkpoint stores `tree`: without zero-size leaves (orbax
    refuses to write them; e.g. MJX's empty `act` for models without actuator
    activations). Restore takes those from `like`."""
    return {_name(p): x for p, x in _with_path(tree) if x.size}


class Checkpointer:
    def __init__(self, directory: Path, max_to_keep: int | None = 2):
        self.directory = Path(directory).absolute()
        self._manager = ocp.CheckpointManager(
            self.directory, options=ocp.CheckpointManagerOptions(max_to_keep=max_to_keep,
                                                                 create=True))
        self.failed = False  # a save ran out of space: closing then says nothing more

    def save(self, step: int, state, metadata: dict | None = None) -> None:
        """`metadata` (JSON) is written with the checkpoint, in the same atomic step. A full
        disk raises OSError(ENOSPC) naming the checkpoint's folder, and nothing else is
        printed."""
        with _HeldLogs().held() as logs:
            try:
                self._manager.save(step, args=ocp.args.StandardSave(leaves_by_name(state)),
                                   custom_metadata=metadata)
                self._manager.wait_until_finished()
            except Exception as e:
                if not _no_space(e):
                    raise
                logs.records.clear()
                self.failed = True
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC),
                              str(self.directory / str(step))) from None

    def saved_metadata(self, step: int) -> dict:
        """The `metadata` saved with the checkpoint at `step` ({} for one saved without)."""
        return dict(self._manager.metadata(step).custom_metadata or {})

    def latest_step(self) -> int | None:
        return self._manager.latest_step()

    def all_steps(self) -> list[int]:
        return list(self._manager.all_steps())

    def stored_names(self, step: int | None = None) -> set[str]:
        """Leaf names held by the checkpoint at `step` (default: the latest)."""
        return set(self._metadata(step).keys())

    def stored_shape(self, name: str, step: int | None = None) -> tuple[int, ...]:
        return self.stored_shapes(step)[name]

    def stored_shapes(self, step: int | None = None) -> dict[str, tuple[int, ...]]:
        return {name: tuple(m.shape) for name, m in self._metadata(step).items()}

    def _metadata(self, step: int | None) -> dict:
        step = self.latest_step() if step is None else step
        metadata = ocp.StandardCheckpointer().metadata(self.directory / str(step) / "default")
        return metadata.item_metadata

    def restore(self, like, step: int | None = None, rename=None):
        """Restores into the structure, shapes and dtypes of `like` (a RunState).

        `rename(name) -> stored name | None` reads checkpoints written with other leaf names
        (an older state layout); None keeps `like`'s value for that leaf."""
        step = self.latest_step() if step is None else step
        if step is None:
            raise FileNotFoundError(f"no checkpoint in {self.directory}")
        rename = rename or (lambda name: name)
        flat_like = leaves_by_name(like)
        stored = {name: rename(name) for name in flat_like}
        abstract = {stored[name]: ocp.utils.to_shape_dtype_struct(x)
                    for name, x in flat_like.items() if stored[name] is not None}
        flat = self._manager.restore(step, args=ocp.args.StandardRestore(abstract))
        leaves = [flat.get(stored.get(_name(path)), leaf) for path, leaf in _with_path(like)]
        return step, jax.tree.unflatten(jax.tree.structure(like), leaves)

    def close(self) -> None:
        if not self.failed:
            self._manager.close()
            return
        with _HeldLogs().held() as logs:
            try:
                self._manager.close()
            except Exception:  # noqa: BLE001 - the same full disk, already reported
                pass
            logs.records.clear()
