"""`--teacher human`: a training run asks a person through the labelling page, waits, and
trains on the answers; answered as the oracle would, it is the oracle's run."""
import dataclasses
import json
import threading
import time

import httpx
import numpy as np
import pytest

from hprior_jax import presets
from hprior_jax.labelling.server import ServerOptions
from hprior_jax.labelling.teacher import AskOptions
from hprior_jax.loop import host
from hprior_jax.runs.build import build_engine, train
from hprior_jax.runs.run_dir import prepare_run_dir
from tests.ports import free_port
from tests.test_pebble_loop import SMALL

# two rounds of 10 queries per seed (steps 40 and 80), two seeds
RUN = dict(seeds=(3, 4), steps=120, eval_every=60, checkpoint_every=60, **SMALL)


def _cfg(tmp_path, name, teacher, algo="pebble"):
    cfg = presets.train_preset("toy_point", algo, "smoke", out=str(tmp_path / name), **RUN)
    cfg = dataclasses.replace(cfg, pebble=dataclasses.replace(cfg.pebble, max_feedback=20))
    return presets.with_teacher(cfg, teacher)


class Answerer(threading.Thread):
    """Answers the page's next query as the oracle would (the segment with the larger true
    return; its label 1 is "right"), through HTTP, until `stop` or `limit` answers."""

    def __init__(self, run_dir, port, limit=None, then=None):
        super().__init__(daemon=True)
        self.run_dir, self.url, self.limit, self.then = run_dir, f"http://127.0.0.1:{port}", limit, then
        self.given, self.done = 0, threading.Event()

    def run(self):
        while not self.done.is_set() and (self.limit is None or self.given < self.limit):
            try:
                query = httpx.get(f"{self.url}/api/next", timeout=5).json()["query"]
            except httpx.TransportError:  # the run has not started its server yet
                query = None
            if query is None:
                time.sleep(0.05)
                continue
            with np.load(self.run_dir / "labels" / "segments" / f"{query['id']}.npz") as z:
                right = z["true_reward2"].sum() > z["true_reward1"].sum()
            r = httpx.post(f"{self.url}/api/answer", timeout=5, json={
                "id": query["id"], "answer": "right" if right else "left", "labeller": "test"})
            assert r.status_code == 200, r.text
            self.given += 1
        if self.then is not None:
            self.then()


def _train(cfg, port, answerer=None, resume=False, timeout_s=60.0, interrupt=None):
    if answerer is not None:
        answerer.start()
    try:
        return train(cfg, prepare_run_dir(cfg) if not resume else cfg.out, resume=resume,
                        progress=False, interrupt=interrupt, labelling=AskOptions(
                            ServerOptions(port=port), timeout_s=timeout_s, poll_s=0.05))
    finally:
        if answerer is not None:
            answerer.done.set()
            answerer.join(10)


def _metrics(run_dir):
    out = []
    for line in (run_dir / "metrics.jsonl").read_text().splitlines():
        rec = json.loads(line)
        out.append({k: v for k, v in rec.items() if not k.startswith("perf/")})
    return out


def _assert_same_run(a, b):
    ma, mb = _metrics(a), _metrics(b)
    ma, mb = [m for m in ma if len(m) > 2], [m for m in mb if len(m) > 2]
    assert len(ma) == len(mb)
    for x, y in zip(ma, mb):
        assert x.keys() == y.keys()
        for k in x:
            np.testing.assert_allclose(x[k], y[k], rtol=1e-5, atol=1e-6, err_msg=k)
    assert (a / "eval.csv").read_text() == (b / "eval.csv").read_text()


class _Stop:
    requested = False


