"""The PyTorch world-model reference of benchmarks/updates/world_model_update.py computes our
update.

Runs only where the `.[bench]` extra (torch) is installed; the benchmark repeats the loss and
gradient-norm check at the sizes it times."""
import dataclasses

import jax
import numpy as np
import optax
import pytest

torch = pytest.importorskip("torch")

from benchmarks.updates._torch_world_model import TorchDynamicsUpdate  # noqa: E402
from hprior_jax.prior import world_model as wm  # noqa: E402

CFG = wm.WorldModelConfig(obs_size=5, act_size=2, obs_hidden=(16, 16), embed_dim=16, num_heads=2,
                          head_dim=4, num_layers=2, ff_dim=32, head_hidden=(16, 16),
                          segment_len=6, memory_len=6, batch_size=3)


def _data():
    rng = np.random.default_rng(0)
    return (rng.standard_normal((3, 6, 5)).astype(np.float32),
            rng.uniform(-1, 1, (3, 6, 2)).astype(np.float32))


def _jax_loss(state, obs, act, cfg):
    (loss, _), grads = jax.value_and_grad(wm.dynamics_loss, has_aux=True)(
        state.params.dyn, state.params.obs, obs, act, None, cfg, True)
    return float(loss), float(optax.global_norm(grads))


def test_same_loss_and_gradient_norm():
    obs, act = _data()
    state = wm.init(jax.random.key(1), CFG)
    ref = TorchDynamicsUpdate(state, CFG)
    loss, norm = _jax_loss(state, obs, act, CFG)
    with torch.no_grad():
        assert float(ref.loss(torch.from_numpy(obs), torch.from_numpy(act), False)) == \
            pytest.approx(loss, rel=1e-5)
    assert ref.grad_norm(torch.from_numpy(obs), torch.from_numpy(act)) == pytest.approx(norm, rel=1e-5)


def test_same_loss_after_one_optimizer_step():
    cfg = dataclasses.replace(CFG, dropout=0.0)  # the two sides draw different dropout masks
    obs, act = _data()
    state = wm.init(jax.random.key(1), cfg)
    ref = TorchDynamicsUpdate(state, cfg)
    state, _ = wm.update_dynamics(state, obs, act, jax.random.key(2), cfg)
    ref.step(torch.from_numpy(obs), torch.from_numpy(act))
    with torch.no_grad():
        after = float(ref.loss(torch.from_numpy(obs), torch.from_numpy(act), False))
    assert after == pytest.approx(_jax_loss(state, obs, act, cfg)[0], rel=1e-5)
    assert after < _jax_loss(wm.init(jax.random.key(1), cfg), obs, act, cfg)[0]
