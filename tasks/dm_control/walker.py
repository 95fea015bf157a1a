"""dm_control `walker` `walk` on MJX (dm_control/suite/walker.py).

Model: dm_control's walker.xml, unchanged (MJX supports everything it uses: capsules on a
plane, slide/hinge joints with limits, motors, a subtreelinvel sensor).

Observation (24), in dm_control's OrderedDict order, flattened as dmc2gym does:
  orientations (14) = xmat[1:, (xx, xz)] of the 7 bodies, row-major (body, component);
  height (1)        = xpos['torso', z];
  velocity (9)      = qvel.
Reward: standing = tolerance(height, (1.2, inf), margin 0.6) (gaussian, value 0.1 at the
margin); upright = (1 + xmat['torso', zz]) / 2; stand = (3 standing + upright) / 4;
move = tolerance(torso subtree linear velocity x, (1, inf), margin 0.5, value_at_margin 0.5,
linear); reward = stand * (5 move + 1) / 6.
Control timestep 0.025 s = 10 physics substeps of 0.0025 s; time limit 25 s -> 1000 steps.

Reset (randomizers.randomize_limited_and_rotational_joints): the unlimited hinge `rooty` is
uniform in [-pi, pi], every limited hinge uniform in its range, the root slides stay at 0
(torso at its XML height 1.3 m), velocities zero, then `mj_forward` with actuation disabled.
No settling: like dm_control, an episode may start with a limb below the floor. The only
difference is the random stream (jax.random instead of numpy's RandomState), so resets draw
from the same distribution but a given seed does not give the same pose.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from tasks.dm_control.common import DMControlTask, load_suite_model
from tasks.physics import mjx
from tasks.rewards import tolerance

CONTROL_TIMESTEP = 0.025
TIME_LIMIT = 25.0
STAND_HEIGHT = 1.2
WALK_SPEED = 1.0
# No MJX contact cap (tasks.physics.with_max_contacts): of 14 candidate floor contacts (7
# capsules, 2 each) C MuJoCo held up to 10 at once in 60 episodes of random, bang-bang and
# held actions (`python -m benchmarks.env_profile --census-counts`), and a cap of 10 stepped
# only 1.17x faster at batch 128 (12: no gain), too little for so thin a margin
MAX_CONTACTS = None


class WalkerWalk(DMControlTask):
    name = "walker_walk"
    obs_size = 24

    def __init__(self, move_speed: float = WALK_SPEED, contacts: str = "floor",
                 max_contacts: int | None = MAX_CONTACTS):
        model = load_suite_model("walker", max_contacts)
        super().__init__(model, control_timestep=CONTROL_TIMESTEP, time_limit=TIME_LIMIT,
                         contacts=contacts)
        self.move_speed = move_speed
        self._torso = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "torso")
        # randomize_limited_and_rotational_joints, restricted to the joint kinds walker has
        lo, hi, adr = [], [], []
        for j in range(model.njnt):
            jtype = int(model.jnt_type[j])
            if jtype not in (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE)):
                raise NotImplementedError("walker port expects hinge/slide joints only")
            if model.jnt_limited[j]:
                lo.append(model.jnt_range[j, 0]), hi.append(model.jnt_range[j, 1])
            elif jtype == int(mujoco.mjtJoint.mjJNT_HINGE):
                lo.append(-np.pi), hi.append(np.pi)
            else:  # unlimited slides (rootx, rootz) are not randomised
                continue
            adr.append(model.jnt_qposadr[j])
        self._rand_adr = jnp.asarray(adr)
        self._rand_lo = jnp.asarray(lo, jnp.float32)
        self._rand_hi = jnp.asarray(hi, jnp.float32)

    def _initial_data(self, key: jax.Array) -> mjx.Data:
        data = mjx.make_data(self.model)
        sample = jax.random.uniform(key, self._rand_lo.shape,
                                    minval=self._rand_lo, maxval=self._rand_hi)
        data = data.replace(qpos=data.qpos.at[self._rand_adr].set(sample))
        return self.reset_forward(data)

    # -- dm_control's Physics helpers -------------------------------------------------
    def torso_upright(self, data: mjx.Data) -> jax.Array:
        return data.xmat[self._torso, 2, 2]

    def torso_height(self, data: mjx.Data) -> jax.Array:
        return data.xpos[self._torso, 2]

    def horizontal_velocity(self, data: mjx.Data) -> jax.Array:
        return self.sensor(data, "torso_subtreelinvel")[0]

    def orientations(self, data: mjx.Data) -> jax.Array:
        # xmat rows are (xx xy xz / yx yy yz / zx zy zz); dm_control takes xx and xz
        return data.xmat[1:, 0, :][:, jnp.array([0, 2])].ravel()

    def _observation(self, data: mjx.Data) -> jax.Array:
        return jnp.concatenate([
            self.orientations(data), self.torso_height(data)[None], data.qvel,
        ]).astype(jnp.float32)

    def _reward(self, data: mjx.Data) -> jax.Array:
        standing = tolerance(self.torso_height(data), bounds=(STAND_HEIGHT, float("inf")),
                             margin=STAND_HEIGHT / 2)
        upright = (1 + self.torso_upright(data)) / 2
        stand_reward = (3 * standing + upright) / 4
        if self.move_speed == 0:
            return stand_reward
        move_reward = tolerance(self.horizontal_velocity(data),
                                bounds=(self.move_speed, float("inf")),
                                margin=self.move_speed / 2, value_at_margin=0.5,
                                sigmoid="linear")
        return stand_reward * (5 * move_reward + 1) / 6
