"""button-press-v3 (metaworld/envs/sawyer_button_press_v3.py) on MJX.

Contacts: the 4 gripper geoms x the button's cap cylinder (the outermost of the button's
three collision cylinders, the only part the gripper reaches when pressing along +y):
4 pairs. The button box faces are dropped: the button travels 6 cm into its box and the
gripper (wider than the opening) stops at the cap in metaworld's solution.
"""
from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from tasks.metaworld import reward_utils as ru
from tasks.metaworld.sawyer import SawyerTask, SceneSpec


class ButtonPress(SawyerTask):
    name = "button_press"
    scene = SceneSpec(
        xml="sawyer_button_press.xml",
        hand_init_pos=(0.0, 0.4, 0.2),
        object_geoms=(("button", (2,)),),  # cap cylinder at y = -0.183
        placed_body="box",
    )
    obj_low = (-0.1, 0.85, 0.115)
    obj_high = (0.1, 0.9, 0.115)

    def _place(self, key, data):
        pos = self.sample_uniform(key, self.obj_low, self.obj_high)
        return data, {"placement": pos}  # button joint qpos stays 0 (_set_obj_xyz(0))

    def _after_forward(self, data, info):
        target = self.site_pos(data, "hole")
        start = self.site_pos(data, "buttonStart")
        return dict(info, target_pos=target, obj_to_target_init=jnp.abs(target[1] - start[1]))

    def _objects(self, data):
        bid = self.mj_model.body("button").id
        return data.xpos[bid] + jnp.array([0.0, -0.193, 0.0]), data.xquat[bid]

    def _reward(self, obs, action, data, info):
        obj = obs[4:7]
        tcp = self.tcp_center(data)
        tcp_to_obj = jnp.linalg.norm(obj - tcp)
        tcp_to_obj_init = jnp.linalg.norm(obj - info["init_tcp"])
        obj_to_target = jnp.abs(info["target_pos"][1] - obj[1])
        tcp_closed = jnp.maximum(obs[3], 0.0)
        near_button = ru.tolerance(tcp_to_obj, bounds=(0, 0.05), margin=tcp_to_obj_init,
                                   sigmoid="long_tail")
        button_pressed = ru.tolerance(obj_to_target, bounds=(0, 0.005),
                                      margin=info["obj_to_target_init"], sigmoid="long_tail")
        reward = 2 * ru.hamacher_product(tcp_closed, near_button)
        reward = reward + jnp.where(tcp_to_obj <= 0.05, 8 * button_pressed, 0.0)
        return reward, (obj_to_target <= 0.02).astype(jnp.float32)

    def _task_info_from_metaworld(self, env):
        return {"target_pos": np.asarray(env._target_pos),
                "obj_to_target_init": np.asarray(env._obj_to_target_init)}
