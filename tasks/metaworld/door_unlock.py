"""door-unlock-v3 (metaworld/envs/sawyer_door_unlock_v3.py, sawyer_door_lock.xml) on MJX.

Contacts: the 4 gripper geoms and the wrist (the gripper base's bounding box, sawyer.py)
x the lock lever box of `lock_link`: 5 pairs. The door (fixed in this scene) and safe are
not on the scripted solution's path; the arm is replaced by the free hand (sawyer.py). In
metaworld's own scripted episodes (contact census, C MuJoCo) the lever is pushed by the
*wrist* only (1162 contact steps in 3 episodes) and swings far past its range ([0, 1.57]:
down to -0.86).

Measured, `python -m benchmarks.metaworld_dynamics --tasks door_unlock` (metaworld's
scripted policy, 20 episodes a side, 500 steps, MJX port): return 4313 vs 4433 (x0.97),
success at step 500 100% vs 100%, first success at step 49 vs 43. Targets missed: the
lever's excursion, -1.09..3.00 vs metaworld's -0.86..1.64 rad (in some episodes the
wrist's box catches the lever from below and flips it over its upper stop: 1 of 10 in C
MuJoCo, where the other 9 stay within -0.91..1.68), and the hand-mocap distance, 0.064 vs
0.125 m (x0.51). Without the wrist pair (the port before this change, claws only) the lever
stays in range but the claws unlock it late: first success at step 103 vs 43, return x0.90,
hand-mocap x0.19.
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
