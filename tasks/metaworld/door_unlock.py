"""door-unlock-v3 (metaworld/envs/sawyer_door_unlock_v3.py, sawyer_door_lock.xml) on MJX.

Contacts: the 4 gripper geoms and the wrist x the lock lever box of `lock_link`: 5 pairs.
The door (fixed in this scene) and safe are not on the scripted solution's path. In
metaworld's own scripted episodes (contact census, C MuJoCo, 10 episodes) the lever touches
nothing but the *wrist* (the gripper base's mesh on `right_hand`: 13259 contact steps) and
swings far past its range ([0, 1.57]: down to -0.86). The wrist here is a convex hull of 32
of the mesh's hull points (`wrist = 32`): with the box the hand trailed the mocap x0.68 of
metaworld's (MJX, arm, 20 episodes), with the hull x1.04 (C MuJoCo); the MJX step runs at 609
env steps/s at batch 64 (the box: 671 in a run earlier the same day).

The lever's upper excursion is a rare event, in metaworld too: in 12 of 100 of metaworld's
own scripted episodes (seed 1) the lever passed its upper stop by more than 0.05 rad (up to
3.00 rad). So "never beyond metaworld's own excursion over 20 episodes" fails whenever the
port's 20 episodes hold a flip and metaworld's do not (metaworld's seed-0 episodes hold
none); `above_range_share` in benchmarks/metaworld_dynamics.py reports how often it happens.

Measured, `python -m benchmarks.metaworld_dynamics --tasks door_unlock` (metaworld's scripted
policy, 500 steps, MJX port with metaworld's arm): 20 episodes a side (seed 0): return 4406 vs
4433 (x0.99), success at step 500 100% vs 100%, first success at step 46 vs 43, hand-mocap
0.116 vs 0.125 m (x0.93); the excursion target missed by that rare event (lever up to 2.96
rad here, 1.64 in metaworld's 20). 100 episodes a side (`--episodes 100 --seed 1`): all four
targets met; return x1.01, the lever past its upper stop in 13% of the port's episodes and
12% of metaworld's (up to 2.43 and 3.00 rad), hand-mocap x0.94. The free hand with the box
wrist: return x0.97, hand-mocap x0.51; without the wrist pair (claws only) the lever stayed
in range but the claws unlocked it late (first success at step 103 vs 43, return x0.90).
"""
from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from tasks.metaworld import reward_utils as ru
from tasks.metaworld.sawyer import SawyerTask, SceneSpec

LOCK_LENGTH = 0.1


class DoorUnlock(SawyerTask):
    name = "door_unlock"
    scene = SceneSpec(
        xml="sawyer_door_lock.xml",
        hand_init_pos=(0.0, 0.6, 0.2),
        object_geoms=(("lock_link", (0,)),),
        wrist_geoms=(("lock_link", (0,)),),  # metaworld pushes the lever with the wrist
        placed_body="door",
    )
    # a convex hull of 32 of the gripper-base mesh's hull points: with the box, the wrist
    # caught the lever from below and held the hand back (hand-mocap x0.68 with the arm)
    wrist = 32
    hand_low = (-0.5, 0.40, -0.15)
    obj_low = (-0.1, 0.8, 0.15)
    obj_high = (0.1, 0.85, 0.15)
    goal_low = (0.0, 0.64, 0.2100)
    goal_high = (0.2, 0.7, 0.2111)

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        m = self.mj_model
        self._lock_qadr = int(m.jnt_qposadr[m.body_jntadr[m.body("lock_link").id]])

    def _place(self, key, data):
        pos = self.sample_uniform(key, self.obj_low, self.obj_high)
        data = data.replace(qpos=data.qpos.at[self._lock_qadr].set(1.5708))  # _set_obj_xyz
        return data, {"placement": pos}

    def _after_forward(self, data, info):
        obj_init = data.xpos[self.mj_model.body("lock_link").id]
        return dict(info, obj_init_pos=obj_init, target_pos=obj_init + jnp.array([0.1, -0.04, 0.0]))

    def _objects(self, data):
        return self.site_pos(data, "lockStartUnlock"), data.xquat[self.mj_model.body("door_link").id]

    def _reward(self, obs, action, data, info):
        gripper, lock = obs[:3], obs[4:7]
        offset = jnp.array([0.0, 0.055, 0.07])
        scale = jnp.array([0.25, 1.0, 0.5])
        shoulder_to_lock = (gripper + offset - lock) * scale
        shoulder_to_lock_init = (info["init_tcp"] + offset - info["obj_init_pos"]) * scale
        ready_to_push = ru.tolerance(jnp.linalg.norm(shoulder_to_lock), bounds=(0, 0.02),
                                     margin=jnp.linalg.norm(shoulder_to_lock_init),
                                     sigmoid="long_tail")
        obj_to_target = jnp.abs(info["target_pos"][0] - lock[0])
        pushed = ru.tolerance(obj_to_target, bounds=(0, 0.005), margin=LOCK_LENGTH,
                              sigmoid="long_tail")
        reward = 2 * ready_to_push + 8 * pushed
        return reward, (obj_to_target <= 0.02).astype(jnp.float32)

    def _task_info_from_metaworld(self, env):
        return {"obj_init_pos": np.asarray(env.obj_init_pos),
                "target_pos": np.asarray(env._target_pos)}
