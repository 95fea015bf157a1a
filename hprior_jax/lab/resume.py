"""A lab's state between rounds, so that a lab stopped by Ctrl-C, a kill or the end of a
session goes on from where it was (`hprior reward-lab ... --resume`): every cell (reward
ensemble, optimizer, stored pairs with their credit, random key), the next round, the rows of
the budgets already reached (with their held-out predictions), and the time spent. The rounds
are deterministic functions of the cells, so a resumed lab gives the rows of one that never
stopped.

One .npz, written whole and then renamed: a kill while writing leaves the previous state.
The state names the lab it belongs to (a digest of its settings, data and given labels);
resuming another lab into the same folder is refused rather than mixed.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path

import jax
import numpy as np

from hprior_jax.lab.npz_files import tree_of, write_atomically

STATE_NAME = "lab_state.npz"


class StateMismatch(ValueError):
    """The folder's state belongs to a lab with other settings, data or labels."""


@dataclass
class LabState:
    """Where a lab is: schedule `schedule` (one per budget in a one-shot lab, else one), its
    next round `next_round`, the leaves of each program group's cells, the rows reached
    (with `prediction`) and the counters of the time and work done."""

    schedule: int
    next_round: int
    cells: list[list[np.ndarray]]
    rows: list[dict]
    adam_steps: int = 0
    seconds: dict[str, float] = field(default_factory=dict)
    wall_seconds: float = 0.0


def fingerprint(cfg, data, given=None) -> str:
    """Digest of what decides a lab's rows: its config, its dataset's arrays and the given
    labels (a person's), and the jax version its programs are compiled by."""
    h = hashlib.sha256()
    h.update(json.dumps(dataclasses.asdict(cfg), sort_keys=True, default=str).encode())
    for array in (data.train_obs, data.train_act, data.train_reward, data.test_obs,
                  data.test_act, *(() if given is None else jax.tree.leaves(given))):
        h.update(np.ascontiguousarray(array).tobytes())
    h.update(jax.__version__.encode())
    return h.hexdigest()[:20]


def save(path: Path, lab: str, state: LabState) -> Path:
    """`state` of the lab with fingerprint `lab` to `path`, atomically."""
    rows = [{k: v for k, v in r.items() if k != "prediction"} for r in state.rows]
    meta = dict(lab=lab, schedule=state.schedule, next_round=state.next_round, rows=rows,
                groups=[len(leaves) for leaves in state.cells], adam_steps=state.adam_steps,
                seconds=state.seconds, wall_seconds=state.wall_seconds)
    arrays = {f"cell_{g}_{i}": np.asarray(x)
              for g, leaves in enumerate(state.cells) for i, x in enumerate(leaves)}
    if state.rows:
        arrays["prediction"] = np.stack([r["prediction"] for r in state.rows])
    return write_atomically(path, dict(
        meta=np.frombuffer(json.dumps(meta).encode(), np.uint8), **arrays))


def load(path: Path, lab: str, cells: bool = True) -> LabState | None:
    """The state at `path` (without its cells' arrays unless `cells`); None when there is
    none. Raises StateMismatch when it is the state of another lab."""
    path = Path(path)
    if not path.exists():
        return None
    with np.load(path) as stored:  # reads only the arrays asked for
        meta = json.loads(stored["meta"].tobytes().decode())
        if meta["lab"] != lab:
            raise StateMismatch(
                f"{path} is the state of another lab (other settings, dataset or labels): "
                "run the same command as the lab that left it, or choose another --out")
        if not cells:
            meta["groups"] = []
        cells = [[stored[f"cell_{g}_{i}"] for i in range(n)]
                 for g, n in enumerate(meta["groups"])]
        predictions = stored["prediction"] if meta["rows"] else []
    rows = [dict(r, prediction=p) for r, p in zip(meta["rows"], predictions)]
    return LabState(schedule=meta["schedule"], next_round=meta["next_round"], cells=cells,
                    rows=rows, adam_steps=meta["adam_steps"], seconds=meta["seconds"],
                    wall_seconds=meta["wall_seconds"])


def restore(like, leaves: list[np.ndarray]):
    """`leaves` as a tree shaped like `like` (freshly initialised cells), each leaf checked."""
    tree = tree_of(like, leaves)
    if tree is None:
        raise StateMismatch("the saved cells do not fit this lab's cells")
    return tree


class Checkpoints:
    """The host side of a resumable lab: where its state lives, whose it is, how often it is
    written (`every_s`: after a round once that long has passed since the last write, and
    whenever a budget is reached)."""

    def __init__(self, path: Path, lab: str, every_s: float = 600.0):
        self.path, self.lab, self.every_s = Path(path), lab, every_s

    def load(self) -> LabState | None:
        return load(self.path, self.lab)

    def check(self) -> None:
        """Raises StateMismatch when the state kept is another lab's."""
        load(self.path, self.lab, cells=False)

    def save(self, state: LabState) -> None:
        save(self.path, self.lab, state)

    def discard(self) -> None:
        self.path.unlink(missing_ok=True)
