"""The Python entry points: train with callbacks (one stops the run, which resumes), an env
a notebook steps and renders, a policy evaluated."""
import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

import hprior_jax
from hprior_jax import cli, dir_lock
from hprior_jax.agents.sac import SACConfig
from hprior_jax.config import RunConfig
from hprior_jax.runs.run_dir import RunDirError, load_run_config
from tests.test_life_cycle import _rows

ROOT = Path(__file__).resolve().parent.parent

TOY = dict(task="toy_point", steps=120, num_seed_steps=20, chunk_steps=20, eval_every=40,
           checkpoint_every=120, num_eval_episodes=2, seeds=(3, 4),
           sac=SACConfig(hidden_dim=16, hidden_depth=1, batch_size=8))


def test_a_callback_sees_every_evaluation_and_can_stop_the_run_which_resumes(tmp_path):
    seen = []

    def stop_at_80(evaluation: hprior_jax.Evaluation) -> bool:
        seen.append(evaluation)
        return evaluation.step >= 80

    run_dir = hprior_jax.train(RunConfig(**TOY, out=str(tmp_path / "run")), callbacks=(
        stop_at_80,), progress=False)
    assert [e.step for e in seen] == [40, 80]
    assert seen[0].seeds == (3, 4) and seen[0].returns.shape == (2,)
    assert seen[0].successes.shape == (2,)  # the toy task reports success
    assert np.all(np.isfinite(seen[1].returns))
    steps = sorted(int(p.name) for p in (run_dir / "checkpoints").iterdir() if p.name.isdigit())
    assert steps == [80]  # stopped there, checkpointed although checkpoint_every is 120
    assert [r[0] for r in _rows(run_dir / "eval.csv")[1:]] == ["40", "40", "80", "80"]
    assert cli.main(["train", "--resume", str(run_dir), "--no-progress"]) == 0  # to the budget
    assert load_run_config(run_dir).steps == 120
    assert _rows(run_dir / "eval.csv")[-1][0] == "120"


def test_the_api_locks_its_run_records_provenance_and_resumes_in_python_words(tmp_path):
    """`hprior_jax.train` keeps the run directory's guarantees: locked while it trains (another
    real process cannot take it), `run_info` in config.json; running the cell again is
    refused in Python's words, and `resume=True` continues the run."""
    cfg = RunConfig(**TOY, out=str(tmp_path / "run"))
    taken = []

    def another_process_takes_the_lock(evaluation) -> bool:
        if not taken:
            taken.append(subprocess.run(
                [sys.executable, "-c", "import sys; from hprior_jax import dir_lock; "
                 "dir_lock.hold(sys.argv[1])", cfg.out], cwd=ROOT, capture_output=True,
                text=True, env={**os.environ, "PYTHONPATH": str(ROOT)}))
        return evaluation.step >= 80

    run_dir = hprior_jax.train(cfg, callbacks=(another_process_takes_the_lock,),
                               progress=False)
    assert taken[0].returncode != 0 and f"is in use by PID {os.getpid()}" in taken[0].stderr
    info = json.loads((run_dir / "config.json").read_text())["run_info"]
    assert info["versions"]["hprior_jax"] == hprior_jax.__version__ and info["command"]
    with pytest.raises(RunDirError) as refused:
        hprior_jax.train(cfg)
    assert "hprior_jax.train(config, resume=True)" in str(refused.value)
    assert "--" not in str(refused.value) and "config.out" in str(refused.value)
    wider = dataclasses.replace(cfg, sac=SACConfig(hidden_dim=32, hidden_depth=1, batch_size=8))
    with pytest.raises(ValueError, match=r"resume=True continues .* config.sac.hidden_dim "
                                         r"\(16 -> 32\)"):
        hprior_jax.train(wider, resume=True)
    assert hprior_jax.train(cfg, resume=True, progress=False) == run_dir
    assert _rows(run_dir / "eval.csv")[-1][0] == "120"
    dir_lock.hold(run_dir).release()  # given back when training ended


def test_an_env_a_notebook_steps_and_renders():
    env = hprior_jax.make_env("cheetah_run", num_envs=2, seed=1)
    obs = env.reset()
    assert obs.shape == (2, env.task.obs_size)
    total = np.zeros(2)
    for _ in range(3):
        obs, reward, done, info = env.step(np.zeros((2, env.task.action_size)))
        total += reward
    assert obs.shape == (2, env.task.obs_size) and not done.any()
    np.testing.assert_allclose(info["episode_return"], total, rtol=1e-5)
    frame = env.render(index=1, width=64, height=48)
    assert frame.shape == (48, 64, 3) and frame.dtype == np.uint8
    assert frame.std() > 5  # a scene, not a blank frame


