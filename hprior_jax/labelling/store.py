"""A query folder: what is asked (written by a producer) and what was answered (by the app).

    DIR/queries.jsonl      one query per line: {"id", "round", "task", "fps"[, "seed"]}
    DIR/segments/<id>.npz  the two segments' physics states (qpos1, qpos2, ... [T, ...]),
                           and where a run wrote them, their true rewards (true_reward1, 2)
    DIR/clips/<id>_<1|2>.mp4   rendered on first request, then served from here
    DIR/answers.jsonl      one record per answer or undo, appended and fsync'd

Answers are never rewritten: the current answer of a query is its last record unless an undo
followed it, so a restart replays the file and loses nothing, and two browsers append to the
same file under one lock (a process-wide lock: one server process per folder)."""
from __future__ import annotations

import json
import os
import re
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ANSWERS = ("left", "right", "equal", "skip")
# B-Pref labels (hprior_jax/pbrl/teacher.py): 0 = segment 1 preferred, 1 = segment 2,
# -1 = equally preferable; a skipped query is dropped (valid = False)
LABEL_OF = {"left": 0, "right": 1, "equal": -1, "skip": 0}
ID_PATTERN = re.compile(r"^[A-Za-z0-9_-]{1,64}$")  # no path separators, dots or spaces


class LabelError(ValueError):
    """A request the folder refuses: `status` is the HTTP status the app answers with."""

    def __init__(self, message: str, status: int = 400):
        super().__init__(message)
        self.status = status


@dataclass(frozen=True)
class Query:
    id: str
    round: int
    task: str
    fps: float
    seed: int | None = None  # the training seed whose replay buffer a run's query comes from


def query_id(round_: int, index: int, seed: int | None = None) -> str:
    return f"r{round_}-" + ("" if seed is None else f"s{seed}-") + f"q{index:04d}"


def pair_arrays(one: dict, two: dict) -> dict:
    """A query's two segments as stored: each field named with its side (qpos1, qpos2)."""
    return {f"{k}1": v for k, v in one.items()} | {f"{k}2": v for k, v in two.items()}


def write_queries(folder: Path, task: str, round_: int, segments: list[tuple[dict, dict]],
                  fps: float, first_index: int = 0, seed: int | None = None) -> list[str]:
    """Adds one round of queries: `segments[i]` = (states of segment 1, of segment 2), each
    {field: array [T, ...]} (`hprior_jax.render.FIELDS`, and any extras such as
    true_reward). Returns their ids."""
    folder = Path(folder)
    (folder / "segments").mkdir(parents=True, exist_ok=True)
    ids = []
    for i, (one, two) in enumerate(segments, start=first_index):
        qid = query_id(round_, i, seed)
        arrays = pair_arrays(one, two)
        path = folder / "segments" / f"{qid}.npz"
        np.savez(path.with_suffix(".tmp.npz"), **arrays)
        os.replace(path.with_suffix(".tmp.npz"), path)
        ids.append(qid)
    # the queries become visible (to a server reading the folder) only once their segments are
    with open(folder / "queries.jsonl", "a") as f:
        for qid in ids:
            record = {"id": qid, "round": round_, "task": task, "fps": fps}
            f.write(json.dumps(record | ({} if seed is None else {"seed": seed})) + "\n")
        f.flush()
        os.fsync(f.fileno())
    return ids


