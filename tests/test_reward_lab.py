"""The reward-learning lab on a synthetic task with tiny networks: its cells are independent
(one seed equals its slot in the vmapped batch), the true reward reaches only the teacher,
the oracle credit and the metrics, and the oracle-credit control beats PEBBLE on a task built
so that it must (a check that the lab can detect a real effect). Three compiled round
programs in all: the lab caches them by settings and shapes."""
import dataclasses
import json
from functools import partial

import numpy as np
import pytest
from scipy import stats

from hprior_jax.lab import metrics
from hprior_jax.lab.dataset import Dataset, heldout_pairs, split_episodes
from hprior_jax.lab.config import LabConfig
from hprior_jax.lab.learn import Lab
from hprior_jax.lab.rules import REFERENCE, default_rules, rules
from hprior_jax.lab.sweep import lab_config
from hprior_jax.methods import registry
from hprior_jax.networks.reward_ensemble import RewardConfig
from hprior_jax.pbrl.preference import PreferenceConfig
from hprior_jax.prior.world_model import WorldModelConfig

T = 10  # segment length
ALL = default_rules()
quiet = dict(progress=lambda *_: None)


def confounded(seed=0, episodes=24, length=40, reward="half") -> Dataset:
    """The reward is 1 on the states with obs[0] > 0, else 0. Each episode has a level μ that
    shifts obs[0] (so it sets how often the episode is rewarded) and that obs[1] shows almost
    without noise: a reward of obs[1] alone explains segment returns nearly as well as the true
    one, so labels of whole segments cannot tell the two apart, and the true per-step credit
    can. A learner that reads the credit must get closer to the true reward than one that
    cannot. `reward="sparse"`: 1 only where obs[0] > 1.5 (rare steps); `"level"`: μ itself on
    every step of its episode (no per-step structure: uniform credit is the true credit)."""
    rng = np.random.default_rng(seed)
    n = episodes * length
    level = np.repeat(rng.uniform(-1.5, 1.5, episodes), length)
    obs = rng.normal(size=(n, 4)).astype(np.float32)
    obs[:, 0] += level
    obs[:, 1] = level + 0.05 * obs[:, 1]
    act = rng.uniform(-1, 1, size=(n, 2)).astype(np.float32)
    true = (level if reward == "level"
            else obs[:, 0] > {"half": 0.0, "sparse": 1.5}[reward]).astype(np.float32)
    (tr_o, te_o), (tr_a, te_a), (tr_r, te_r) = split_episodes(obs, act, true, length)
    index, label = heldout_pairs(te_r, T, 300, rng)
    return Dataset(task="confounded", segment_len=T, train_obs=tr_o, train_act=tr_a,
                   train_reward=tr_r, test_obs=te_o, test_act=te_a, test_reward=te_r,
                   pair_index=index, pair_label=label, info={"steps": n})


TINY_WM = WorldModelConfig(obs_size=4, act_size=2, latent_dim=4, obs_hidden=(16,), embed_dim=16,
                           num_heads=2, head_dim=8, num_layers=1, ff_dim=32, dropout=0.0,
                           head_hidden=(16,), segment_len=T, memory_len=T, batch_size=8)


def tiny(**kw) -> LabConfig:
    from hprior_jax.lab.surf_round import SurfLabRule
    from hprior_jax.methods.surf import SurfConfig

    known = rules()
    names = kw.get("rules", ALL)
    surf = (("surf", SurfLabRule(cfg=SurfConfig(), segment_len=T)),)
    base = dict(rules=tuple(ALL), credits=tuple(known[r] for r in ALL), lam=5.0,
                own_rules=surf if "surf" in names and "own_rules" not in kw else (),
                budgets=(20, 50), queries_per_round=10, seeds=(0, 1),
                # BISIM's head for the bisim rule (the other rules never read it)
                reward=RewardConfig(hidden_sizes=(32, 32), ensemble_size=3,
                                    next_embedding_head=True),
                # 16-row minibatches: one round program per lab (the lab picks the smallest
                # of 16/32/64/... that holds the labels, at most this)
                preference=PreferenceConfig(max_epochs=100, lr=1e-3, batch_size=16),
                world_model=TINY_WM, wm_pretrain_steps=5, wm_steps=5, profile_segments=16)
    return LabConfig(**{**base, **kw})


def by_cell(rows):
    return {(r["seed"], r["rule"], r["budget"]): r for r in rows}


def test_rules_are_the_registered_reward_learners_and_the_controls():
    """The lab's table names registered methods only, and every method but those that learn
    no reward from preferences of their own (SAC, RUNE, MRN); the methods know nothing of it."""
    from hprior_jax.lab import rules as lab_rules

    assert set(registry.names()) - set(lab_rules.METHODS) == {"sac", "rune", "mrn"}
    learners = [n for n in registry.names() if n in lab_rules.METHODS]
    assert ALL == learners + ["positional", "oracle"]
    assert REFERENCE in ALL and set(lab_rules.OWN_PROGRAMS) == {"surf"}
    assert rules()["prior"] == "attention" and rules()["prior_nrp"] == "attention_nrp"
    assert registry.REFERENCE not in ALL  # SAC learns no reward
    assert list(rules()) == ALL + ["prior_no_own_step", "prior_clipped", "prior_unlabelled",
                                   "rvar_unlabelled", "positional_unlabelled",  # by name
                                   "state_importance", "state_importance_positional",
                                   "pref_attention", "pref_attention_positional"]
    assert rules()["bisim"] == "bisimulation"


