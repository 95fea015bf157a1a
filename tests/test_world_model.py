"""PRIOR's world model (hprior_jax.prior.world_model) and the Transformer-XL it runs on."""
import hprior_jax  # noqa: F401

import dataclasses
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hprior_jax.networks import transformer_xl as txl
from hprior_jax.prior import world_model as wm
from tests.xla_opt import AS_RUNS

DS, DA, T = 3, 2, 6


def _cfg(**kw):
    base = dict(obs_size=DS, act_size=DA, latent_dim=4, obs_hidden=(32,), embed_dim=16, num_heads=2,
                head_dim=8, num_layers=1, ff_dim=32, head_hidden=(32,), segment_len=T, memory_len=T,
                batch_size=8, obs_lr=3e-3, dyn_lr=3e-3, dropout=0.0)
    return wm.WorldModelConfig(**{**base, **kw})


CFG = _cfg()


# ---------------------------------------------------------------- config
def test_the_world_models_sizes_are_written_once():
    """PRIOR's options default to the world model's defaults, and its transformer's sizes to
    TransformerXLConfig's: the paper's sizes (TWM's) have one source."""
    from hprior_jax.methods.prior import PriorConfig

    made = PriorConfig().world_model(17, 6, segment_len=50)
    assert made == wm.WorldModelConfig(17, 6, segment_len=50, memory_len=50)
    assert (made.embed_dim, made.num_heads, made.head_dim, made.num_layers, made.ff_dim,
            made.latent_dim, made.obs_hidden, made.head_hidden) == (
        256, 4, 64, 10, 1024, 32, (512, 512), (512, 512, 512, 512))
    net, default = made.transformer(), txl.TransformerXLConfig()
    for size in ("embed_dim", "num_heads", "head_dim", "num_layers", "ff_dim", "dropout"):
        assert getattr(net, size) == getattr(default, size), size


def test_config_rejects_memory_shorter_than_segment():
    with pytest.raises(ValueError, match="memory_len"):
        _cfg(segment_len=10, memory_len=8)
    cfg = _cfg(segment_len=10, memory_len=9)  # the last step just sees the first
    tc = cfg.transformer()
    mask = np.asarray(txl.attention_mask(20, 0, tc.window))
    assert mask[-1].all()  # last action token sees every token of the segment
    assert tc.mem_len >= 2 * (10 - 1)  # the autoregressive procedure's memory fits
    with pytest.raises(ValueError, match="obs_size"):
        _cfg(obs_size=0)
    with pytest.raises(ValueError, match="mem_len"):
        txl.TransformerXLConfig(mem_len=-1)


# ---------------------------------------------------------------- Transformer-XL pieces
def test_rel_shift_aligns_relative_distances():
    """Column p of the input holds distance Tk-1-p; output [i, j] must hold distance M + i - j."""
    tq, tk = 4, 7
    m = tk - tq
    x = np.random.default_rng(0).normal(size=(2, 3, tq, tk)).astype(np.float32)
    y = np.asarray(txl.rel_shift(jnp.asarray(x)))
    for i in range(tq):
        for j in range(m + i + 1):  # causal entries
            dist = m + i - j
            np.testing.assert_array_equal(y[..., i, j], x[..., i, tk - 1 - dist])


def test_attention_mask_causal_window_and_key_mask():
    mask = np.asarray(txl.attention_mask(3, 2, window=2, key_mask=jnp.array([False, True, True, True, False])))
    # queries sit at positions 2, 3, 4; keys 0..4; key 0 invalid, key 4 invalid but is query 2's self
    want = np.array([[0, 1, 1, 0, 0],
                     [0, 1, 1, 1, 0],
                     [0, 0, 1, 1, 1]], bool)
    np.testing.assert_array_equal(mask, want)


