"""dm_control `quadruped` `walk` on MJX (dm_control/suite/quadruped.py).

Model: dm_control's own `quadruped.make_model(floor_size=10)`, unedited. Observation (78):
egocentric state (44), torso velocity (3), torso upright (1), imu (6), arcsinh of the toe
forces and torques (24); acceleration-stage sensors one substep old, as after dm_control's
legacy step. Reward: upright x move. Control timestep 0.02 s = 4 substeps, 20 s -> 1000
steps. Reset: a uniform random orientation, hinges at 0, dropped to dm_control's
non-contacting height, computed in closed form (`non_contacting_height`) instead of its 1 cm
search.

Parity (`python -m benchmarks.ports.dm_control_parity --tasks quadruped_walk`): same state, obs
within 4.1e-4, reward within 8.3e-8; reset height equal to dm_control's search on 200 of 200
orientations; same actions, return within 2.3e-4 over 20 steps; returns are bimodal (upright
or not): zero-action episodes upright at step 300, 0.217 vs 0.183 of 60 resets. Details:
docs/ports/dm_control.md.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from tasks.dm_control.common import DMControlTask
from tasks.physics import mjx, with_max_contacts
from tasks.rewards import tolerance

CONTROL_TIMESTEP = 0.02
TIME_LIMIT = 20.0
WALK_SPEED = 0.5
HEIGHT_STEP = 0.01  # dm_control's increment in _find_non_contacting_height
# MJX's contact cap (tasks.physics.with_max_contacts): 35 candidate floor contacts; C MuJoCo
# held at most 6 at once over 60 episodes of random, bang-bang and held actions
# (`python -m benchmarks.ports.env_profile --census-counts`); 8 steps 2.1x faster at batch 128
MAX_CONTACTS = 8


def load_quadruped_model(floor_size: float, max_contacts: int | None = None) -> mujoco.MjModel:
    """dm_control's quadruped XML, edited by dm_control's own `make_model` as `walk` does
    (and MJX's contact cap, `tasks.physics.with_max_contacts`)."""
    from dm_control.suite import common, quadruped

    xml = quadruped.make_model(floor_size=floor_size)
    return mujoco.MjModel.from_xml_string(with_max_contacts(xml, max_contacts), common.ASSETS)


def _sensor_ids(model: mujoco.MjModel, *types) -> np.ndarray:
    """Sensordata indices of all sensors of `types`, in model order (dm_control's order)."""
    types = {int(t) for t in types}  # mujoco enums do not compare equal to numpy ints
    idx = []
    for s in range(model.nsensor):
        if int(model.sensor_type[s]) in types:
            adr, dim = model.sensor_adr[s], model.sensor_dim[s]
            idx.extend(range(adr, adr + dim))
    if not idx:
        raise KeyError(f"no sensors of types {sorted(types)} in model")
    return np.asarray(idx, np.int32)


class QuadrupedWalk(DMControlTask):
    name = "quadruped_walk"
    goal_text = "Walk forward."
    suite = ("quadruped", "walk")
    obs_size = 78
    render_camera = "y"  # tracks the torso from the side (the first, "global", is far)

    def __init__(self, desired_speed: float = WALK_SPEED, contacts: str = "floor",
                 max_contacts: int | None = MAX_CONTACTS):
        model = load_quadruped_model(TIME_LIMIT * WALK_SPEED, max_contacts)
        super().__init__(model, control_timestep=CONTROL_TIMESTEP, time_limit=TIME_LIMIT,
                         contacts=contacts)
        self.desired_speed = desired_speed
        self._torso = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "torso")
        hinges = np.flatnonzero(model.jnt_type == int(mujoco.mjtJoint.mjJNT_HINGE))
        self._hinge_qpos = jnp.asarray(model.jnt_qposadr[hinges])
        self._hinge_qvel = jnp.asarray(model.jnt_dofadr[hinges])
        st = mujoco.mjtSensor
        self._imu = jnp.asarray(_sensor_ids(model, st.mjSENS_GYRO, st.mjSENS_ACCELEROMETER))
        self._ft = jnp.asarray(_sensor_ids(model, st.mjSENS_FORCE, st.mjSENS_TORQUE))
        self._velocimeter = jnp.asarray(_sensor_ids(model, st.mjSENS_VELOCIMETER))
        root = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, "root")
        assert int(model.jnt_type[root]) == int(mujoco.mjtJoint.mjJNT_FREE)
        self._root_qpos = int(model.jnt_qposadr[root])
        # geoms that can touch the floor in the reset search: every non-world geom
        gt = mujoco.mjtGeom
        body_geoms = np.flatnonzero(model.geom_bodyid != 0)
        supported = {gt.mjGEOM_SPHERE, gt.mjGEOM_CAPSULE, gt.mjGEOM_ELLIPSOID, gt.mjGEOM_CYLINDER}
        if not set(model.geom_type[body_geoms].tolist()) <= {int(t) for t in supported}:
            raise NotImplementedError("quadruped reset: unexpected geom type")
        self._body_geoms = jnp.asarray(body_geoms)
        self._geom_type = jnp.asarray(model.geom_type[body_geoms])
        self._geom_size = jnp.asarray(model.geom_size[body_geoms], jnp.float32)

    # -- reset ------------------------------------------------------------------------
    def _floor_penetration(self, data: mjx.Data) -> jax.Array:
        """Depth of the lowest point of any body geom below z=0 (geom poses from kinematics)."""
        gt = mujoco.mjtGeom
        z = data.geom_xpos[self._body_geoms, 2]
        rz = data.geom_xmat[self._body_geoms, 2, :]  # world-z row: z-components of local axes
        size = self._geom_size
        axial = jnp.abs(rz[:, 2])
        sphere = size[:, 0]
        capsule = axial * size[:, 1] + size[:, 0]
        ellipsoid = jnp.sqrt(jnp.sum((rz * size) ** 2, axis=-1))
        cylinder = axial * size[:, 1] + size[:, 0] * jnp.sqrt(jnp.maximum(1 - axial**2, 0.0))
        t = self._geom_type
        extent = jnp.where(t == int(gt.mjGEOM_SPHERE), sphere,
                 jnp.where(t == int(gt.mjGEOM_CAPSULE), capsule,
                 jnp.where(t == int(gt.mjGEOM_ELLIPSOID), ellipsoid, cylinder)))
        return -jnp.min(z - extent)

    def non_contacting_height(self, quat: jax.Array) -> jax.Array:
        """z that dm_control's `_find_non_contacting_height` picks for `quat` (closed form)."""
        data = mjx.make_data(self.model)
        r = self._root_qpos
        # root at the origin (qpos0 holds the XML's torso height, dm_control overwrites it)
        qpos = data.qpos.at[r : r + 3].set(0.0).at[r + 3 : r + 7].set(quat)
        data = mjx.kinematics(self.model, data.replace(qpos=qpos))
        depth = self._floor_penetration(data)
        k = jnp.maximum(jnp.floor(depth / HEIGHT_STEP) + 1, 0.0)
        return k * HEIGHT_STEP

    def _initial_data(self, key: jax.Array) -> mjx.Data:
        quat = jax.random.normal(key, (4,))
        quat = quat / jnp.linalg.norm(quat)
        return self.initial_data_from_orientation(quat)

    def initial_data_from_orientation(self, quat: jax.Array) -> mjx.Data:
        data = mjx.make_data(self.model)
        z = self.non_contacting_height(quat)
        r = self._root_qpos
        qpos = data.qpos.at[r : r + 3].set(jnp.stack([0.0, 0.0, z]))
        qpos = qpos.at[r + 3 : r + 7].set(quat)
        return self.reset_forward(data.replace(qpos=qpos))

    # -- dm_control's Physics helpers -------------------------------------------------
    def torso_upright(self, data: mjx.Data) -> jax.Array:
        return data.xmat[self._torso, 2, 2]

    def torso_velocity(self, data: mjx.Data) -> jax.Array:
        return data.sensordata[self._velocimeter]

    def egocentric_state(self, data: mjx.Data) -> jax.Array:
        return jnp.concatenate([data.qpos[self._hinge_qpos], data.qvel[self._hinge_qvel],
                                data.act])

    def imu(self, data: mjx.Data) -> jax.Array:
        return data.sensordata[self._imu]

    def force_torque(self, data: mjx.Data) -> jax.Array:
        return jnp.arcsinh(data.sensordata[self._ft])

    def _observation(self, data: mjx.Data) -> jax.Array:
        return jnp.concatenate([
            self.egocentric_state(data), self.torso_velocity(data),
            self.torso_upright(data)[None], self.imu(data), self.force_torque(data),
        ]).astype(jnp.float32)

    def _reward(self, data: mjx.Data) -> jax.Array:
        move = tolerance(self.torso_velocity(data)[0],
                         bounds=(self.desired_speed, float("inf")), margin=self.desired_speed,
                         value_at_margin=0.5, sigmoid="linear")
        # _upright_reward with deviation_angle=0: cos(0) = 1
        upright = tolerance(self.torso_upright(data), bounds=(1.0, float("inf")),
                            sigmoid="linear", margin=2.0, value_at_margin=0.0)
        return upright * move