def test_ablations_and_lambdas_are_rules_of_one_lab(data):
    cfg = lab_config(dataclasses.replace(data, task="toy_point"), "smoke",
                     ["pebble", "prior@0", "prior", "prior_clipped", "prior_no_own_step@25",
                      "prior_unlabelled"])
    assert cfg.credits == ("none", "attention", "attention", "attention",
                           "attention_no_own_step", "attention")
    assert cfg.clips == (False, False, False, True, False, False)
    assert cfg.unlabelled == (False,) * 5 + (True,) and cfg.needs_unlabelled
    assert cfg.unlabelled_segments == 64  # the lab's N, as --prior.unlabelled-segments is 0
    assert cfg.rule_lams == (None, 0.0, None, None, 25.0, None)
    lab = Lab(cfg, dataclasses.replace(data, task="toy_point"))
    np.testing.assert_array_equal(lab.rule_args.lam, [0, 0, cfg.lam, cfg.lam, 25, cfg.lam])
    np.testing.assert_array_equal(lab.rule_args.clip, cfg.clips)
    np.testing.assert_array_equal(lab.rule_args.unlabelled, cfg.unlabelled)
    assert lab_config(dataclasses.replace(data, task="toy_point"), "smoke", ["prior_unlabelled"],
                      prior_settings=["unlabelled_segments=16"]).unlabelled_segments == 16
    assert not cfg.reward.next_embedding_head  # BISIM's head only with a bisim rule
    assert lab_config(dataclasses.replace(data, task="toy_point"), "smoke",
                      ["pebble", "bisim"]).reward.next_embedding_head
    for bad, match in ((["pebble@5"], "no prior term"), (["bisim@1"], "no prior term"),
                       (["prior@x"], "RULE@LAMBDA"), (["prior", "prior"], "named twice")):
        with pytest.raises(ValueError, match=match):
            lab_config(dataclasses.replace(data, task="toy_point"), "smoke", bad)


def test_surf_is_a_rule_of_its_own_program_at_its_presets_settings(data):
    """The lab's table builds SURF's rule from `hprior train --algo surf`'s preset."""
    from hprior_jax.agents.sac import SACConfig
    from hprior_jax.lab.surf_round import SurfLabRule
    from hprior_jax.methods.surf import surf_preset

    cfg = lab_config(dataclasses.replace(data, task="toy_point"), "smoke", ["pebble", "surf"])
    want = surf_preset("toy_point", "smoke", SACConfig())
    assert cfg.credits == ("none", "own_program") and cfg.shared_rules == [0]
    assert cfg.own_rules == (("surf", SurfLabRule(cfg=want["surf"],
                                                  segment_len=want["pebble"].segment_len)),)


def test_prior_settings_change_the_world_model_and_tag_the_rules_that_read_it(data):
    """`--prior-set`: a world-model ablation as a lab of its own; its world-model rules carry
    the settings (or `--tag`) in their names, so its rows and another lab's merge apart."""
    toy = dataclasses.replace(data, task="toy_point", info={"steps": 50_000})
    names = ["pebble", "prior", "positional", "rvar", "prior@25"]
    base = lab_config(toy, "smoke", names)
    cfg = lab_config(toy, "smoke", names, prior_settings=["wm_layers=2", "wm-update-steps=7"])
    assert cfg.world_model.num_layers == 2 != base.world_model.num_layers
    from hprior_jax import presets

    per_update = presets.train_preset("toy_point", registry.PROPOSED, "smoke").prior
    assert cfg.wm_steps * per_update.wm_update_steps == base.wm_steps * 7 > 0
    tag = "[wm_layers=2,wm-update-steps=7]"
    assert cfg.rules == ("pebble", f"prior{tag}", f"positional{tag}", "rvar", f"prior@25{tag}")
    assert cfg.rule_lams == base.rule_lams and cfg.credits == base.credits
    tagged = lab_config(toy, "smoke", names, prior_settings=["wm_layers=2"], tag="deep")
    assert tagged.rules[1] == "prior[deep]"
    assert lab_config(toy, "smoke", names, prior_settings=["wm_lr=0.001"]
                      ).world_model.num_layers == base.world_model.num_layers
    assert not base.wm_normalize_obs and lab_config(
        toy, "smoke", names, prior_settings=["wm_normalize_obs=true"]).wm_normalize_obs
    assert base.wm_order == "joint" and lab_config(
        toy, "smoke", names, prior_settings=["wm_order=observation_first"]
    ).wm_order == "observation_first"
    from hprior_jax.lab.sweep import with_settings
    from hprior_jax.methods.prior import PriorConfig

    assert with_settings(PriorConfig(), ["clip_targets=True"]).clip_targets is True
    with pytest.raises(ValueError, match="true or false"):
        with_settings(PriorConfig(), ["clip_targets=yes"])  # not bool("yes")
    for bad, match in ((["wm_layer=1"], "FIELD=VALUE"), (["wm_layers"], "FIELD=VALUE"),
                       (["wm_dropout=x"], "x"), (["wm_layers=0"], "positive"),
                       (["clip-targets=true"], "prior_clipped"),
                       (["wm_order=dynamics_first"], "wm-order")):
        with pytest.raises(ValueError, match=match):
            lab_config(toy, "smoke", names, prior_settings=bad)


