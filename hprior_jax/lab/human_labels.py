"""Queries from a reward-lab dataset, and the answers back as the lab's given labels.

`hprior label --from-lab DATASET` writes uniform segment pairs of the dataset's training
episodes (it must keep their physics states: `hprior reward-lab --dataset-only --physics`)
into a query folder, with `lab_pairs.json` saying which dataset and where each pair lies;
after a person answered, `hprior reward-lab --labels DIR` trains every rule once on those
answers (`given_labels`) and reports the reward quality on the held-out episodes as usual."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

import tasks
from hprior_jax.lab.config import GivenLabels
from hprior_jax.lab.dataset import Dataset, random_pairs
from hprior_jax.labelling.store import QueryFolder, write_queries

LAB_PAIRS = "lab_pairs.json"


def queries_from_lab(dataset: Path, out: Path, pairs: int = 50, seed: int = 0) -> list[str]:
    """Writes `pairs` uniform pairs of the dataset's training episodes (segments of the
    dataset's length, independent episodes and starts drawn with `seed`) into the query
    folder `out`. Returns the query ids."""
    if pairs < 1:
        raise ValueError(f"--pairs must be positive, got {pairs}")
    dataset = Path(dataset).absolute()
    data = Dataset.load(dataset)
    if data.train_physics is None:
        raise ValueError(f"{dataset} keeps no physics states to render: build the dataset "
                         f"with `hprior reward-lab --task {data.task} --dataset-only --physics`")
    episodes, length = data.train_reward.shape
    index = random_pairs(np.random.default_rng(seed), episodes, length, data.segment_len,
                         pairs)

    def segment(episode, start):
        steps = slice(start, start + data.segment_len)
        return ({k: v[episode, steps] for k, v in data.train_physics.items()}
                | {"true_reward": data.train_reward[episode, steps]})

    segments = [(segment(e1, s1), segment(e2, s2)) for e1, s1, e2, s2 in index]
    fps = 1.0 / tasks.make(data.task).control_timestep
    ids = write_queries(out, data.task, 1, segments, fps)
    Path(out, LAB_PAIRS).write_text(json.dumps(
        {"dataset": str(dataset), "task": data.task, "segment_len": data.segment_len,
         "pairs": {qid: [int(x) for x in row] for qid, row in zip(ids, index)}}, indent=1))
    return ids


def given_labels(folder: Path):
    """(the dataset's path, `GivenLabels` of the answered queries of `folder`, how many were
    left unanswered)."""
    path = Path(folder) / LAB_PAIRS
    if not path.exists():
        raise FileNotFoundError(f"{path} not found: {folder} was not written by "
                                "`hprior label --from-lab`")
    spec = json.loads(path.read_text())
    queries = QueryFolder(folder)
    answered = [q for q in spec["pairs"] if q in queries.answers()]
    if not answered:
        raise ValueError(f"no query of {folder} is answered yet: label them with "
                         f"`hprior label --dir {folder}`")
    labels, valid = queries.labels(answered)
    index = np.array([spec["pairs"][q] for q in answered], np.int32)
    return (Path(spec["dataset"]), GivenLabels(index, labels, valid),
            len(spec["pairs"]) - len(answered))
