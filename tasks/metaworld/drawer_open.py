"""drawer-open-v3 (metaworld/envs/sawyer_drawer_open_v3.py, sawyer_drawer.xml) on MJX.

Contacts: the 4 gripper geoms x the 3 handle capsules of `drawer_link` (12 pairs); the drawer
stops on its soft joint limit alone, as in metaworld. Reward, success and the 39-D
observation are metaworld's (drawer handle at `drawer_link` - 0.16 y).

Parity (`python -m benchmarks.ports.metaworld_dynamics --tasks drawer_open`, metaworld's scripted
policy, 20 episodes a side): return 4031 vs 4049 (x1.00), success at step 500 100% vs 100%,
drawer out to -0.2025 vs -0.2025, hand-mocap x1.00: all four targets met. Same states:
observation within 1.1e-6, reward within 6.7e-6. Details: docs/ports/metaworld.md.
"""
from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from tasks.metaworld import reward_utils as ru
from tasks.metaworld.sawyer import SawyerTask
from tasks.metaworld.scene import SceneSpec

MAX_DIST = 0.2
GOAL_OFFSET = (0.0, -0.16 - MAX_DIST, 0.09)  # target_pos - obj_init_pos


class DrawerOpen(SawyerTask):
    name = "drawer_open"
    goal_text = "Pull the drawer open."
    metaworld_env = "drawer-open-v3"
    scripted_policy = "SawyerDrawerOpenV3Policy"
    object_joint = "goal_slidey"
    # MJX keeps the 8 deepest contacts per condim group (tasks.physics.with_max_contacts):
    # metaworld's scripted policy on this port left at most 4 of its 24 (condim-4) slots active
    # (`python -m benchmarks.ports.metaworld_dynamics --sides port --max-contacts none`,
    # 20 episodes)
    max_contacts = 8
    scene = SceneSpec(
        xml="sawyer_drawer.xml",
        hand_init_pos=(0.0, 0.6, 0.2),
        object_geoms=(("drawer_link", (5, 6, 7)),),  # the handle capsules
        placed_body="drawer",
    )
    obj_low = (-0.1, 0.9, 0.0)
    obj_high = (0.1, 0.9, 0.0)

    def _place(self, key, data):
        obj_init_pos = self.sample_uniform(key, self.obj_low, self.obj_high)
        target = obj_init_pos + jnp.array(GOAL_OFFSET)
        return data, {"placement": obj_init_pos, "obj_init_pos": obj_init_pos,
                      "target_pos": target}

    @staticmethod
    def goal_sites(data):
        return {"goal": data.body("drawer").xpos + GOAL_OFFSET}

    def _objects(self, data):
        link = self.mj_model.body("drawer_link").id
        return data.xpos[link] + jnp.array([0.0, -0.16, 0.0]), data.xquat[link]

    def _reward(self, obs, action, data, info):
        gripper, handle = obs[:3], obs[4:7]
        target = info["target_pos"]
        handle_error = jnp.linalg.norm(handle - target)
        reward_for_opening = ru.tolerance(handle_error, bounds=(0, 0.02), margin=MAX_DIST,
                                          sigmoid="long_tail")
        handle_pos_init = target + jnp.array([0.0, MAX_DIST, 0.0])
        scale = jnp.array([3.0, 3.0, 1.0])
        gripper_error = (handle - gripper) * scale
        gripper_error_init = (handle_pos_init - info["init_tcp"]) * scale
        reward_for_caging = ru.tolerance(jnp.linalg.norm(gripper_error), bounds=(0, 0.01),
                                         margin=jnp.linalg.norm(gripper_error_init),
                                         sigmoid="long_tail")
        reward = 5.0 * (reward_for_caging + reward_for_opening)
        return reward, (handle_error <= 0.03).astype(jnp.float32)

    def _task_info_from_metaworld(self, env):
        return {"obj_init_pos": np.asarray(env.obj_init_pos),
                "target_pos": np.asarray(env._target_pos)}