def test_the_report_is_written_as_each_budget_is_reached(data, tmp_path, monkeypatch):
    """A lab stopped after its first budget keeps that budget's report."""
    from hprior_jax.lab import sweep

    seen = []

    class TwoBudgets:  # Lab's protocol: run(progress, on_budget) with rows per budget
        seconds, compile_seconds, adam_steps, diagnostics, wall_before = {}, {}, 0, [], 0.0

        def __init__(self, cfg, data, given, world_model_cache=None):
            pass

        def run(self, progress, on_budget, checkpoints=None):
            for budget in (10, 20):
                on_budget([dict(seed=s, rule=r, budget=budget,
                                prediction=np.asarray(data.test_reward) + s)
                           for s in (0, 1) for r in ("pebble", "rvar")])
                seen.append((tmp_path / "lab" / "results.csv").read_text().count("\n"))

    monkeypatch.setattr(sweep, "Lab", TwoBudgets)
    sweep.run_lab(data, tiny(rules=("pebble", "rvar"), credits=("none", "uniform")),
                  tmp_path / "lab")
    assert seen == [1 + 4, 1 + 8]  # header + 2 seeds x 2 rules, then the second budget's too
    assert "run_info.json" in {p.name for p in (tmp_path / "lab").iterdir()}


def test_a_stopped_lab_resumes_to_the_rows_of_a_lab_that_never_stopped(data, tmp_path,
                                                                        monkeypatch):
    """Stopped in its fourth round of five (after the first budget), the lab keeps the state
    of its third; `resume` runs the last two rounds and ends with the same results and
    predictions, bit for bit, as a lab that never stopped. Without `resume` the state is not
    overwritten; another lab's state is refused before any work; the state goes at the end."""
    from hprior_jax.lab import resume, sweep

    cfg = tiny(rules=("pebble", "rvar", "oracle"), credits=("none", "uniform", "oracle"))
    assert len(cfg.rounds()) == 5
    run = partial(sweep.run_lab, data, cfg, **quiet, checkpoint_every_s=0.0)
    run(tmp_path / "whole")
    step, calls = Lab._shared_step, []

    def stops_in_round_four(self, *args):
        calls.append(1)
        if len(calls) == 4:
            raise KeyboardInterrupt
        return step(self, *args)

    monkeypatch.setattr(Lab, "_shared_step", stops_in_round_four)
    with pytest.raises(KeyboardInterrupt):
        run(tmp_path / "stopped")
    monkeypatch.setattr(Lab, "_shared_step", step)
    stopped = tmp_path / "stopped"
    state = resume.load(stopped / resume.STATE_NAME, resume.fingerprint(cfg, data))
    assert (state.schedule, state.next_round) == (0, 3)
    assert {r["budget"] for r in state.rows} == {20} and len(state.rows) == 2 * 3
    with pytest.raises(FileExistsError):
        run(stopped)
    with pytest.raises(resume.StateMismatch):
        sweep.run_lab(data, dataclasses.replace(cfg, seeds=(0,)), stopped, resume=True, **quiet)
    said = []
    run(stopped, resume=True, progress=said.append)  # a line a round, from the fourth on
    assert [line.split(":")[0] for line in said] == [
        "resuming at round 4 of 5 with 6 rows reached", "round 4 of 5", "50 labels"]
    assert not (stopped / resume.STATE_NAME).exists()
    assert (stopped / "results.csv").read_text() == (tmp_path / "whole/results.csv").read_text()
    with np.load(stopped / "predictions.npz") as a, \
            np.load(tmp_path / "whole/predictions.npz") as b:
        for name in ("seed", "rule", "budget", "prediction"):
            np.testing.assert_array_equal(a[name], b[name])


def test_unlabelled_segments_carry_their_rules_credit(data):
    """prior_unlabelled's controls differ from it only in the credit of the same unlabelled
    segments: uniform (rvar_unlabelled), the world model's mean profile
    (positional_unlabelled), or the segment's own attention (prior_unlabelled)."""
    import jax

    from hprior_jax.lab.config import CREDITS

    names = ["prior_unlabelled", "rvar_unlabelled", "positional_unlabelled"]
    cfg = lab_config(dataclasses.replace(data, task="toy_point"), "smoke", names)
    assert cfg.credits == ("attention", "uniform", "positional") and all(cfg.unlabelled)
    lab = Lab(tiny(rules=tuple(names), credits=cfg.credits, unlabelled=cfg.unlabelled,
                   unlabelled_segments=16, seeds=(0,)), data)
    ctx = lab.seed_context(jax.random.PRNGKey(0), lab.train)
    pools = {c: lab.unlabelled_segments(jax.random.PRNGKey(1), ctx, lab.train, 32,
                                        CREDITS.index(c))
             for c in cfg.credits}
    for c in cfg.credits:  # the same segments, row r holding segment r mod 16
        np.testing.assert_array_equal(pools[c].obs, pools["attention"].obs)
        np.testing.assert_array_equal(pools[c].obs[16:], pools[c].obs[:16])
    np.testing.assert_allclose(pools["uniform"].alpha, 1.0 / T)
    np.testing.assert_allclose(pools["positional"].alpha,
                               np.broadcast_to(ctx.profile, (32, T)), rtol=1e-6)
    # the profile is the world model's mean α per position, not uniform: the mean attention
    # of 16 other training segments follows its shape
    others = lab.unlabelled_segments(jax.random.PRNGKey(2), ctx, lab.train, 16,
                                     CREDITS.index("attention")).alpha.mean(0)
    profile = np.asarray(ctx.profile)
    assert np.abs(profile - 1.0 / T).max() > 0.005  # a tiny world model: ~0.009
    assert np.corrcoef(others, profile)[0, 1] > 0.5
    attention = np.asarray(pools["attention"].alpha)
    np.testing.assert_allclose(attention.sum(-1), 1.0, rtol=1e-5)
    assert np.abs(attention[:16] - attention[:16].mean(0)).max() > 1e-4  # per segment