@pytest.mark.slow  # 115 s: two PEBBLE runs
def test_a_person_answering_as_the_oracle_trains_the_oracles_run(tmp_path):
    oracle = _cfg(tmp_path, "oracle", "oracle")
    train(oracle, prepare_run_dir(oracle), progress=False)

    human = _cfg(tmp_path, "human", "human")
    run_dir = tmp_path / "human"
    port = free_port()
    assert build_engine(human).method.asks_person
    # nobody answers: after the timeout the run stops at the first round, checkpointed there
    with pytest.raises(host.Interrupted, match="no answer for 1 s") as stopped:
        _train(human, port, timeout_s=1.0)
    assert stopped.value.step == 40
    # resumed, it asks the same queries; a person answers 5, then stops the run (Ctrl-C)
    stop = _Stop()
    with pytest.raises(host.Interrupted, match="5 of 20 given, all kept"):
        _train(human, port, Answerer(run_dir, port, limit=5,
                                     then=lambda: setattr(stop, "requested", True)),
               resume=True, interrupt=stop)
    # resumed again, every answer is kept and only the rest are asked
    _train(human, port, Answerer(run_dir, port), resume=True)

    records = [json.loads(l) for l in (run_dir / "labels" / "answers.jsonl").read_text().split("\n")
               if l]
    assert len(records) == 40 and len({r["id"] for r in records}) == 40  # 2 rounds x 2 seeds x 10
    queries = [json.loads(l) for l in (run_dir / "labels" / "queries.jsonl").read_text().split("\n")
               if l]
    assert len(queries) == 40 and {q["seed"] for q in queries} == {3, 4}
    _assert_same_run(tmp_path / "oracle", run_dir)
    waits = [json.loads(l).get("perf/label_wait_s") for l in
             (run_dir / "metrics.jsonl").read_text().splitlines()]
    assert sum(1 for w in waits if w) == 2 * 2  # per seed, after each round's chunk
    last_round = [m for m in _metrics(run_dir) if "feedback/mistakes" in m][-1]
    assert last_round["feedback/mistakes"] == 0 and last_round["feedback/labeled"] == 10


@pytest.mark.slow  # CI time: 50-85 s each; pebble is the fast suite's
@pytest.mark.parametrize("algo", ["surf", "mrn", "rune", "rvar", "bisim", "prior"])
def test_every_pebble_family_method_asks_a_person_as_its_teacher(tmp_path, algo):
    oracle = _cfg(tmp_path, "oracle", "oracle", algo)
    train(oracle, prepare_run_dir(oracle), progress=False)
    port = free_port()
    _train(_cfg(tmp_path, "human", "human", algo), port, Answerer(tmp_path / "human", port))
    _assert_same_run(tmp_path / "oracle", tmp_path / "human")


def test_a_persons_answers_become_b_pref_labels(tmp_path):
    """equal -> -1, can't tell -> not valid; the pairs beyond the round's count (the last
    round clipped to the budget) are not asked and not valid."""
    from hprior_jax.labelling.teacher import HumanTeacher

    task = build_engine(_cfg(tmp_path, "x", "human")).task
    shown = {f"physics{s}": {"qpos": np.zeros((1, 3, 4, 1), np.float32)} for s in (1, 2)}
    shown |= {"true_reward1": np.ones((1, 3, 4), np.float32),
              "true_reward2": np.zeros((1, 3, 4), np.float32)}
    teacher = HumanTeacher(tmp_path / "labels", task, [9],
                           AskOptions(ServerOptions(port=0), timeout_s=30, poll_s=0.02))
    answers = iter(["equal", "skip"])

    def answer_when_asked():
        while len(teacher.folder.queries()) < 2:
            time.sleep(0.02)
        for q in teacher.folder.queries():
            teacher.folder.answer(q.id, next(answers), "test")

    threading.Thread(target=answer_when_asked, daemon=True).start()
    try:
        labels, valid = teacher.ask(1, 40, shown, count=2)
    finally:
        teacher.close()
    np.testing.assert_array_equal(labels, [[-1, 0, 0]])
    np.testing.assert_array_equal(valid, [[True, False, False]])
