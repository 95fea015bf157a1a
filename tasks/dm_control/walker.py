"""dm_control `walker` `walk` on MJX (dm_control/suite/walker.py), its walker.xml unchanged.

Observation (24), dm_control's order flattened as dmc2gym does: orientations (xx, xz of the 7
bodies' xmat, 14), torso height (1), qvel (9). Reward: stand = (3 standing + upright) / 4,
move = tolerance(torso subtree x velocity, (1, inf), margin 0.5, value 0.5, linear), reward =
stand (5 move + 1) / 6. Control timestep 0.025 s = 10 substeps, 25 s -> 1000 steps. Reset:
`rooty` uniform in [-pi, pi], limited hinges uniform in their range, zero velocity, an
actuation-free forward, no settling (dm_control's distribution, jax.random's stream).

Parity (`python -m benchmarks.ports.dm_control_parity --tasks walker_walk`): same state, obs within
1.8e-6, reward within 1.5e-7; same actions from dm_control's reset, return within 3.0e-5
over 20 steps (chaos parts the trajectories after that); random-policy return 32.1 vs 32.4
(10 episodes). Details: docs/ports/dm_control.md.
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
# held actions (`python -m benchmarks.ports.env_profile --census-counts`), and a cap of 10 stepped
# only 1.17x faster at batch 128 (12: no gain), too little for so thin a margin
MAX_CONTACTS = None


class WalkerWalk(DMControlTask):
    name = "walker_walk"
    goal_text = "Walk forward while staying upright, torso high."
    suite = ("walker", "walk")
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