@pytest.mark.slow  # CI time (~100 s)
def test_a_prior_rule_at_lambda_zero_is_pebble_and_the_ablations_and_bisim_change_the_reward(
        data):
    """prior@0 stores α but weighs it by 0: it must train exactly PEBBLE's reward (same
    queries, labels and weights). Leaving out the own step changes the credit and so the
    reward; clipping changes it where targets leave [-1, 1], which on this task the oracle
    credit's do (the tiny world model's α is near uniform: its targets stay in range). The
    bisim rule trains its term; the head it adds to every cell leaves PEBBLE's reward as it is
    without it. The prior on unlabelled segments changes PRIOR's reward."""
    names = ("pebble", "prior@0", "prior", "prior_no_own_step", "oracle", "oracle clipped",
             "bisim", "prior_unlabelled")
    cfg = tiny(rules=names, credits=("none", "attention", "attention", "attention_no_own_step",
                                     "oracle", "oracle", "bisimulation", "attention"),
               rule_lams=(None, 0.0, None, None, None, None, None, None),
               clips=(False,) * 5 + (True, False, False), unlabelled=(False,) * 7 + (True,),
               unlabelled_segments=8, seeds=(0,), budgets=(20,),
               reward=RewardConfig(hidden_sizes=(32, 32), ensemble_size=3,
                                   next_embedding_head=True))
    cells = {rule: cell for (_, rule, _), cell in by_cell(Lab(cfg, data).run(**quiet)).items()}
    pred = {n: cells[n]["prediction"] for n in names}
    np.testing.assert_array_equal(pred["prior@0"], pred["pebble"])
    assert cells["prior@0"]["prior_loss"] > 0  # computed, weighed by 0
    assert cells["oracle"]["target_out_of_range"] > 0
    for ablated, base in (("prior_no_own_step", "prior"), ("oracle clipped", "oracle"),
                          ("bisim", "pebble"), ("prior_unlabelled", "prior")):
        assert np.abs(pred[ablated] - pred[base]).mean() > 1e-3, ablated
    assert cells["bisim"]["bisim_loss"] > 0 and cells["bisim"]["bisim_grad_ratio"] > 0
    assert cells["pebble"]["bisim_grad_ratio"] == 0  # computed, weighed by 0
    assert cells["prior_unlabelled"]["unlabelled_prior_loss"] > 0
    alone = Lab(tiny(rules=("pebble",), credits=("none",), seeds=(0,), budgets=(20,),
                     world_model=None), data).run(**quiet)
    # another program: equal up to its rounding (<= 1e-5 in test_one_seed_equals_its_slot)
    assert np.abs(alone[0]["prediction"] - pred["pebble"]).max() < 1e-4


def test_bisim_transitions_from_episodes_never_cross_an_episode_end():
    import jax

    from hprior_jax.lab.config import Episodes
    from hprior_jax.lab.rounds import episode_transitions

    e, length = 5, 7
    step = np.arange(e * length, dtype=np.float32).reshape(e, length, 1)  # obs = global step
    eps = Episodes(obs=step, act=-step, reward=np.zeros((e, length), np.float32))
    tr = jax.tree.map(np.asarray, episode_transitions(jax.random.PRNGKey(0), eps, 300, 4))
    assert tr.obs.shape == (300, 4, 1) and tr.valid.all()
    np.testing.assert_array_equal(tr.next_obs, tr.obs + 1)
    np.testing.assert_array_equal(tr.next_act, -tr.next_obs)
    assert set(np.unique(tr.obs % length)) == set(range(length - 1))  # every non-last step


def test_rounds_land_on_every_budget():
    rounds = tiny(budgets=(25, 100)).rounds()
    assert [n for n, _ in rounds] == [10, 10, 5] + [10] * 7 + [5]
    assert [b for _, b in rounds if b] == [25, 100]


@pytest.fixture(scope="module")
def data():
    return confounded()