def test_pre_ln_transformer_xl_memory_equals_one_pass():
    """Feeding 8 tokens as 2 chunks of 4 with XL memory = one causal pass (outputs, and the
    attention over the keys each chunk sees; window 5 also cuts into the memory). Pre-LN variant
    (the post-LN one TWM uses is covered by the autoregressive-credit test); mem_len 0 keeps no
    memory."""
    c = txl.TransformerXLConfig(embed_dim=8, num_heads=2, head_dim=4, num_layers=2, ff_dim=16,
                                mem_len=4, window=5, norm_first=True)
    net = txl.TransformerXL(c)
    x = jnp.asarray(np.random.default_rng(1).normal(size=(2, 8, 8)).astype(np.float32))
    params = jax.jit(net.init)(jax.random.key(0), x[:, :4])
    apply = jax.jit(net.apply)
    out, mems, attn = apply(params, x)
    assert mems.shape == (2, 2, 4, 8) and attn.shape == (2, 2, 2, 8, 8)
    o1, mem, a1 = apply(params, x[:, :4])
    o2, mem2, a2 = apply(params, x[:, 4:], mem)
    np.testing.assert_allclose(np.concatenate([o1, o2], 1), out, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(a1, attn[..., :4, :4], rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(a2, attn[..., 4:, :], rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(mem2, mems, rtol=1e-5, atol=1e-6)  # memory = last 4 layer inputs
    a = np.asarray(attn)
    assert np.all(a[..., 7, :2] == 0) and np.all(a[..., 7, 2:] > 0)  # window of 5 tokens
    none = txl.TransformerXL(dataclasses.replace(c, mem_len=0))
    assert jax.eval_shape(none.apply, params, x[:, :4])[1].shape == (2, 2, 0, 8)
    np.testing.assert_array_equal(txl.new_mem_mask(None, 2, 3, 4, 0), np.zeros((2, 0), bool))


def test_unrolled_layers_compute_the_same_and_count_every_layer():
    """`unroll_layers` changes only the loop structure: same outputs from the same params, and
    XLA's cost analysis (which counts a loop body once) then sees all layers."""
    from benchmarks._timing import xla_gflop

    c = txl.TransformerXLConfig(embed_dim=8, num_heads=2, head_dim=4, num_layers=3, ff_dim=16,
                                mem_len=0)
    x = jnp.asarray(np.random.default_rng(2).normal(size=(2, 6, 8)).astype(np.float32))
    params = txl.TransformerXL(c).init(jax.random.key(0), x)
    unrolled = txl.TransformerXL(dataclasses.replace(c, unroll_layers=True))
    for a, b in zip(txl.TransformerXL(c).apply(params, x), unrolled.apply(params, x)):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)
    looped = xla_gflop(jax.jit(txl.TransformerXL(c).apply), params, x)
    assert xla_gflop(jax.jit(unrolled.apply), params, x) > 2.5 * looped


# ---------------------------------------------------------------- segment sampler
def test_sample_segments_stay_inside_one_episode_and_the_valid_prefix():
    ep_len, cap, size, seg = 10, 50, 27, 4  # 2 full episodes + 7 steps of the third
    rows = np.arange(cap)
    obs = np.stack([rows // ep_len, rows % ep_len, rows], -1).astype(np.float32)  # (episode, t, row)
    obs[size:] = -1.0  # not yet written
    act = np.stack([rows, -rows], -1).astype(np.float32)
    f = jax.jit(partial(wm.sample_segments, episode_len=ep_len, batch_size=600, segment_len=seg))
    o, a = map(np.asarray, f(jax.random.key(0), jnp.asarray(obs), jnp.asarray(act), jnp.asarray(size)))
    assert o.shape == (600, seg, 3) and a.shape == (600, seg, 2)
    assert np.all(o >= 0)  # inside the valid prefix
    assert np.all(o[:, :, 0] == o[:, :1, 0])  # one episode per segment
    np.testing.assert_array_equal(np.diff(o[:, :, 1], axis=1), 1)  # consecutive steps
    assert np.all(o[:, -1, 1] <= ep_len - 1) and np.all(o[:, -1, 2] < size)
    np.testing.assert_array_equal(a[..., 0], o[..., 2])  # actions from the same rows
    starts = {(int(e), int(t)) for e, t in o[:, 0, :2]}
    want = {(e, t) for e in (0, 1) for t in range(ep_len - seg + 1)} | {(2, t) for t in range(7 - seg + 1)}
    assert starts == want  # every valid start is drawn, nothing else
    # a full buffer (size = cap) uses all 5 episodes
    o, _ = f(jax.random.key(1), jnp.asarray(np.stack([rows // ep_len, rows % ep_len, rows], -1).astype(np.float32)),
             jnp.asarray(act), jnp.asarray(cap))
    assert set(np.asarray(o)[:, 0, 0].astype(int)) == set(range(5))
    with pytest.raises(ValueError, match="episode_len"):
        wm.sample_segments(jax.random.key(0), jnp.asarray(obs), jnp.asarray(act), jnp.asarray(size),
                           episode_len=3, batch_size=2, segment_len=seg)


# ---------------------------------------------------------------- training
EP, N_EP = 12, 4


def _rollouts():
    """Deterministic, action-dependent dynamics: θ' = θ + 0.4 + 0.3·a_0, obs = (cos θ, sin θ, cos 2θ)."""
    rng = np.random.default_rng(2)
    act = rng.uniform(-1, 1, size=(N_EP, EP, DA)).astype(np.float32)
    theta = rng.uniform(0, 2 * np.pi, size=(N_EP, 1)) + np.cumsum(0.4 + 0.3 * act[..., 0], axis=1)
    theta = np.concatenate([theta[:, :1] - 0.4 - 0.3 * act[:, :1, 0], theta[:, :-1]], axis=1)
    obs = np.stack([np.cos(theta), np.sin(theta), np.cos(2 * theta)], -1).astype(np.float32)
    return jnp.asarray(obs.reshape(-1, DS)), jnp.asarray(act.reshape(-1, DA))


OBS_BUF, ACT_BUF = _rollouts()
SIZE = jnp.asarray(EP * N_EP, jnp.int32)
STEPS = 40
_train = jax.jit(partial(wm.train, cfg=CFG, episode_len=EP, num_steps=STEPS),
                 static_argnames=("observation_model", "dynamics_model"),
                 compiler_options=AS_RUNS)  # compared bit for bit with pretrain below
_init = jax.jit(wm.init, static_argnums=1)
_obs_loss = jax.jit(lambda p, o: wm.observation_loss(p, o, CFG)[0])
_dyn_loss = jax.jit(lambda p, o, a: wm.dynamics_loss(p.dyn, p.obs, o, a, None, CFG, deterministic=True)[0])


def _leaves_equal(a, b):
    return all(np.array_equal(x, y) for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)))


def test_train_updates_only_the_requested_parts_and_learns():
    eval_obs = OBS_BUF.reshape(N_EP, EP, DS)[:, :T]
    eval_act = ACT_BUF.reshape(N_EP, EP, DA)[:, :T]
    st0 = _init(jax.random.key(0), CFG)

    # observation model only
    st1, m1 = _train(st0, jax.random.key(1), OBS_BUF, ACT_BUF, SIZE, observation_model=True, dynamics_model=False)
    assert _leaves_equal(st1.params.dyn, st0.params.dyn) and _leaves_equal(st1.dyn_opt, st0.dyn_opt)
    assert not _leaves_equal(st1.params.obs, st0.params.obs)
    assert int(st1.obs_steps) == STEPS and int(st1.dyn_steps) == 0
    assert set(m1) == {"prior/wm_obs_loss", "prior/wm_obs_grad_norm"}
    l0, l1 = float(_obs_loss(st0.params.obs, OBS_BUF)), float(_obs_loss(st1.params.obs, OBS_BUF))
    assert l1 < 0.5 * l0, (l0, l1)

    # then dynamics only (the appendix's schedule after pre-training)
    st2, m2 = _train(st1, jax.random.key(2), OBS_BUF, ACT_BUF, SIZE, observation_model=False, dynamics_model=True)
    assert _leaves_equal(st2.params.obs, st1.params.obs) and _leaves_equal(st2.obs_opt, st1.obs_opt)
    assert not _leaves_equal(st2.params.dyn, st1.params.dyn)
    assert int(st2.obs_steps) == STEPS and int(st2.dyn_steps) == STEPS
    assert "prior/wm_dyn_loss" in m2 and "prior/wm_obs_loss" not in m2
    d1, d2 = float(_dyn_loss(st1.params, eval_obs, eval_act)), float(_dyn_loss(st2.params, eval_obs, eval_act))
    assert np.isfinite(d2) and d2 < 0.5 * d1, (d1, d2)

    # both at once
    st3, m3 = _train(st0, jax.random.key(1), OBS_BUF, ACT_BUF, SIZE, observation_model=True, dynamics_model=True)
    assert not _leaves_equal(st3.params.obs, st0.params.obs) and not _leaves_equal(st3.params.dyn, st0.params.dyn)
    assert int(st3.obs_steps) == STEPS and int(st3.dyn_steps) == STEPS
    assert {"prior/wm_obs_loss", "prior/wm_dyn_loss"} <= set(m3)
    with pytest.raises(ValueError):
        wm.train(st0, jax.random.key(1), OBS_BUF, ACT_BUF, SIZE, cfg=CFG, episode_len=EP, num_steps=1,
                 observation_model=False, dynamics_model=False)


def test_pretrain_joint_is_both_at_once_and_observation_first_is_the_two_in_turn():
    """`pretrain`: "joint" = train(both); "observation_first" = train(observation model) with
    the first half of its key's split, then train(dynamics) on the result with the second."""
    st0 = _init(jax.random.key(0), CFG)
    key = jax.random.key(4)
    pretrain = partial(wm.pretrain, obs_buf=OBS_BUF, act_buf=ACT_BUF, size=SIZE, cfg=CFG,
                       episode_len=EP, num_steps=STEPS)
    joint, _ = jax.jit(partial(pretrain, order="joint"), compiler_options=AS_RUNS)(st0, key)
    both, _ = _train(st0, key, OBS_BUF, ACT_BUF, SIZE, observation_model=True,
                     dynamics_model=True)
    assert _leaves_equal(joint.params, both.params)
    first, m = jax.jit(partial(pretrain, order="observation_first"),
                       compiler_options=AS_RUNS)(st0, key)
    k_obs, k_dyn = jax.random.split(key)
    obs_only, _ = _train(st0, k_obs, OBS_BUF, ACT_BUF, SIZE, observation_model=True,
                         dynamics_model=False)
    then_dyn, _ = _train(obs_only, k_dyn, OBS_BUF, ACT_BUF, SIZE, observation_model=False,
                         dynamics_model=True)
    assert _leaves_equal(first.params, then_dyn.params)
    assert int(first.obs_steps) == int(first.dyn_steps) == STEPS
    assert {"prior/wm_obs_loss", "prior/wm_dyn_loss"} <= set(m)
    assert not _leaves_equal(first.params.dyn, joint.params.dyn)
    with pytest.raises(ValueError, match="order"):
        pretrain(st0, key, order="dynamics_first")


def test_a_scaler_standardises_the_valid_rows_and_training_with_it_is_training_on_them():
    """fit_obs_scaler: numpy's mean and std per dimension over rows 0..size-1 only, a constant
    dimension's std floored (it maps to 0); train(obs_scaler=S) on the raw buffer = train on
    the buffer S already standardised (--prior.wm-normalize-obs)."""
    size = 30
    buf = np.asarray(OBS_BUF).copy()
    buf[:, 2] = 3.0  # constant
    buf[size:] = 1e6  # past the valid prefix: never read
    scaler = wm.fit_obs_scaler(jnp.asarray(buf), jnp.int32(size))
    np.testing.assert_allclose(scaler.mean, buf[:size].mean(0), rtol=1e-5)
    np.testing.assert_allclose(scaler.std, np.maximum(buf[:size].std(0), wm.MIN_OBS_STD),
                               rtol=1e-5)
    assert scaler.std[2] == np.float32(wm.MIN_OBS_STD)
    np.testing.assert_allclose(wm.scaled(scaler, jnp.asarray(buf[:size]))[:, 2], 0.0, atol=1e-4)
    assert wm.scaled(None, OBS_BUF) is OBS_BUF
    st0, key = _init(jax.random.key(0), CFG), jax.random.key(5)
    with_scaler, _ = _train(st0, key, jnp.asarray(buf), ACT_BUF, jnp.int32(size),
                            observation_model=True, dynamics_model=True, obs_scaler=scaler)
    prescaled, _ = _train(st0, key, scaler(jnp.asarray(buf)), ACT_BUF, jnp.int32(size),
                          observation_model=True, dynamics_model=True)
    # equal up to float rounding that 40 Adam steps carry to ~5e-6 (raw inputs: ~1e-1 apart)
    for a, b in zip(jax.tree.leaves(with_scaler.params), jax.tree.leaves(prescaled.params)):
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=5e-5)
    raw, _ = _train(st0, key, jnp.asarray(buf), ACT_BUF, jnp.int32(size),
                    observation_model=True, dynamics_model=True)
    gap = max(float(np.abs(a - b).max()) for a, b in zip(jax.tree.leaves(raw.params.obs),
                                                          jax.tree.leaves(with_scaler.params.obs)))
    assert gap > 1e-2, gap


@pytest.mark.parametrize("predict", wm.PREDICTIONS)
def test_dynamics_gradient_leaves_the_observation_model_alone(predict):
    """The dynamics loss has no gradient w.r.t. the observation model (z enters under
    stop_gradient, the decoder is frozen), but does w.r.t. the dynamics params."""
    cfg = _cfg(predict=predict)
    st = _init(jax.random.key(3), cfg)
    o = OBS_BUF.reshape(N_EP, EP, DS)[:2, :T]
    a = ACT_BUF.reshape(N_EP, EP, DA)[:2, :T]
    g_dyn, g_obs = jax.jit(jax.grad(lambda d, p: wm.dynamics_loss(d, p, o, a, None, cfg, deterministic=True)[0],
                                    argnums=(0, 1)))(st.params.dyn, st.params.obs)
    assert all(float(jnp.abs(g).max()) == 0.0 for g in jax.tree_util.tree_leaves(g_obs))
    assert sum(float(jnp.abs(g).sum()) for g in jax.tree_util.tree_leaves(g_dyn)) > 0.0


# the default (hash) in the fast suite; rbg and threefry, the other options, with -m slow
@pytest.mark.parametrize("impl", [i if i == "hash" else pytest.param(i, marks=pytest.mark.slow)
                                  for i in wm.DROPOUT_RNGS])
def test_dropout_rng_drops_reproducibly_and_every_impl_is_vmappable(impl):
    """Every source of bits gives dropout masks that depend on the key only (same key: same output; other
    key: other output), leave the deterministic pass alone, and work under vmap over seeds."""
    cfg = _cfg(dropout=0.5, dropout_rng=impl)
    st = _init(jax.random.key(4), cfg)
    o = OBS_BUF.reshape(N_EP, EP, DS)[:2, :T]
    a = ACT_BUF.reshape(N_EP, EP, DA)[:2, :T]
    run = jax.jit(lambda k: wm.dynamics(st.params, o, a, cfg, deterministic=False, key=k)[0])
    z1, z1_again, z2 = run(jax.random.key(5)), run(jax.random.key(5)), run(jax.random.key(6))
    z_det = wm.dynamics(st.params, o, a, cfg)[0]
    assert np.array_equal(z1, z1_again)
    assert not np.allclose(z1, z2) and not np.allclose(z1, z_det)
    z_batched = jax.vmap(run)(jax.random.split(jax.random.key(7), 2))
    assert z_batched.shape == (2,) + z1.shape and not np.allclose(z_batched[0], z_batched[1])
    with pytest.raises(ValueError, match="dropout_rng"):
        _cfg(dropout_rng="philox")


def test_delta_prediction_adds_the_change_to_the_present_and_starts_as_persistence():
    """predict="delta": ẑ_{t+1} = z_t + the head's output, decoded as s_t + dec(ẑ) - dec(z_t);
    its head's output layer starts at zero, so an untrained change model is persistence
    exactly (an untrained state model predicts noise around the decoder's output)."""
    with pytest.raises(ValueError, match="predict"):
        _cfg(predict="next")
    delta = _cfg(predict="delta")
    obs = OBS_BUF.reshape(N_EP, EP, DS)[:, :T]
    act = ACT_BUF.reshape(N_EP, EP, DA)[:, :T]
    fresh = _init(jax.random.key(0), delta).params
    np.testing.assert_allclose(wm.predict_next(fresh, obs, act, delta)[1], obs[:, :-1], atol=1e-6)
    params = _init(jax.random.key(0), CFG).params  # a head that outputs something
    z_state, _ = wm.predict_next(params, obs, act, CFG)
    z_delta, s_delta = wm.predict_next(params, obs, act, delta)
    z_now = wm.encode(params.obs, obs[:, :-1], CFG)
    np.testing.assert_allclose(z_delta, z_now + z_state, rtol=1e-5, atol=1e-6)
    decode = lambda z: wm.decode(params.obs, z, CFG)
    s_expected = obs[:, :-1] + decode(z_now + z_state) - decode(z_now)
    np.testing.assert_allclose(s_delta, s_expected, rtol=1e-5, atol=1e-5)
