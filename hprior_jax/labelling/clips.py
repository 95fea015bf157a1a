"""Each query's two clips, rendered once (same camera, size and frame rate for both) and
cached as browser-playable MP4 files in the query folder."""
from __future__ import annotations

import functools
import os
import threading
from pathlib import Path

import numpy as np

import tasks
from hprior_jax.labelling.store import QueryFolder
from hprior_jax.render import default_camera, hand_start, render_frames, write_video

_render_lock = threading.Lock()  # one OpenGL context renders at a time


@functools.cache
def _mj_model(task: str):
    return tasks.make(task).mj_model


def clip_path(folder: QueryFolder, qid: str, side: int) -> Path:
    """The MP4 of segment `side` (1 or 2) of query `qid`, rendering both on first use."""
    query = folder.query(qid)
    path = folder.dir / "clips" / f"{qid}_{side}.mp4"
    if path.exists():
        return path
    with _render_lock:
        if path.exists():  # rendered while this request waited
            return path
        model = _mj_model(query.task)
        states = [folder.segment_states(qid, s) for s in (1, 2)]
        starts = [hand_start(s) for s in states]
        lookat = None if starts[0] is None else np.mean(starts, axis=0)
        camera = default_camera(model, lookat)  # one camera for both sides
        for s, st in zip((1, 2), states):
            out = folder.dir / "clips" / f"{qid}_{s}.mp4"
            tmp = out.with_suffix(".tmp.mp4")
            write_video(render_frames(model, st, camera=camera), tmp, fps=query.fps)
            os.replace(tmp, out)  # a reader never sees half a file
    return path