def test_a_labs_world_models_are_kept_and_the_next_lab_of_the_same_settings_loads_them(
        data, tmp_path):
    """The second lab gets the first one's world models and profiles, leaf for leaf, without
    training; another world-model setting or seed list names another file; a file whose
    leaves do not fit is trained over."""
    import jax
    import jax.numpy as jnp

    from hprior_jax.lab import world_model_cache as cache

    # with standardised world-model inputs, so the kept context holds the scaler too
    cfg = tiny(rules=("prior",), credits=("attention",), seeds=(0,), wm_normalize_obs=True)
    path = cache.cache_path(cfg, data, tmp_path)
    keys = jnp.stack([jax.random.PRNGKey(s) for s in cfg.seeds])
    first = Lab(cfg, data, world_model_cache=path)
    trained = first.seed_contexts(keys)
    assert path.exists() and not first.world_model_loaded and first.seconds["world_model"] > 0
    second = Lab(cfg, data, world_model_cache=path)
    loaded = second.seed_contexts(keys)
    assert second.world_model_loaded and "world_model" not in second.seconds
    for a, b in zip(jax.tree.leaves(trained), jax.tree.leaves(loaded), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    np.testing.assert_allclose(loaded.obs_scaler.mean[0],
                               data.train_obs.reshape(-1, 4).mean(0), atol=1e-5)
    for other in (dataclasses.replace(cfg, wm_steps=cfg.wm_steps + 1),
                  dataclasses.replace(cfg, wm_normalize_obs=False),
                  dataclasses.replace(cfg, seeds=(0, 1)),
                  dataclasses.replace(cfg, world_model=dataclasses.replace(TINY_WM, dyn_lr=1e-3))):
        assert cache.cache_path(other, data, tmp_path) != path
    assert Lab(tiny(rules=("pebble",), credits=("none",)), data,
               world_model_cache=path).world_model_cache is None  # no world model to keep
    cache.save(path, {"other": np.zeros(3)})
    assert cache.load(path, jax.eval_shape(jax.vmap(second.seed_context, (0, None)), keys,
                                           second.train)) is None


TARGET_FORMS = ("pebble", "oracle", "oracle~shift", "rvar", "rvar~shift")


@pytest.fixture(scope="module")
def oracle_vs_pebble(data):
    """BPref's tanh head, uniform queries, 6 seeds: the oracle credit under both target
    forms, and uniform credit under both (where they must coincide)."""
    cfg = tiny(rules=TARGET_FORMS, credits=("none", "oracle", "oracle", "uniform", "uniform"),
               shifts=(False, False, True, False, True), seeds=tuple(range(6)), budgets=(20,),
               feed_type="uniform", reward=RewardConfig(hidden_sizes=(32, 32), ensemble_size=3))
    return cfg, Lab(cfg, data).run(**quiet)


def _gains(data, cfg, rows, rule, metric):
    cells = by_cell(rows)
    score = lambda s, r: metrics.reward_quality(cells[(s, r, 20)]["prediction"],
                                                data.test_reward, data.pair_index,
                                                data.pair_label, T)[metric]
    return np.array([score(s, rule) - score(s, "pebble") for s in cfg.seeds])


@pytest.mark.parametrize("metric", ["pearson", "episode_pearson"])
def test_oracle_credit_beats_pebble_with_the_shifted_target_and_loses_with_the_raw(
        data, oracle_vs_pebble, metric):
    """BT leaves the per-step level free, so R̂ < 0 happens under tanh; the raw target α·R̂
    then pushes the most-credited steps down (measured: Pearson −0.097 mean over 6 seeds),
    the shifted one α·(R̂ + T) − 1 does not (+0.142). Both are asserted: the form is wired
    and it matters."""
    cfg, rows = oracle_vs_pebble
    shifted = _gains(data, cfg, rows, "oracle~shift", metric)
    raw = _gains(data, cfg, rows, "oracle", metric)
    assert shifted.min() > 0 and shifted.mean() > 0.08, shifted
    assert raw.mean() < 0, raw


def test_uniform_credit_is_the_same_under_both_target_forms(oracle_vs_pebble):
    _, rows = oracle_vs_pebble
    cells = by_cell(rows)
    for seed in range(6):
        np.testing.assert_allclose(cells[(seed, "rvar~shift", 20)]["prediction"],
                                   cells[(seed, "rvar", 20)]["prediction"], atol=2e-5)


def test_uniform_queries_give_every_rule_of_a_seed_the_same_labels(oracle_vs_pebble):
    """Same labels, same initial weights: only λ·L_prior differs, and it reaches the reward;
    the shifted form's targets are the raw ones moved by α·T − 1, so their out-of-range
    shares differ."""
    _, rows = oracle_vs_pebble
    cells = by_cell(rows)
    pebble, oracle = cells[(0, "pebble", 20)], cells[(0, "oracle", 20)]
    assert pebble["labels"] == oracle["labels"] == cells[(0, "oracle~shift", 20)]["labels"] == 20
    assert pebble["prior_loss"] > 0 and oracle["prior_loss"] > 0
    assert oracle["target_out_of_range"] != cells[(0, "oracle~shift", 20)]["target_out_of_range"]
    assert not np.allclose(pebble["prediction"], oracle["prediction"], atol=1e-3)


@pytest.fixture(scope="module")
def disagreement(data):
    cfg = tiny()
    return cfg, Lab(cfg, data).run(**quiet)


@pytest.fixture(scope="module")
def seed_one_alone(data):
    cfg = dataclasses.replace(tiny(), seeds=(1,))
    return cfg, Lab(cfg, data).run(**quiet)


@pytest.mark.slow
def test_one_seed_equals_its_slot_in_the_vmapped_batch(disagreement, seed_one_alone):
    _, rows = disagreement
    _, alone = seed_one_alone
    batch = by_cell(rows)
    gap = lambda a, b: float(np.abs(a["prediction"] - b["prediction"]).mean())
    for row in alone:
        slot = batch[(row["seed"], row["rule"], row["budget"])]
        assert row["labels"] == slot["labels"] and row["epochs"] == slot["epochs"]
        # equal up to the rounding of a vmapped program (measured: <= 1e-5), far closer than
        # the other seed's reward under the same rule (~0.1). At λ = 50 the same rounding
        # grew to 0.05 for some rules over the two budgets: training that hot is chaotic.
        other_seed = gap(row, batch[(0, row["rule"], row["budget"])])
        assert gap(row, slot) < 1e-4 and gap(row, slot) < 1e-3 * other_seed, row["rule"]


@pytest.mark.slow
def test_true_reward_reaches_only_the_teacher_and_the_oracle(data, seed_one_alone):
    """Doubling every true reward leaves the oracle teacher's labels and the oracle credit
    unchanged, so every rule must learn exactly the same reward; a learner that read true
    rewards (regressed on them, normalised by them) would not."""
    cfg, a = seed_one_alone
    b = Lab(cfg, dataclasses.replace(data, train_reward=2 * data.train_reward)).run(**quiet)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x["prediction"], y["prediction"])


