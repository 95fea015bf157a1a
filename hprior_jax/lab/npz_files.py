"""The lab's .npz files: written whole and then renamed (a kill while writing leaves the
previous file, never half a file under the final name), and trees read back leaf by leaf."""
from __future__ import annotations

from pathlib import Path

import jax
import numpy as np


def write_atomically(path: Path, arrays: dict, compressed: bool = False) -> Path:
    """`arrays` ({name: array}) to the .npz `path`, through a temporary file renamed over it."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.npz")
    with open(tmp, "wb") as f:  # a file object: np.savez appends .npz to other names
        (np.savez_compressed if compressed else np.savez)(f, **arrays)
    tmp.replace(path)
    return path


def tree_of(like, leaves: list[np.ndarray]):
    """`leaves` as a tree shaped like `like` (a tree of arrays or ShapeDtypeStructs); None
    when their number, shapes or dtypes do not fit it."""
    want, treedef = jax.tree.flatten(like)
    if len(want) != len(leaves) or any(
            a.shape != tuple(x.shape) or a.dtype != x.dtype for a, x in zip(leaves, want)):
        return None
    return jax.tree.unflatten(treedef, [jax.numpy.asarray(a) for a in leaves])
