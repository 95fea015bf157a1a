"""Assertions shared by the loop tests."""
import jax
import numpy as np

from hprior_jax.networks.reward_ensemble import mean_reward


def assert_buffer_holds_learned_reward(rs, reward_cfg, lane: int = 0) -> None:
    """Every stored transition of seed `lane` carries r̂(s, a) of the current reward model
    (rows relabelled at the last round and rows stored since alike), not the true reward."""
    size = int(np.asarray(rs.replay.size)[lane])
    params = jax.tree.map(lambda x: x[lane], rs.method.reward)
    stored = np.asarray(rs.replay.reward[lane, :size])
    expect = mean_reward(params, rs.replay.obs[lane, :size], rs.replay.action[lane, :size],
                         reward_cfg)
    np.testing.assert_allclose(stored, np.asarray(expect), rtol=2e-5, atol=2e-6)
    assert not np.allclose(stored, np.asarray(rs.replay.true_reward[lane, :size]))