def test_no_rule_but_the_oracle_reads_the_true_reward_beyond_segment_returns(data):
    """A T-periodic zero-sum pattern added to every training reward leaves every segment's
    return, so the teacher's labels, unchanged, and changes each step's share r/Σr; every rule
    but the oracle must then learn exactly the same reward. (Doubling the rewards, the test
    above, cannot see a leak of r/Σr: it is scale-free.)"""
    names = ("pebble", "prior", "rvar", "positional", "prior~shift")
    cfg = tiny(rules=names, credits=("none", "attention", "uniform", "positional", "attention"),
               shifts=(False,) * 4 + (True,), seeds=(0,), budgets=(20,))
    pattern = np.tile([0.5, -0.5], data.train_reward.shape[1] // 2).astype(np.float32)
    moved = dataclasses.replace(data, train_reward=data.train_reward + pattern)
    a, b = (Lab(cfg, d).run(**quiet) for d in (data, moved))
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x["prediction"], y["prediction"])
    # and the oracle does read it
    oracle = tiny(rules=("oracle",), credits=("oracle",), seeds=(0,), budgets=(20,))
    a, b = (Lab(oracle, d).run(**quiet) for d in (data, moved))
    assert not np.array_equal(a[0]["prediction"], b[0]["prediction"])


def test_reward_quality_matches_numpy_and_scipy(data):
    rng = np.random.default_rng(3)
    pred = data.test_reward + rng.normal(scale=0.5, size=data.test_reward.shape)
    got = metrics.reward_quality(pred, data.test_reward, data.pair_index, data.pair_label, T)
    correct = 0
    for (e1, s1, e2, s2), label in zip(data.pair_index, data.pair_label):
        r1, r2 = pred[e1, s1:s1 + T].sum(), pred[e2, s2:s2 + T].sum()
        correct += (r2 > r1) == bool(label)
    assert got["heldout_accuracy"] == pytest.approx(correct / len(data.pair_label))
    assert got["pearson"] == pytest.approx(np.corrcoef(pred.ravel(), data.test_reward.ravel())[0, 1])
    ranks = lambda x: stats.rankdata(x.ravel())
    assert got["spearman"] == pytest.approx(np.corrcoef(ranks(pred), ranks(data.test_reward))[0, 1])
    assert got["kendall_tau"] == pytest.approx(
        stats.kendalltau(pred.sum(1), data.test_reward.sum(1)).statistic)
    perfect = metrics.reward_quality(data.test_reward, data.test_reward, data.pair_index,
                                     data.pair_label, T)
    assert perfect["heldout_accuracy"] == 1.0 and perfect["pearson"] == pytest.approx(1.0)


# -m slow for CI time (70 s of one worker): the lab's pieces stay in the fast suite above
@pytest.mark.slow
def test_cli_builds_the_dataset_once_runs_and_reports(tmp_path, monkeypatch, capsys):
    """`hprior reward-lab` end to end on the toy task: a SAC run's replay buffer becomes the
    cached dataset, two rules x two seeds train, and the report's files are written; a second
    call finds the dataset in the cache."""
    from hprior_jax import cli

    monkeypatch.setenv("HPRIOR_LAB_CACHE", str(tmp_path / "cache"))
    argv = ["reward-lab", "--task", "toy_point", "--preset", "smoke", "--dataset-steps", "200",
            "--seeds", "2", "--budgets", "10", "--rules", "pebble", "rvar",
            "--out", str(tmp_path / "lab")]
    assert cli.main(argv) == 0
    out = tmp_path / "lab"
    assert {"report.md", "results.csv", "summary.csv", "run_info.json"} <= {
        p.name for p in out.iterdir()}
    results = (out / "results.csv").read_text().splitlines()
    assert len(results) == 1 + 2 * 2 and results[0].startswith("task,rule,budget,seed")
    assert "rvar − pebble at 10 labels" in (out / "report.md").read_text()
    cached = list((tmp_path / "cache").glob("toy_point_*.npz"))
    assert len(cached) == 1
    data = Dataset.load(cached[0])
    assert data.train_reward.shape == (7, 20) and data.test_reward.shape == (3, 20)
    assert cli.main(argv[:-2] + ["--dataset-only"]) == 0
    assert "dataset" in capsys.readouterr().out and len(list(cached[0].parent.iterdir())) == 1

    # the same lab as two seed shards, merged: the same rows as the lab of both seeds
    for first in ("0", "1"):
        assert cli.main(argv[:8] + ["1", "--first-seed", first] + argv[9:-1]
                        + [str(tmp_path / f"shard{first}")]) == 0
    from hprior_jax.lab import report

    report.main([str(tmp_path / f"shard{i}" / "results.csv") for i in (0, 1)]
                + [str(tmp_path / "merged")])
    infos = [json.loads((tmp_path / f"shard{i}" / "run_info.json").read_text()) for i in (0, 1)]
    assert {i["dataset_digest"] for i in infos} == {data.digest()}  # what the merge checks
    assert dataclasses.replace(data, info={}).digest() == data.digest()  # not how it was made
    assert dataclasses.replace(data, pair_label=1 - data.pair_label).digest() != data.digest()
    whole, merged = (by_cell(report.read_results(p / "results.csv"))
                     for p in (out, tmp_path / "merged"))
    assert whole.keys() == merged.keys() and {seed for seed, *_ in merged} == {0, 1}
    for cell, row in whole.items():  # up to a vmapped program's rounding
        assert merged[cell]["heldout_accuracy"] == pytest.approx(row["heldout_accuracy"],
                                                                 abs=0.02), cell
        assert merged[cell]["pearson"] == pytest.approx(row["pearson"], abs=1e-3), cell


