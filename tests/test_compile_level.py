"""`--compile-level`: which XLA optimisation level a run's programs compile at."""
import os
import warnings

import jax
import pytest

import tasks
from hprior_jax import presets
from hprior_jax.agents.sac import SACConfig
from hprior_jax.config import RunConfig
from hprior_jax.runs.build import build_engine
from hprior_jax.setup_jax import LEVEL_OPTION, PHYSICS_FREE, compiler_options, program_options


def test_the_level_follows_the_flag_the_task_and_xla_flags(monkeypatch):
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_use_fusion_emitters=false")
    assert compiler_options("task", 1) == {LEVEL_OPTION: 1}
    assert compiler_options("task", None) == {}
    assert compiler_options("xla", 1) == {}
    assert compiler_options("2", None) == {LEVEL_OPTION: 2}
    # a level in XLA_FLAGS (the suite's -O0, a user's choice) wins over the task's only
    monkeypatch.setenv("XLA_FLAGS", f"--{LEVEL_OPTION}=0")
    assert compiler_options("task", 1) == {}
    assert compiler_options("3", 1) == {LEVEL_OPTION: 3}


def test_the_tasks_cpu_levels_stay_off_other_backends(monkeypatch):
    monkeypatch.setenv("XLA_FLAGS", "")
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    assert compiler_options("task", 1) == {}
    assert compiler_options("1", 1) == {LEVEL_OPTION: 1}  # asked for, it is set anywhere


@pytest.mark.parametrize("jaxlib, needed", [("0.10.2", True), ("0.11.2", False),
                                            ("1.0.0", False)])
def test_the_fusion_flag_only_for_jaxlibs_that_know_it(monkeypatch, jaxlib, needed):
    """jaxlib 0.11 aborts on the removed flag (a GPU machine's own jax runs the suite)."""
    from tasks import _xla_flags

    monkeypatch.setattr(_xla_flags.metadata, "version", lambda name: jaxlib)
    assert _xla_flags.jaxlib_needs_fusion_flag() is needed
    monkeypatch.setenv("XLA_FLAGS", "")
    with warnings.catch_warnings():  # jax is imported already: the too-late warning
        warnings.simplefilter("ignore")
        _xla_flags.ensure_xla_flags()
    assert (_xla_flags.FLAG in os.environ["XLA_FLAGS"]) is needed


def test_the_level_is_set_only_where_it_was_measured_faster():
    assert [tasks.info(t).compile_level for t in ("cheetah_run", "quadruped_walk")] == [1, 1]
    assert tasks.info("walker_walk").compile_level is None
    assert all(tasks.info(t).compile_level is None for t in tasks.names()
               if tasks.info(t).domain == "metaworld")


def test_runs_written_before_the_option_restore_with_xlas_level():
    old = {k: v for k, v in RunConfig(task="cheetah_run").__dict__.items()
           if k != "compile_level"}
    assert RunConfig.from_dict(old).compile_level == "xla"
    assert RunConfig().compile_level == "task"
    with pytest.raises(ValueError, match="--compile-level"):
        RunConfig(compile_level="4")


def test_every_program_of_the_run_compiles_with_the_options(tmp_path):
    cfg = presets.train_preset("toy_point", "sac", "smoke", out=str(tmp_path / "r"),
                               compile_level="0", num_eval_episodes=2,
                               sac=SACConfig(hidden_dim=16, hidden_depth=1, batch_size=8))
    engine = build_engine(cfg)
    assert engine.compiler_options == {LEVEL_OPTION: 0}
    rs = engine.init_seeds(cfg.seeds)
    # an option XLA does not know fails the compile: the options reach it
    engine.compiler_options = {"xla_no_such_option": 1}
    with pytest.raises(jax.errors.JaxRuntimeError, match="xla_no_such_option"):
        engine.run_chunk(rs, 0, 10)
    with pytest.raises(jax.errors.JaxRuntimeError, match="xla_no_such_option"):
        engine.run_eval(rs, cfg.seeds, 0)


def test_programs_without_physics_get_xlas_fusion_emitters_back_only_on_cpu(monkeypatch):
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_use_fusion_emitters=false")
    level = {LEVEL_OPTION: 1}
    assert program_options(level, physics_free=True) == {**level, **PHYSICS_FREE}
    assert program_options(level, physics_free=False) == level
    monkeypatch.setenv("XLA_FLAGS", "")  # a jaxlib without the flag: nothing to undo
    assert program_options(level, physics_free=True) == level
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_use_fusion_emitters=false")
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    assert program_options(level, physics_free=True) == level


def test_priors_world_model_programs_are_the_physics_free_ones(tmp_path, monkeypatch):
    """Only the world-model update asks (measured 1.12-1.17x faster without the flag; the
    reward epoch 0.97-1.21x, left as it is), and the option reaches its compile."""
    from hprior_jax.loop.engine import Engine

    cfg = presets.train_preset("toy_point", "prior", "smoke", out=str(tmp_path / "r"),
                               num_eval_episodes=2)
    engine = build_engine(cfg)
    asked = {}  # id(program) -> physics_free
    per_seed = Engine.per_seed

    def recording(self, fn, in_axes=(0,), donate_argnums=(), physics_free=False):
        program = per_seed(self, fn, in_axes, donate_argnums, physics_free)
        asked[id(program)] = physics_free
        return program

    monkeypatch.setattr(Engine, "per_seed", recording)
    rs = engine.init_seeds(cfg.seeds)
    programs = engine.method.programs(rs)
    assert {name: asked[id(program)] for name, program, _ in programs} == {
        name: name.startswith("world_model/") for name, *_ in programs}
    assert any(name.startswith("world_model/") for name, *_ in programs)
    monkeypatch.setitem(PHYSICS_FREE, "xla_no_such_option", 1)
    name, program, args = engine.method.programs(rs)[0]
    assert name.startswith("world_model/")
    with pytest.raises(jax.errors.JaxRuntimeError, match="xla_no_such_option"):
        program.lower(*args).compile()
