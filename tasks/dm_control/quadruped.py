"""dm_control `quadruped` `walk` on MJX (dm_control/suite/quadruped.py).

Model: built at run time by dm_control's own `quadruped.make_model(floor_size=10)` (the
walk task's call): no walls, ball, target, heightfield terrain geom or rangefinders. The
unused `terrain` hfield *asset* stays in the model; no geom refers to it, so MJX never
collides with it (MJX's heightfield collision would not be needed for this task). Nothing
else is edited: MJX supports every feature walk uses (ellipsoid/capsule/sphere/cylinder
collisions incl. self-collisions, fixed tendons with tendon equality constraints, filter
actuators with `act`, accelerometer/gyro/velocimeter/force/torque/subtreecom sensors).

Observation (78), dm_control's OrderedDict order, flattened as dmc2gym does:
  egocentric_state (44) = qpos of the 16 hinges, qvel of the 16 hinges, act (12);
  torso_velocity (3)    = velocimeter sensor (torso frame);
  torso_upright (1)     = xmat['torso', zz];
  imu (6)               = sensors of type gyro/accelerometer in model order (imu_accel, imu_gyro);
  force_torque (24)     = arcsinh of the force (4x3) then torque (4x3) sensors at the toes.
Reward: upright = tolerance(torso_upright, (1, inf), margin 2, linear, value_at_margin 0);
move = tolerance(torso_velocity x, (0.5, inf), margin 0.5, value_at_margin 0.5, linear);
reward = upright * move. Control timestep 0.02 s = 4 substeps of 0.005 s; 20 s -> 1000 steps.

Acceleration-stage sensors (accelerometer, force, torque): after dm_control's legacy
`physics.step`, they hold what the *last* `mj_step2` computed, i.e. at the state before the
last integration; `legacy_substeps` runs `mjx.sensor_acc` inside its last step2 as well, so
the observation carries the same one-substep-old values (checked in the parity tests). After
a reset they come from `mj_forward` with actuation disabled (dm_control's `reset_context`),
reproduced with `DMControlTask.reset_forward`.

Reset (Move.initialize_episode): orientation = normalised 4-D standard normal (uniform on
the unit quaternions), hinges at 0, zero velocity and activation; dm_control then raises the
torso from z=0 in 1 cm increments, each time running `mj_forward` and counting contacts,
until there are none (`_find_non_contacting_height`, up to 10 000 tries). That loop is not
jit-friendly, so we compute its answer in closed form: with hinges at 0 no body geoms touch
each other, so the only contacts are with the floor plane; for each body geom we take its
lowest point at z=0 from the geom's pose (sphere: c-r; capsule: c-|R_zz|h-r; ellipsoid:
c-|R_z. * size|; cylinder: c-|R_zz|h-r*sqrt(1-R_zz^2)), so the penetration depth is
D = -min(lowest), and dm_control stops at the first k with 0.01 k > D: z = 0.01 (floor(D/0.01)+1).
Differences: dm_control accumulates z by repeated float64 additions of 0.01 (off by ~1e-16)
and counts a contact at exactly zero distance; we evaluate in float32, so the chosen height
can differ by one 1 cm step only when D lies within ~1e-6 m of a multiple of 1 cm (the
parity tests compare heights for many orientations). There is no 10 000-try cap (D < 1 m
always). The random stream is jax.random, so a seed does not give dm_control's pose.
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
# (`python -m benchmarks.env_profile --census-counts`); 8 steps 2.1x faster at batch 128
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
    obs_size = 78

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