def test_evaluate_policy_runs_whole_episodes_of_a_policy():
    toward_origin = lambda obs: -jnp.clip(obs[:, :1], -1.0, 1.0)
    returns, successes = hprior_jax.evaluate_policy(toward_origin, "toy_point", episodes=3)
    still, _ = hprior_jax.evaluate_policy(lambda obs: jnp.zeros((obs.shape[0], 1)),
                                          "toy_point", episodes=3)
    assert returns.shape == successes.shape == (3,)
    assert not np.allclose(returns, still)  # the policy's actions reach the episodes


def test_evaluate_policy_calls_a_numpy_policy_at_every_step():
    """A NumPy policy (it cannot be traced) gives the returns of the same policy in JAX; one
    that keeps state between calls is called once per step, on real observations, instead of
    being frozen into one constant action by tracing."""
    numpy_policy = lambda obs: np.tanh(-3.0 * obs[:, :1])
    jax_policy = lambda obs: jnp.tanh(-3.0 * obs[:, :1])
    on_host = hprior_jax.evaluate_policy(numpy_policy, "toy_point", episodes=3)
    compiled = hprior_jax.evaluate_policy(jax_policy, "toy_point", episodes=3)
    np.testing.assert_allclose(on_host[0], compiled[0], rtol=1e-5)
    np.testing.assert_array_equal(on_host[1], compiled[1])
    seen = []

    def alternating(obs):  # state between calls: +1, -1, +1, ...
        seen.append(obs)
        return np.full((len(obs), 1), (-1.0) ** len(seen))

    hprior_jax.evaluate_policy(alternating, "toy_point", episodes=2)
    real = [o for o in seen if isinstance(o, np.ndarray)]
    assert len(real) == 20 and all(o.shape == (2, 2) for o in real)  # 20 steps an episode


def test_a_policy_or_action_of_the_wrong_shape_is_named():
    with pytest.raises(ValueError, match=r"expected actions of shape \(3, 1\) \(3 environments "
                                         r"of toy_point, 1 action dimensions\), got \(3, 6\)"):
        hprior_jax.evaluate_policy(lambda obs: jnp.zeros((obs.shape[0], 6)), "toy_point",
                                   episodes=3)
    with pytest.raises(ValueError, match=r"the policy fails on observations of toy_point "
                                         r"\(shape \(3, 2\)\): TypeError"):
        hprior_jax.evaluate_policy(lambda obs: obs @ jnp.ones((17, 6)), "toy_point", episodes=3)
    env = hprior_jax.make_env("toy_point", num_envs=2)
    assert (env.num_envs, env.obs_size, env.action_size) == (2, 2, 1)
    env.reset()
    with pytest.raises(ValueError, match=r"expected actions of shape \(2, 1\).*got \(2,\)"):
        env.step(np.zeros(2))
    obs, *_ = env.step(np.zeros((2, 1)))
    assert obs.shape == (2, 2)


@pytest.mark.slow  # cheetah's programs: ~100 s on 2 cores
def test_capture_video_writes_each_seeds_episode_at_every_kth_evaluation(tmp_path):
    """On cheetah (the toy task has no scene): every 2nd evaluation, one short MP4 a seed;
    `hprior eval --video` of the same step writes its own files beside them."""
    import imageio.v3 as iio

    out = tmp_path / "run"
    assert cli.main(["train", "--task", "cheetah_run", "--preset", "smoke", "--algo", "sac",
                     "--steps", "60", "--num-seed-steps", "20", "--chunk-steps", "20",
                     "--eval-every", "20", "--num-eval-episodes", "1", "--seeds", "1", "2",
                     "--sac.hidden-dim", "16", "--sac.hidden-depth", "1",
                     "--sac.batch-size", "8", "--capture-video", "2", "--video-steps", "10",
                     "--out", str(out), "--no-progress"]) == 0
    videos = sorted(p.name for p in (out / "videos").iterdir())
    assert videos == ["step20_seed1.mp4", "step20_seed2.mp4",
                      "step60_seed1.mp4", "step60_seed2.mp4"]
    assert iio.imread(out / "videos" / videos[0]).shape[0] == 11  # the start and 10 steps
    captured = {p.name: p.read_bytes() for p in (out / "videos").iterdir()}
    # hprior eval --video of the same step: files of its own beside training's, none replaced
    assert cli.main(["eval", "--run", str(out), "--episodes", "1", "--video"]) == 0
    assert sorted(p.name for p in (out / "videos").iterdir()) == sorted(
        [*videos, "eval_step60_seed1.mp4", "eval_step60_seed2.mp4"])
    assert all((out / "videos" / name).read_bytes() == data for name, data in captured.items())
