"""A person as the teacher of a training run (`hprior train --teacher human`).

At each feedback round the method hands over what the round's queries show (physics states
and true rewards of both segments, per seed); this writes them into the run's query folder
(`RUN/labels/`), serves the labelling page from a background thread, renders the clips
ahead, and waits until every query of the round is answered. The answers come back as
B-Pref labels (`QueryFolder.labels`: left 0, right 1, equal -1, can't tell = skipped).

Waiting can end without answers: Ctrl-C, or no new answer within the timeout. Then
`LabellingStopped` tells the host loop to stop; it has checkpointed the run before the
round, and a resumed run proposes the same queries again (same state, same keys), finds
them in the folder with the answers already given, and asks only for the rest."""
from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from hprior_jax.labelling.clips import clip_path
from hprior_jax.labelling.server import BackgroundServer, ServerOptions
from hprior_jax.labelling.store import QueryFolder, pair_arrays, query_id, write_queries


class LabellingStopped(Exception):
    """The run stops while waiting for a person's answers (the answers given are kept)."""


@dataclass(frozen=True)
class AskOptions:
    server: ServerOptions = field(default_factory=ServerOptions)
    timeout_s: float = 3600.0
    """Stop (with a checkpoint) when no new answer came for this long."""
    poll_s: float = 0.5


class HumanTeacher:
    def __init__(self, folder: Path, task, seeds, options: AskOptions,
                 should_stop: Callable[[], bool] = lambda: False,
                 say: Callable[[str], None] = print):
        self.dir = Path(folder)
        self.dir.mkdir(parents=True, exist_ok=True)
        (self.dir / "queries.jsonl").touch()
        self.folder = QueryFolder(self.dir)
        self.task, self.seeds, self.options = task, list(seeds), options
        self.should_stop, self.say = should_stop, say
        self._server: BackgroundServer | None = None
        self._renderer: threading.Thread | None = None
        self._stop_rendering = threading.Event()
        self.waited_s = 0.0  # seconds the run has waited for answers (logged apart)

    def serve(self) -> str:
        """Starts serving the folder (once) and returns its address."""
        if self._server is None:
            self._server = BackgroundServer(self.folder, self.options.server.resolved())
        return self._server.url

    def ask(self, round_: int, step: int, shown: dict, count: int
            ) -> tuple[np.ndarray, np.ndarray]:
        """`shown`: "physics1"/"physics2" {field: [S, Q, H, ...]}, "true_reward1"/"2"
        [S, Q, H] for the run's S seeds; the first `count` of each seed's Q pairs are asked.
        Returns B-Pref labels int32 [S, Q] and valid bool [S, Q] (False where skipped or
        beyond `count`)."""
        num_seeds, num_pairs = np.shape(shown["true_reward1"])[:2]
        ids = [[query_id(round_, q, seed) for q in range(count)] for seed in self.seeds]
        self._write(round_, shown, ids)
        flat = [q for seed_ids in ids for q in seed_ids]
        self._render_ahead(flat)
        t0 = time.perf_counter()
        try:
            self._wait(round_, step, flat)
        finally:
            self.waited_s += time.perf_counter() - t0
        labels = np.zeros((num_seeds, num_pairs), np.int32)
        valid = np.zeros((num_seeds, num_pairs), bool)
        for i, seed_ids in enumerate(ids):
            labels[i, :count], valid[i, :count] = self.folder.labels(seed_ids)
        return labels, valid

    def close(self) -> None:
        # the clip in progress is finished first: a GL context torn down by the interpreter's
        # exit under a rendering thread crashes the process
        self._stop_rendering.set()
        if self._renderer is not None:
            self._renderer.join(timeout=120)
        if self._server is not None:
            self._server.close()
            self._server = None

    # -------------------------------------------------------------------------------------
    def _write(self, round_: int, shown: dict, ids: list[list[str]]) -> None:
        """Writes the queries not in the folder yet; those already there (a resumed round)
        must hold the same segments, or the answers given would be for other clips."""
        asked = {q.id for q in self.folder.queries()}
        fps = 1.0 / self.task.control_timestep
        for i, (seed, seed_ids) in enumerate(zip(self.seeds, ids)):
            for q, qid in enumerate(seed_ids):
                one, two = (_segment(shown, side, i, q) for side in (1, 2))
                if qid not in asked:
                    write_queries(self.dir, self.task.name, round_, [(one, two)], fps,
                                  first_index=q, seed=seed)
                    continue
                stored, new = self.folder.segment_arrays(qid), pair_arrays(one, two)
                if stored.keys() != new.keys() or not all(
                        np.allclose(stored[k], new[k], rtol=1e-5, atol=1e-6) for k in new):
                    raise RuntimeError(
                        f"query {qid} in {self.dir} holds other segments than this round "
                        "proposes: the folder is not this run's (or the run changed since); "
                        "move the folder away to be asked afresh")

    def _render_ahead(self, ids: list[str]) -> None:
        """Clips are rendered on first request; rendering them now spares the person the
        wait (in a thread: a run that goes on does not wait for it; it skips the queries
        answered meanwhile and stops at `close`)."""
        if not hasattr(self.task, "mj_model"):
            return
        def render():
            for qid in ids:
                if self._stop_rendering.is_set():
                    return
                if qid in self.folder.answers():
                    continue
                try:
                    clip_path(self.folder, qid, 1)
                except Exception as e:  # the page asks again and shows the error
                    self.say(f"rendering the clips of {qid} failed: {e}")
                    return

        if self._renderer is not None:
            self._renderer.join()  # the last round's, which stops at its answered queries
        self._renderer = threading.Thread(target=render, daemon=True)
        self._renderer.start()

    def _wait(self, round_: int, step: int, ids: list[str]) -> None:
        per_seed = len(ids) // max(len(self.seeds), 1)
        url = self.serve()
        self.say(f"feedback round {round_} (step {step}): {len(ids)} queries ({per_seed} per "
                 f"seed x {len(self.seeds)} seeds) wait for your answers: open {url}\n"
                 "  (Ctrl-C checkpoints and stops; `hprior train --resume` asks again and "
                 "keeps every answer given)")
        answered_before, last_change = -1, time.monotonic()
        while True:
            done = self.folder.answers()
            answered = sum(q in done for q in ids)
            if answered == len(ids):
                self.say(f"feedback round {round_}: all {len(ids)} answered; training goes on")
                return
            now = time.monotonic()
            if answered != answered_before:
                answered_before, last_change = answered, now
            if self.should_stop():
                raise LabellingStopped(f"stopped while round {round_} waited for answers "
                                       f"({answered} of {len(ids)} given, all kept)")
            if now - last_change > self.options.timeout_s:
                raise LabellingStopped(
                    f"no answer for {self.options.timeout_s:.0f} s (--label-timeout) while "
                    f"round {round_} waited ({answered} of {len(ids)} given, all kept)")
            time.sleep(self.options.poll_s)


def _segment(shown: dict, side: int, seed_index: int, pair: int) -> dict[str, np.ndarray]:
    arrays = {k: np.asarray(v[seed_index, pair]) for k, v in shown[f"physics{side}"].items()}
    arrays["true_reward"] = np.asarray(shown[f"true_reward{side}"][seed_index, pair])
    return arrays