class QueryFolder:
    def __init__(self, folder: Path):
        self.dir = Path(folder)
        if not (self.dir / "queries.jsonl").exists():
            raise FileNotFoundError(f"{self.dir}/queries.jsonl not found: {self.dir} is not a "
                                    "query folder (make one with `hprior label --from-run`)")
        self._lock = threading.Lock()
        self._answers_path = self.dir / "answers.jsonl"

    # -- what is asked ------------------------------------------------------------------
    def queries(self) -> list[Query]:
        lines = (self.dir / "queries.jsonl").read_text().splitlines()
        return [Query(**json.loads(line)) for line in lines if line.strip()]

    def segment_arrays(self, qid: str) -> dict[str, np.ndarray]:
        """Everything stored of query `qid`'s two segments ({name + side: array})."""
        self.query(qid)
        with np.load(self.dir / "segments" / f"{qid}.npz") as z:
            return {k: z[k] for k in z.files}

    def query(self, qid: str) -> Query:
        if not isinstance(qid, str) or not ID_PATTERN.match(qid):
            raise LabelError(f"bad query id {qid!r}: ids are letters, digits, '-' and '_'")
        found = next((q for q in self.queries() if q.id == qid), None)
        if found is None:
            raise LabelError(f"unknown query id {qid!r}", status=404)
        return found

    def segment_states(self, qid: str, side: int) -> dict[str, np.ndarray]:
        return {k[:-1]: v for k, v in self.segment_arrays(qid).items() if k.endswith(str(side))}

    # -- what was answered --------------------------------------------------------------
    def _records(self) -> list[dict]:
        if not self._answers_path.exists():
            return []
        out = []
        for line in self._answers_path.read_text().splitlines():
            try:
                out.append(json.loads(line))
            except json.JSONDecodeError:  # a torn last line from a killed server
                continue
        return out

    def answers(self) -> dict[str, dict]:
        """{query id: its current answer record}, replaying answers and undos in order."""
        current: dict[str, dict] = {}
        for rec in self._records():
            if rec.get("undo"):
                current.pop(rec["id"], None)
            else:
                current[rec["id"]] = rec
        return current

    def answer(self, qid: str, answer: str, labeller: str) -> bool:
        """Records an answer; True if written, False for a repeat of the current answer (a
        double click or a retried request). A different answer to an answered query is
        refused: undo it first."""
        self.query(qid)
        if answer not in ANSWERS:
            raise LabelError(f"answer {answer!r}: choose one of {', '.join(ANSWERS)}")
        labeller = _labeller(labeller)
        with self._lock:
            previous = self.answers().get(qid)
            if previous is not None:
                if previous["answer"] == answer:
                    return False
                raise LabelError(f"query {qid} is already answered {previous['answer']!r} "
                                 f"(by {previous['labeller']}); undo it first", status=409)
            self._append({"id": qid, "answer": answer, "labeller": labeller,
                          "time": time.time()})
        return True

    def undo_last(self, labeller: str) -> str | None:
        """Undoes `labeller`'s most recent current answer; returns its query id (None if
        they have none)."""
        labeller = _labeller(labeller)
        with self._lock:
            current = self.answers()
            mine = [r for r in current.values() if r["labeller"] == labeller]
            if not mine:
                return None
            last = max(mine, key=lambda r: r["time"])
            self._append({"id": last["id"], "undo": True, "labeller": labeller,
                          "time": time.time()})
            return last["id"]

    def _append(self, record: dict) -> None:
        # one write of a whole line, then fsync: the page hears "saved" only after this
        with open(self._answers_path, "a") as f:
            f.write(json.dumps(record) + "\n")
            f.flush()
            os.fsync(f.fileno())

    def next_query(self) -> Query | None:
        done = self.answers()
        return next((q for q in self.queries() if q.id not in done), None)

    def progress(self, round_: int | None = None) -> dict:
        """Answered / asked, of one round (default: the latest)."""
        queries = self.queries()
        if round_ is None:
            round_ = max((q.round for q in queries), default=0)
        asked = [q.id for q in queries if q.round == round_]
        done = self.answers()
        return {"round": round_, "asked": len(asked),
                "answered": sum(q in done for q in asked)}

    def labels(self, ids: list[str]) -> tuple[np.ndarray, np.ndarray]:
        """B-Pref (labels int32 [N], valid bool [N]) of `ids`; every one must be answered."""
        done = self.answers()
        missing = [q for q in ids if q not in done]
        if missing:
            raise LabelError(f"{len(missing)} queries are not answered yet: {missing[:3]}...")
        answers = [done[q]["answer"] for q in ids]
        return (np.array([LABEL_OF[a] for a in answers], np.int32),
                np.array([a != "skip" for a in answers]))


def _labeller(name) -> str:
    if not isinstance(name, str):
        raise LabelError(f"the labeller is a {type(name).__name__}: give a name of 1-64 "
                         "letters, digits, ' .@-_'")
    if not re.fullmatch(r"[\w .@-]{1,64}", name):
        shown = repr(name) if len(name) <= 40 else f"{name[:40]!r}... ({len(name)} characters)"
        raise LabelError(f"labeller {shown}: give a name of 1-64 letters, digits, ' .@-_'")
    return name
