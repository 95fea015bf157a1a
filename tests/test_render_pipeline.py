"""What a person sees of a MetaWorld task through each path that renders the pipeline's own
(batched, MJX) states: `Env.render(i)` of a batch, the physics a human teacher's clips are
drawn from (the engine's recorded physics), and the episode recorder (evaluation videos,
`--capture-video`). Each frame must show the manipulated object where that environment's
physics put it: the object's pixels (segmentation) are compared with a frame posed directly
from the environment's own joints and placement (`info["placement"]`, one env, C MuJoCo),
not through `Task.render_state`."""
import copy

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco import mjx

import tasks
from hprior_jax import make_env, presets
from hprior_jax.loop.episodes import episode_states
from hprior_jax.render import render_frames
from hprior_jax.runs.build import build_engine
from tasks.metaworld.reference import ports
from tasks.render_scene import PLACEMENT, render_scene

W, H = 320, 240  # the size a person is shown
METAWORLD = ports()
# The fast suite checks `render_states` on every task without compiling a step (MJX data put
# from C MuJoCo) and `Env.render` on one; each path's own program (Env.render's reset, the
# recorder's episode scan, the engine's recorded physics) on every task runs under -m slow
FAST = "drawer_open"


def _one_fast(names):
    return [pytest.param(n, marks=() if n == FAST else pytest.mark.slow) for n in names]


def _posed(task, placement_shift) -> mujoco.MjData:
    """C MuJoCo data of `task` at rest (the settled hand), its placed body moved by
    `placement_shift` (metaworld's placement is the body's position in the model)."""
    m = copy.copy(task.mj_model)
    if task._placed_body is not None:
        m.body_pos[task._placed_body] += placement_shift
    d = mujoco.MjData(m)
    d.qpos[:] = task._settled["qpos"]
    d.mocap_pos[task._hand_mocap] = task.scene.hand_init_pos
    mujoco.mj_kinematics(m, d)
    return d


@pytest.mark.parametrize("name", METAWORLD)
def test_render_states_reads_each_envs_own_row(name):
    """A batch of two envs with two placements: row i of `Task.render_states` is env i's own
    state, and its frame shows the object where env i's physics put it."""
    task = tasks.make(name)
    shifts = [np.zeros(3), np.array([0.05, 0.0, 0.0])]
    posed = [_posed(task, s) for s in shifts]
    batch = jax.tree.map(lambda *x: jnp.stack(x), *[mjx.put_data(task.mj_model, d)
                                                    for d in posed])
    rows = {k: np.asarray(v) for k, v in task.render_states(batch).items()}
    for i, d in enumerate(posed):
        truth = {k: np.asarray(getattr(d, k))[None] for k in ("qpos", "qvel", "mocap_pos",
                                                              "mocap_quat")}
        if task._placed_body is not None:
            truth[PLACEMENT] = np.asarray(d.xpos[task._placed_body])[None]
            np.testing.assert_allclose(rows[PLACEMENT][i], truth[PLACEMENT][0], atol=1e-6)
        _assert_object_where_physics_put_it(task, {k: v[i][None] for k, v in rows.items()},
                                            truth, f"render_states row {i}")


def _object_mask(task, states) -> np.ndarray:
    """bool[T, H, W]: the pixels of the task's object (its render scene's object bodies)."""
    scene = render_scene(task.mj_model)
    seg = render_frames(task.mj_model, states, width=W, height=H, segmentation=True)
    geoms = np.flatnonzero(np.isin(scene.model.geom_bodyid, list(scene.object_bodies)))
    return (seg[..., 1] == 5) & np.isin(seg[..., 0], geoms)  # 5: mjOBJ_GEOM


def _true_states(task, data, info, rows) -> dict:
    """Render states [len(rows), ...] posed from `data`'s joints and mocap and `info`'s
    placement at `rows` of their leading axis, written out field by field."""
    fields = {k: np.asarray(getattr(data, k))[rows] for k in ("qpos", "qvel", "mocap_pos",
                                                               "mocap_quat")}
    if "placement" in info:
        fields[PLACEMENT] = np.asarray(info["placement"])[rows]
    return fields


def _assert_object_where_physics_put_it(task, shown: dict, truth: dict, where: str):
    got, want = _object_mask(task, shown), _object_mask(task, truth)
    for t in range(len(want)):
        assert want[t].sum() >= 25, f"{task.name}: the true object covers {want[t].sum()} px"
        iou = (got[t] & want[t]).sum() / (got[t] | want[t]).sum()
        assert iou > 0.95, (f"{task.name} {where} frame {t}: the object's pixels overlap its "
                            f"true position's by {iou:.2f} (IoU)")


@pytest.mark.parametrize("name", _one_fast(METAWORLD))
def test_env_render_shows_each_envs_object(name):
    """`Env.render(i)` of a batch of 2 is the frame posed from env i's own state."""
    env = make_env(name, num_envs=2, seed=1)
    env.reset()
    task, state = env.task, env.state.task
    if PLACEMENT in state.info:  # the two envs hold different placements: the row matters
        assert not np.allclose(state.info[PLACEMENT][0], state.info[PLACEMENT][1])
    for i in (0, 1):
        truth = _true_states(task, state.data, state.info, [i])
        mask = _object_mask(task, truth)[0]
        assert mask.sum() >= 25
        want = render_frames(task.mj_model, truth, width=W, height=H)[0].astype(float)
        got = env.render(i, width=W, height=H).astype(float)
        off = np.abs(got - want)[mask].mean()
        assert off < 2.0, f"{name}: Env.render({i}) differs from env {i}'s object by {off:.1f}"
        _assert_object_where_physics_put_it(
            task, {k: np.asarray(v)[i][None] for k, v in task.render_states(state.data).items()},
            truth, f"render_states row {i}")


@pytest.mark.slow
@pytest.mark.parametrize("name", METAWORLD)
def test_recorded_physics_for_a_persons_clips_shows_the_object(name):
    """The engine records `recorded_physics` of each seed's env into the replay buffer; the
    labelling page's clips are rendered from those rows."""
    cfg = presets.train_preset(name, "pebble", "smoke", seeds=(0,))
    engine = build_engine(cfg, records_physics=True)
    first = engine.env.reset(jax.random.PRNGKey(3))  # one env: [1, ...]
    recorded = jax.jit(engine.recorded_physics)(first)
    shown = {k: np.asarray(v)[None] for k, v in recorded.items()}
    truth = _true_states(engine.task, first.task.data, first.task.info, [0])
    _assert_object_where_physics_put_it(engine.task, shown, truth, "recorded physics")


@pytest.mark.slow
@pytest.mark.parametrize("name", METAWORLD)
def test_episode_recorder_shows_the_object(name):
    """Evaluation videos and `--capture-video` render `episode_states`: the first and the
    last frame of an episode show the object where the episode's own reset placed it."""
    cfg = presets.train_preset(name, "sac", "smoke", seeds=(0,))
    engine = build_engine(cfg)
    params = engine.sac.init(jax.random.PRNGKey(0)).actor
    key = jax.random.PRNGKey(5)
    states = jax.tree.map(lambda x: x[0], episode_states(engine, params, key[None]))
    first = engine.env.reset(key)
    rows = [0, len(states["qpos"]) - 1]
    shown = {k: v[rows] for k, v in states.items()}
    truth = {k: v[rows] for k, v in states.items() if k != PLACEMENT}
    if PLACEMENT in first.task.info:
        truth[PLACEMENT] = np.repeat(np.asarray(first.task.info[PLACEMENT]), 2, axis=0)
    _assert_object_where_physics_put_it(engine.task, shown, truth, "episode recorder")
