"""What a renderer draws for a task: a render-only MuJoCo model beside the physics model.

A port's physics model (`task.mj_model`) may leave out what a person needs to see (the
MetaWorld ports delete every visual geom, the table and the floor). A port registers, for its
physics model, a factory of its `RenderScene`: a model with the same joints and mocap bodies
(qpos, qvel and mocap poses copy over as they are) plus what only shows (meshes, materials,
table, floor, sky), whose geoms collide with nothing. `render_scene(mj_model)` returns it,
built once; a model nobody registered is drawn as it is. The physics model is never touched.
Drawing (OpenGL, video files) is `hprior_jax.render`'s: nothing here draws.
"""
from __future__ import annotations

import copy
import dataclasses
import threading
import weakref
from typing import Callable

import mujoco
import numpy as np

from tasks.base import RENDER_FIELDS

PLACEMENT = "placement"  # a render state's extra field: the placed body's position [3]


@dataclasses.dataclass
class RenderScene:
    """A render-only model and how a task's render state poses it."""

    model: mujoco.MjModel
    # bodies (ids in `model`) of what the task is judged by: the manipulated object, the robot
    object_bodies: tuple[int, ...]
    # a camera of `model` by name, a free camera {lookat, distance, azimuth, elevation}, or
    # None: the model's first camera, else a free camera on the scene
    camera: str | dict | None = None
    placed_body: int | None = None  # body whose `body_pos` a state's PLACEMENT sets
    # goal markers: (forwarded data) -> {site name: world position}
    goal_sites: Callable[[mujoco.MjData], dict[str, np.ndarray]] | None = None

    def pose(self, model: mujoco.MjModel, data: mujoco.MjData, states: dict, t: int) -> None:
        """Row t of `states` ({field: [T, ...]}, `Task.render_state`'s fields) put into
        `model` (a copy of `self.model`: the placement edits it) and `data`, forwarded."""
        for name in RENDER_FIELDS:
            if name in states and getattr(data, name).size:
                getattr(data, name)[:] = states[name][t]
        if self.placed_body is not None and PLACEMENT in states:
            model.body_pos[self.placed_body] = states[PLACEMENT][t]
        mujoco.mj_forward(model, data)
        if self.goal_sites is not None:
            for name, pos in self.goal_sites(data).items():
                data.site_xpos[model.site(name).id] = pos


def subtree(model: mujoco.MjModel, root: int) -> tuple[int, ...]:
    """`root` and every body below it."""
    out = []
    for b in range(model.nbody):  # parents come before their children
        if b == root or (b and model.body_parentid[b] in out):
            out.append(b)
    return tuple(out)


def joint_layout(model: mujoco.MjModel) -> tuple:
    """What must agree for a physics state to pose a render model: joint names and types in
    order, nq, nv and the mocap bodies."""
    joints = tuple((model.joint(j).name, int(model.jnt_type[j])) for j in range(model.njnt))
    return joints, model.nq, model.nv, model.nmocap


def plain_scene(mj_model: mujoco.MjModel, camera: str | None = None) -> RenderScene:
    """The model drawn as it is (a copy), judged by every body but the world."""
    return RenderScene(model=copy.copy(mj_model),
                       object_bodies=tuple(range(1, mj_model.nbody)), camera=camera)


_LOCK = threading.Lock()
_FACTORIES: dict[int, Callable[[mujoco.MjModel], RenderScene]] = {}
_BUILT: dict[int, RenderScene] = {}


def _forget(key: int) -> None:
    with _LOCK:
        _FACTORIES.pop(key, None)
        _BUILT.pop(key, None)


def register_render_scene(mj_model: mujoco.MjModel,
                          factory: Callable[[mujoco.MjModel], RenderScene]) -> None:
    """`factory(mj_model)` builds the render scene of physics model `mj_model` on first use.
    The entry goes with the model (the factory must not hold it)."""
    key = id(mj_model)
    with _LOCK:
        _FACTORIES[key] = factory
        _BUILT.pop(key, None)
    weakref.finalize(mj_model, _forget, key)


def render_scene(mj_model: mujoco.MjModel) -> RenderScene:
    """The registered render scene of physics model `mj_model`, else `plain_scene`."""
    key = id(mj_model)
    with _LOCK:
        if key in _BUILT:
            return _BUILT[key]
        factory = _FACTORIES.get(key)
        if factory is None:
            return plain_scene(mj_model)
        scene = _BUILT[key] = factory(mj_model)
        if joint_layout(scene.model) != joint_layout(mj_model):
            del _BUILT[key]
            raise ValueError("the render scene's joints or mocap bodies differ from the "
                             "physics model's: states cannot pose it")
    return scene
