"""A person's labels for the reward lab: queries written from a dataset's training episodes,
answered, and trained on by every rule (`hprior label --from-lab`, `reward-lab --labels`)."""
import json

import numpy as np
import pytest

from hprior_jax.lab.dataset import random_pairs
from hprior_jax.lab.config import GivenLabels
from hprior_jax.lab.learn import Lab
from hprior_jax.lab.sweep import score
from tests.test_reward_lab import T, confounded, quiet, tiny


def _oracle_pairs(data, n, seed=0):
    e, length = data.train_reward.shape
    index = random_pairs(np.random.default_rng(seed), e, length, T, n)
    ret = lambda ep, st: np.array([data.train_reward[a, b:b + T].sum() for a, b in zip(ep, st)])
    r1, r2 = ret(index[:, 0], index[:, 1]), ret(index[:, 2], index[:, 3])
    keep = r1 != r2
    return index[keep], (r2 > r1)[keep].astype(np.int32)


def test_every_rule_learns_from_the_given_labels_and_only_from_them():
    """Answered as the oracle, the learned reward ranks held-out pairs well; answered the
    other way round, it ranks them the other way round; "can't tell" answers are not
    stored."""
    data = confounded()
    index, oracle = _oracle_pairs(data, 60)
    cfg = tiny(rules=("pebble",), credits=("none",), seeds=(0, 1), budgets=(len(oracle),),
               one_shot=True, world_model=None)
    accuracy = {}
    for name, labels in (("oracle", oracle), ("inverted", 1 - oracle)):
        valid = np.ones(len(labels), bool)
        valid[:5] = name != "oracle"  # the oracle run skips 5
        rows = score(Lab(cfg, data, GivenLabels(index, labels, valid)).run(**quiet), data)
        assert {r["labels"] for r in rows} == {int(valid.sum())}
        accuracy[name] = np.mean([r["heldout_accuracy"] for r in rows])
    assert accuracy["oracle"] > 0.7 and accuracy["inverted"] < 0.3, accuracy
    with pytest.raises(ValueError, match="one_shot=True"):
        Lab(tiny(rules=("pebble",), credits=("none",), world_model=None), data,
            GivenLabels(index, oracle, np.ones(len(oracle), bool)))


def test_label_a_lab_dataset_then_train_the_lab_on_the_answers(tmp_path, monkeypatch):
    """End to end through the CLI on the toy task: a dataset built with physics states
    (aligned with its observations), `hprior label --from-lab` writes its pairs, a person
    answers (here as the oracle, two left unanswered), `hprior reward-lab --labels` trains on
    the answered ones."""
    from hprior_jax import cli
    from hprior_jax.lab.dataset import Dataset
    from hprior_jax.labelling.store import QueryFolder

    monkeypatch.setenv("HPRIOR_LAB_CACHE", str(tmp_path / "cache"))
    lab = ["reward-lab", "--task", "toy_point", "--preset", "smoke", "--dataset-steps", "200"]
    assert cli.main(lab + ["--physics", "--dataset-only"]) == 0
    (path,) = (tmp_path / "cache").glob("toy_point_*_physics_code*.npz")
    data = Dataset.load(path)
    # the toy task's "qpos" is its position, which is obs[0]: the state behind each obs
    np.testing.assert_array_equal(data.train_physics["qpos"][..., 0], data.train_obs[..., 0])

    queries = tmp_path / "queries"
    assert cli.main(["label", "--dir", str(queries), "--from-lab", str(path), "--pairs", "12",
                     "--build-only"]) == 0
    folder = QueryFolder(queries)
    spec = json.loads((queries / "lab_pairs.json").read_text())
    assert spec["dataset"] == str(path) and len(spec["pairs"]) == 12
    for q in folder.queries()[:10]:
        seg = folder.segment_arrays(q.id)
        e1, s1, e2, s2 = spec["pairs"][q.id]
        np.testing.assert_array_equal(seg["true_reward1"], data.train_reward[e1, s1:s1 + data.segment_len])
        right = seg["true_reward2"].sum() > seg["true_reward1"].sum()
        folder.answer(q.id, "right" if right else "left", "test")

    out = tmp_path / "lab"
    assert cli.main(lab + ["--labels", str(queries), "--seeds", "2", "--rules", "pebble",
                           "--out", str(out)]) == 0
    results = (out / "results.csv").read_text().splitlines()
    assert len(results) == 1 + 2 and all(",pebble,10," in row for row in results[1:])
