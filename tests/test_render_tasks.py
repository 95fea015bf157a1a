"""Every registered task renders what a person judges it by: one small frame per task from
its render scene (`tasks.render_scene`), with MuJoCo's segmentation telling which pixels
show the task's object (MetaWorld: the manipulated drawer, button, door, window, lock or
puck; DM Control: the robot). Those pixels must be there and must not be black or the
background. No MJX: the states are posed with C MuJoCo."""
import copy

import mujoco
import numpy as np
import pytest

import tasks
from hprior_jax.render import default_camera, render_frames
from tasks.render_scene import PLACEMENT, joint_layout, render_scene, subtree
from tests.toy_task import TOYS

W, H = 160, 120
# the MuJoCo ports (not the model-less toy tasks the tests register)
PORTS = [n for n in tasks.names() if n not in {c.name for c in TOYS}]


def _state(task) -> dict:
    """A render state [1, ...] of the task at rest: MetaWorld's settled hand at its start
    (the object at its XML placement); DM Control's model at qpos0."""
    m = task.mj_model
    d = mujoco.MjData(m)
    if task.domain == "metaworld":
        d.qpos[:] = task._settled["qpos"]
        d.mocap_pos[task._hand_mocap] = task.scene.hand_init_pos
    mujoco.mj_kinematics(m, d)
    return {k: np.asarray(v)[None] for k, v in task.render_state(d).items()}


def _pixels_of(seg: np.ndarray, model: mujoco.MjModel, bodies) -> np.ndarray:
    geoms = np.flatnonzero(np.isin(model.geom_bodyid, list(bodies)))
    return (seg[..., 1] == int(mujoco.mjtObj.mjOBJ_GEOM)) & np.isin(seg[..., 0], geoms)


def _without(task, bodies, states) -> np.ndarray:
    """The same frame with the geoms of `bodies` hidden: what lies behind them."""
    from hprior_jax.render import _install_gl_context

    _install_gl_context()
    scene = render_scene(task.mj_model)
    model = copy.copy(scene.model)
    model.geom_group[np.isin(model.geom_bodyid, list(bodies))] = 5  # a group not drawn
    data = mujoco.MjData(model)
    scene.pose(model, data, states, 0)
    with mujoco.Renderer(model, H, W) as renderer:
        renderer.update_scene(data, camera=default_camera(task.mj_model))
        return renderer.render()


@pytest.mark.parametrize("name", PORTS)
def test_task_object_is_drawn(name):
    task = tasks.make(name)
    states = _state(task)
    scene = render_scene(task.mj_model)
    assert joint_layout(scene.model) == joint_layout(task.mj_model)
    rgb = render_frames(task.mj_model, states, width=W, height=H)[0]
    seg = render_frames(task.mj_model, states, width=W, height=H, segmentation=True)[0]
    mask = _pixels_of(seg, scene.model, scene.object_bodies)
    assert mask.sum() >= 25, f"{name}: the object covers {mask.sum()} pixels"
    shown = rgb[mask].astype(float)
    assert shown.mean() > 25, f"{name}: the object is drawn black"
    behind = _without(task, scene.object_bodies, states)[mask].astype(float)
    assert np.abs(shown - behind).mean() > 15, f"{name}: the object looks like the background"
    if task.domain == "metaworld":  # the hand, the table and the floor are drawn too
        m = scene.model
        for body in ("hand", "tablelink"):
            shown = _pixels_of(seg, m, subtree(m, m.body(body).id))
            assert shown.sum() >= 15, f"{name}: {body} covers {shown.sum()} pixels"
        assert (seg[..., 0] == -1).mean() < 0.5, f"{name}: mostly empty sky"


def test_placement_moves_the_object_and_goal_and_leaves_physics_alone():
    """metaworld moves the object by editing model.body_pos at reset: the render state's
    placement moves it on screen, the goal marker follows; the physics model is unchanged."""
    task = tasks.make("drawer_open")
    before = task.mj_model.body_pos.copy(), task.mj_model.ngeom, task.mj_model.npair
    scene = render_scene(task.mj_model)
    states = _state(task)
    moved = dict(states, **{PLACEMENT: states[PLACEMENT] + [0.1, 0.0, 0.0]})
    both = {k: np.concatenate([states[k], moved[k]]) for k in states}
    seg = render_frames(task.mj_model, both, width=W, height=H, segmentation=True)
    cols = [np.argwhere(_pixels_of(s, scene.model, scene.object_bodies))[:, 1].mean()
            for s in seg]
    assert abs(cols[1] - cols[0]) > 3, cols  # the drawer moved sideways on screen
    goal = scene.model.site("goal").id
    sites = [(s[..., 1] == int(mujoco.mjtObj.mjOBJ_SITE)) & (s[..., 0] == goal) for s in seg]
    assert all(s.any() for s in sites), "the goal marker is not drawn"
    assert np.argwhere(sites[1])[:, 1].mean() != np.argwhere(sites[0])[:, 1].mean()
    after = task.mj_model.body_pos, task.mj_model.ngeom, task.mj_model.npair
    np.testing.assert_array_equal(before[0], after[0])
    assert before[1:] == after[1:]
