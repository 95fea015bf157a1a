"""The critical-event probe (benchmarks/research/lab_probe.py): where the next state depends on one
earlier action only, a trained world model's α must find that action's step.

-m slow: the world model trains for 3000 updates (minutes on a CPU). The data side is fast."""
import jax
import numpy as np
import pytest

from benchmarks.research.lab_probe import ProbeConfig, probe_episodes, run_probe


def test_probe_episodes_reveal_the_gated_action_later():
    cfg = ProbeConfig()
    obs, act, t_star = (np.asarray(x) for x in probe_episodes(jax.random.PRNGKey(3), 16, cfg))
    for o, a, t in zip(obs, act, t_star):
        assert np.flatnonzero(o[:, 0]).tolist() == [t]  # the gate, once
        assert np.flatnonzero(o[:, 1]).tolist() == [t + cfg.delay]  # the reveal, once
        assert o[t + cfg.delay, 2] == a[t, 0] and np.count_nonzero(o[:, 2]) == 1
        assert t + cfg.delay >= cfg.segment_len and t + cfg.delay < cfg.episode_len


def test_the_every_step_control_reveals_each_action_delay_steps_later():
    cfg = ProbeConfig(reveal="every_step", delay=5)
    obs, act, t_star = (np.asarray(x) for x in probe_episodes(jax.random.PRNGKey(3), 4, cfg))
    assert not obs[..., 0].any()  # no gate
    np.testing.assert_array_equal(obs[:, :5, 1:3], 0)
    np.testing.assert_array_equal(obs[:, 5:, 1], 1)
    np.testing.assert_array_equal(obs[:, 5:, 2], act[:, :-5, 0])
    np.testing.assert_array_equal(obs[np.arange(4), t_star + 5, 2], act[np.arange(4), t_star, 0])


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason=(
    "a finding, 2026-12-01 (benchmarks/results/research/probe/): the reduced-size world model "
    "after "
    "3000 updates does not learn the reveal (MSE 0.3066 vs 0.3068 predicting 0) and α puts "
    "0.005 on t* (uniform 0.02) and 0.63 on the last 8 steps. Strict: a fix makes it XPASS, "
    "which fails until this mark goes"))
def test_a_trained_world_model_credits_the_critical_step():
    """The world model must learn the reveal (error well below predicting 0) and α must put
    more mass on t* than on the 8 most recent steps together and ten times uniform's. If this
    fails, it is a finding about the world model, reported in the issue: do not weaken it."""
    out = run_probe(ProbeConfig(steps=3000), seed=0)
    assert out["reveal_mse"] < 0.5 * out["reveal_mse_predict_zero"], out
    assert out["alpha_at_t_star"]["mean"] > 10 * out["uniform"], out
    assert out["alpha_at_t_star"]["mean"] > out["alpha_last_8"]["mean"], out


@pytest.mark.slow
def test_a_world_model_that_learns_a_look_back_credits_the_step_it_reads():
    """The every-step control at delay 5 (2026-12-03, `--reveal every_step --delay 5 --steps
    1500`: reveal MSE 0.005 against 0.333 predicting 0, α on t* 0.267, the largest α of every
    segment): when the world model learns to read an earlier action, α finds that step. So
    the failing probe above is about what the world model learns, not about reading α."""
    out = run_probe(ProbeConfig(steps=1500, delay=5, reveal="every_step"), seed=0)
    assert out["reveal_mse"] < 0.1 * out["reveal_mse_predict_zero"], out
    assert out["alpha_at_t_star"]["mean"] > 10 * out["uniform"], out
    assert out["t_star_rank_1_share"] > 0.9, out


@pytest.mark.slow  # CI time (~20 s of compiling); wm.pretrain's order is tested fast
def test_probe_takes_the_pretraining_order_and_world_model_settings():
    """The probe's ablations: `order` and FIELD=VALUE settings reach the world model it
    trains (here tiny, two steps of each part: the wiring, not the finding). The same seed
    under the other order trains another world model: its reveal prediction and α differ."""
    tiny = ("wm_layers=1", "wm_embed=16", "wm_ff=32", "wm_obs_hidden=16", "wm_head_hidden=16",
            "wm_batch=4", "wm_lr=0.001")
    out = {order: run_probe(ProbeConfig(episodes=8, steps=2, order=order, settings=tiny),
                            seed=0)
           for order in ("observation_first", "joint")}
    assert out["joint"]["world_model"] == {"layers": 1, "embed": 16, "lr": 0.001}
    first, joint = out["observation_first"], out["joint"]
    assert np.isfinite(first["reveal_mse"]) and first["reveal_mse"] != joint["reveal_mse"]
    assert first["alpha_at_t_star"]["mean"] != joint["alpha_at_t_star"]["mean"]