def test_a_given_dataset_file_is_the_labs_and_must_be_of_its_task(tmp_path, monkeypatch,
                                                                  capsys):
    """`--dataset FILE` (a lab shared by machines whose SAC runs differ) reads that file and
    neither builds nor caches another; a file of another task is refused."""
    from hprior_jax import cli

    monkeypatch.setenv("HPRIOR_LAB_CACHE", str(tmp_path / "cache"))
    path = confounded().save(tmp_path / "shared.npz")
    assert cli.main(["reward-lab", "--task", "confounded", "--dataset", str(path),
                     "--dataset-only"]) == 0
    assert f"dataset {path}: {{'steps': 960}}" in capsys.readouterr().out
    assert not (tmp_path / "cache").exists()
    with pytest.raises(SystemExit):
        cli.main(["reward-lab", "--task", "toy_point", "--dataset", str(path)])
    assert "is of confounded, not --task toy_point" in capsys.readouterr().err


def test_a_dataset_is_made_only_from_a_sac_run(tmp_path):
    """`--dataset-from-run` refuses another method's run before reading any checkpoint."""
    from hprior_jax import presets
    from hprior_jax.lab import dataset as datasets
    from hprior_jax.runs.run_dir import prepare_run_dir

    other = presets.train_preset("toy_point", REFERENCE, "smoke", steps=200,
                                 out=str(tmp_path / "pebble"))
    prepare_run_dir(other)  # its config only
    with pytest.raises(ValueError, match="--algo pebble run"):
        datasets.from_run(tmp_path / "pebble")


@pytest.mark.slow  # CI time: two SAC runs (39 s)
def test_a_dataset_from_an_existing_sac_run_equals_the_one_build_makes(tmp_path):
    """`--dataset-from-run`: the replay buffer of a finished SAC run (here with its own
    evaluation and checkpoint cadence) gives the dataset that `build` makes by running the
    same seed and steps itself."""
    from hprior_jax import presets
    from hprior_jax.lab import dataset as datasets
    from hprior_jax.runs.build import train
    from hprior_jax.runs.run_dir import prepare_run_dir

    built = datasets.build("toy_point", seed=3, steps=200, preset="smoke", progress=False)
    cfg = presets.train_preset("toy_point", registry.REFERENCE, "smoke", steps=200, seeds=(3,),
                               eval_every=100, checkpoint_every=100, out=str(tmp_path / "sac"))
    train(cfg, prepare_run_dir(cfg), progress=False)
    made = datasets.from_run(tmp_path / "sac")
    for name in ("train_obs", "train_act", "train_reward", "test_obs", "test_reward",
                 "pair_index", "pair_label"):
        np.testing.assert_array_equal(getattr(made, name), getattr(built, name), err_msg=name)
    assert (made.info["seed"], made.info["steps"], made.segment_len) == (3, 200, built.segment_len)
    with pytest.raises(ValueError, match="--seed 4 is not in this run"):
        datasets.from_run(tmp_path / "sac", seed=4)


def test_a_smaller_minibatch_while_every_pair_fits_in_one_is_the_same_update():
    """The lab trains with a 16/32/64-row minibatch while the labels fit in it: the epoch is
    the same single minibatch of the real pairs, only with less padding."""
    import jax

    from hprior_jax.buffers import preferences
    from hprior_jax.lab.rounds import minibatch_size
    from hprior_jax.networks.reward_ensemble import init_reward_ensemble
    from hprior_jax.pbrl.preference import make_optimizer, train_reward

    assert [minibatch_size(n, 128) for n in (1, 16, 17, 25, 64, 65, 128, 400)] == [
        16, 16, 32, 32, 64, 128, 128, 128]
    rng = np.random.default_rng(0)
    store = preferences.init(T, 4, 2, capacity=100)
    batch = preferences.PreferenceBatch(*(rng.normal(size=(25, T, d)).astype(np.float32)
                                          for d in (4, 2, 4, 2)), labels=rng.integers(0, 2, 25))
    store = preferences.add(store, batch, np.ones(25, bool))
    reward_cfg = RewardConfig(hidden_sizes=(32, 32), ensemble_size=3)
    params = init_reward_ensemble(jax.random.PRNGKey(0), 4, 2, reward_cfg)
    out = {}
    for size in (32, 128):
        cfg = PreferenceConfig(batch_size=size, max_epochs=5, lr=1e-3)
        tx = make_optimizer(cfg)
        out[size], _, m = train_reward(params, tx.init(params), store, jax.random.PRNGKey(1),
                                       tx=tx, reward_cfg=reward_cfg, cfg=cfg)
        assert int(m["reward/epochs"]) == 5
    for a, b in zip(jax.tree.leaves(out[32]), jax.tree.leaves(out[128])):
        np.testing.assert_allclose(a, b, atol=1e-6)


