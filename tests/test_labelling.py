"""The labelling app through FastAPI's test client: clips, answers persisted and fsync'd,
idempotence, undo, restart, bad input, the access token; answers as B-Pref labels."""
import json

import mujoco
import numpy as np
import pytest
from fastapi.testclient import TestClient

import tasks
from hprior_jax.labelling.app import make_app
from hprior_jax.labelling.store import QueryFolder, write_queries


def _segment(model, shift: float, steps: int = 4) -> dict:
    qpos = np.repeat(mujoco.MjData(model).qpos[None], steps, axis=0)
    qpos[:, 2] = np.linspace(0, shift, steps)  # cheetah's torso pitch: the pose moves
    return {"qpos": qpos, "qvel": np.zeros((steps, model.nv))}


@pytest.fixture()
def folder(tmp_path):
    model = tasks.make("cheetah_run").mj_model
    pairs = [(_segment(model, 0.5), _segment(model, -0.5)) for _ in range(3)]
    write_queries(tmp_path / "q", "cheetah_run", 1, pairs, fps=20.0)
    return QueryFolder(tmp_path / "q")


def _client(folder, token=None):
    return TestClient(make_app(folder, token))


def test_page_next_query_and_clips(folder):
    client = _client(folder)
    page = client.get("/")
    assert page.status_code == 200 and "Which clip is better?" in page.text
    nxt = client.get("/api/next").json()
    assert nxt["query"] == {"id": "r1-q0000", "round": 1, "task": "cheetah_run",
                            "goal": "Run forward (to the right) as fast as possible.",
                            "fps": 20.0}
    assert nxt["progress"] == {"round": 1, "asked": 3, "answered": 0}
    clips = [client.get(f"/api/clip/r1-q0000/{side}") for side in (1, 2)]
    assert all(c.status_code == 200 and c.headers["content-type"] == "video/mp4" for c in clips)
    import imageio.v3 as iio

    left, right = (iio.imread(c.content, extension=".mp4") for c in clips)
    assert left.shape == right.shape and left.shape[0] == 4  # same size and speed
    assert np.abs(left[-1].astype(int) - right[-1]).mean() > 1  # the two poses differ
    # cached: served again from the folder, not rendered again
    mtime = (folder.dir / "clips" / "r1-q0000_1.mp4").stat().st_mtime_ns
    client.get("/api/clip/r1-q0000/1")
    assert (folder.dir / "clips" / "r1-q0000_1.mp4").stat().st_mtime_ns == mtime


def test_answers_persist_are_idempotent_undo_and_survive_a_restart(folder):
    client = _client(folder)
    ok = client.post("/api/answer", json={"id": "r1-q0000", "answer": "right",
                                          "labeller": "ada"})
    assert ok.status_code == 200 and ok.json()["written"] is True
    assert ok.json()["progress"] == {"round": 1, "asked": 3, "answered": 1}
    # a double click writes nothing; a different answer is refused until undone
    again = client.post("/api/answer", json={"id": "r1-q0000", "answer": "right",
                                             "labeller": "ada"})
    assert again.status_code == 200 and again.json()["written"] is False
    other = client.post("/api/answer", json={"id": "r1-q0000", "answer": "left",
                                             "labeller": "bob"})
    assert other.status_code == 409 and "undo it first" in other.json()["error"]
    lines = (folder.dir / "answers.jsonl").read_text().splitlines()
    assert len(lines) == 1 and json.loads(lines[0])["labeller"] == "ada"
    # a second browser answers the next query; undo takes back only its own last answer
    assert client.get("/api/next").json()["query"]["id"] == "r1-q0001"
    client.post("/api/answer", json={"id": "r1-q0001", "answer": "equal", "labeller": "bob"})
    assert client.post("/api/undo", json={"labeller": "ada"}).json()["undone"] == "r1-q0000"
    assert client.get("/api/next").json()["query"]["id"] == "r1-q0000"
    client.post("/api/answer", json={"id": "r1-q0000", "answer": "left", "labeller": "ada"})
    client.post("/api/answer", json={"id": "r1-q0002", "answer": "skip", "labeller": "ada"})
    # a restarted server (a new process reading the folder) has every answer
    restarted = _client(QueryFolder(folder.dir))
    assert restarted.get("/api/next").json() == {
        "query": None, "progress": {"round": 1, "asked": 3, "answered": 3}}
    labels, valid = QueryFolder(folder.dir).labels(["r1-q0000", "r1-q0001", "r1-q0002"])
    assert labels.tolist() == [0, -1, 0] and valid.tolist() == [True, True, False]


@pytest.mark.parametrize("method, url, body, status, says", [
    ("post", "/api/answer", {"id": "r9-q0000", "answer": "left", "labeller": "a"}, 404,
     "unknown query id"),
    ("post", "/api/answer", {"id": "../../etc/passwd", "answer": "left", "labeller": "a"}, 400,
     "bad query id"),
    ("post", "/api/answer", {"id": "r1-q0000", "answer": "both", "labeller": "a"}, 400,
     "choose one of left, right, equal, skip"),
    ("post", "/api/answer", {"id": "r1-q0000", "answer": "left", "labeller": "<script>"}, 400,
     "labeller"),
    ("post", "/api/answer", {"id": "r1-q0000"}, 400,
     "malformed request: the field 'answer' is missing; the field 'labeller' is missing; "
     'send a JSON object {"id": "r1-q0000", "answer": "left"'),
    ("post", "/api/answer", "not json", 400,
     "malformed request: the body is not JSON (at character 1); send a JSON object"),
    ("post", "/api/undo", '["ada"]', 400, "malformed request: the body is not a JSON object"),
    ("post", "/api/undo", {"labeller": 3}, 400,
     "malformed request: the field 'labeller': input should be a valid string; send a JSON"),
    ("post", "/api/answer", {"id": "r1-q0000", "answer": "left", "labeller": "a" * 5000}, 400,
     "labeller 'aaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaa'... (5000 characters): give a name"),
    ("get", "/api/clip/r1-q0000/3", None, 400, "segments 1 and 2"),
    ("get", "/api/clip/..%2F..%2Fqueries/1", None, 404, "no such page or API"),
    ("get", "/api/clip/r1-q0000.npz/1", None, 400, "bad query id"),
    ("get", "/api/clip/nope/1", None, 404, "unknown query id"),
])
def test_bad_requests_get_a_4xx_and_write_nothing(folder, method, url, body, status, says):
    client = _client(folder)
    kw = ({"content": body, "headers": {"content-type": "application/json"}}
          if isinstance(body, str) else {"json": body})
    r = getattr(client, method)(url, **({} if body is None else kw))
    assert r.status_code == status and says in r.json()["error"], r.text
    assert len(r.json()["error"]) < 300, r.text  # nothing a request sent is echoed whole
    assert not (folder.dir / "answers.jsonl").exists()
    assert not any((folder.dir / "clips").glob("*")) if (folder.dir / "clips").exists() else True


def test_a_token_guards_every_request(folder):
    client = _client(folder, token="s3cret")
    assert client.get("/").status_code == 403
    assert client.get("/api/next", headers={"X-Hprior-Token": "wrong"}).status_code == 403
    assert client.get("/?token=s3cret").status_code == 200
    assert client.get("/api/next", headers={"X-Hprior-Token": "s3cret"}).status_code == 200


def test_the_goal_line_is_the_tasks_own():
    from hprior_jax.labelling.goals import goal

    assert goal("drawer_open") == "Pull the drawer open."
    assert goal("toy_point") == "" and goal("no_such_task") == ""