@pytest.mark.slow  # CI time (42 s)
def test_one_shot_trains_each_budget_afresh_on_all_its_labels(data):
    cfg = tiny(rules=("pebble",), credits=("none",), seeds=(0,), budgets=(10, 20),
               one_shot=True, world_model=None)
    reached = []
    rows = Lab(cfg, data).run(on_budget=reached.append, **quiet)
    assert [(r["budget"], r["labels"]) for r in rows] == [(10, 10), (20, 20)]
    assert reached == [[rows[0]], [rows[1]]]  # each budget's rows as it is reached
    assert all(r["epochs"] >= 1 for r in rows)


def test_surf_rule_stores_longer_segments_and_its_teacher_judges_the_middle(data):
    """One lab round of SURF's own program: stored segments are H + 2w, labels are the
    oracle's on the middle H (on this task reward = obs[0] > 0, so they can be recomputed from
    the stored observations, and on some pairs the whole segment would order them otherwise),
    the pool gets inv_label_ratio x queries pairs, and the update runs SURF's
    ceil(epochs x labels / batch) iterations."""
    import jax
    import jax.numpy as jnp

    from hprior_jax.lab.config import Episodes
    from hprior_jax.lab.surf_round import SurfLabRule
    from hprior_jax.methods.surf import SurfConfig

    cfg = tiny(rules=("pebble",), credits=("none",), world_model=None)
    rule = SurfLabRule(cfg=SurfConfig(), segment_len=T)
    assert rule.stored_len == T + 10
    train = Episodes(obs=jnp.asarray(data.train_obs), act=jnp.asarray(data.train_act),
                     reward=jnp.asarray(data.train_reward))
    cell = rule.init(jax.random.PRNGKey(0), 40, 4, 2, cfg)
    cell, m = jax.jit(partial(rule.round, lab=cfg, queries=40, feed="uniform",
                              episode_length=data.episode_length))(
        cell, jnp.int32(40), jnp.asarray(True), train, jnp.float32(5.0))
    prefs = jax.tree.map(np.asarray, cell.prefs)
    n = int(prefs.count)
    assert prefs.obs1.shape[1] == T + 10 and 30 <= n <= 40 and int(m["labels"]) == n
    assert int(cell.pool.count) == 40 * SurfConfig().inv_label_ratio
    middle = lambda o: (o[:n, 5:5 + T, 0] > 0).sum(1)
    whole = lambda o: (o[:n, :, 0] > 0).sum(1)
    np.testing.assert_array_equal(prefs.labels[:n], middle(prefs.obs2) > middle(prefs.obs1))
    assert ((whole(prefs.obs2) > whole(prefs.obs1)) != prefs.labels[:n].astype(bool)).any()
    assert int(m["epochs"]) == -(-cfg.preference.max_epochs * n // cfg.preference.batch_size)


@pytest.mark.slow  # CI time (~40 s)
def test_surf_rule_runs_beside_the_shared_program_and_reports_every_budget(data):
    from hprior_jax.lab.surf_round import SurfLabRule
    from hprior_jax.methods.surf import SurfConfig

    rule = SurfLabRule(cfg=SurfConfig(), segment_len=T)
    cfg = tiny(rules=("pebble", "surf"), credits=("none", "own_program"),
               own_rules=(("surf", rule),), world_model=None, seeds=(0, 1))
    cells = by_cell(Lab(cfg, data).run(**quiet))
    for seed in (0, 1):
        for budget in (20, 50):
            surf, pebble = cells[(seed, "surf", budget)], cells[(seed, "pebble", budget)]
            assert surf["labels"] == pebble["labels"] == budget
            assert np.abs(surf["prediction"] - pebble["prediction"]).mean() > 1e-3
    with pytest.raises(ValueError, match="lab rule object"):
        tiny(rules=("pebble", "surf"), credits=("none", "own_program"), own_rules=())


def test_a_dataset_cache_file_is_named_by_the_code_that_builds_it(monkeypatch, tmp_path):
    """Two builds at one commit agree on one machine; other code may give other episodes, so
    the cache file of a build names the digest of the code it runs (the SAC run's modules,
    not the lab's own)."""
    from hprior_jax.lab import dataset

    monkeypatch.setenv("HPRIOR_LAB_CACHE", str(tmp_path))
    digest = dataset.build_code_digest()
    path = dataset.dataset_path("cheetah_run", 0, 50_000, "reduced")
    assert path.parent == tmp_path and path.name.endswith(f"_code{digest}.npz")
    assert dataset.dataset_path("cheetah_run", 0, 50_000, "reduced", physics=True) != path
    # the training loop is in the digest; the lab's modules are not
    monkeypatch.setattr(dataset, "_NOT_BUILD_CODE", (*dataset._NOT_BUILD_CODE, "loop"))
    assert dataset.build_code_digest() != digest
    monkeypatch.setattr(dataset, "_NOT_BUILD_CODE", tuple(n for n in dataset._NOT_BUILD_CODE
                                                          if n not in ("loop", "lab")))
    assert dataset.build_code_digest() != digest
