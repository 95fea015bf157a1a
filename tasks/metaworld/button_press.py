"""button-press-v3 (metaworld/envs/sawyer_button_press_v3.py) on MJX.

How metaworld's scripted solution moves (contact census of its own episodes, C MuJoCo): the
*wrist* (the gripper base, `right_hand`'s collision mesh) presses the button while the claws
rest on the table, and the button stops when its cap meets the box's front face, 2.3 cm past
its soft joint limit (-0.083; range [-0.06, 0]); the wrist is then held by the box while the
mocap target runs on, so the hand trails it by ~0.22 m. Contacts here (13 pairs):
  * claws/pads x the cap (the cap cylinder becomes its bounding box: MJX has no
    cylinder-box collision) and x the table top (a plane at z = 0): 8 pairs;
  * the wrist (its mesh's bounding box, see sawyer.py) x the button's rod, flange and cap,
    and x the box as one solid block (the wrist is wider than the hole): 4 pairs;
  * the cap x the box's front face (a plane at y = -0.09, paired with the cap only): 1 pair.
Removed: the flange's resting contacts with the hole's edges (friction on the slide) and the
arm (free hand, sawyer.py). Tried and not kept (same benchmark, 20 episodes): only wrist x cap
(10 pairs): the wrist slides past the cap and drags the button out (+0.35 m, success at step
500 0%); without the claws x table pairs (9 pairs): return x1.24, button to -0.096.

Speed (`python -m benchmarks.metaworld_throughput --tasks button_press`, batch 64, run
back to back with the first port on the same machine): 358 env steps/s against 1188, x0.30:
misses issue 18's "at least half" (the 3 box-box wrist pairs and 4 plane-box table pairs
add ~34 contact slots to the first port's 16). The first port had only claws x cap: the gripper pushed the
button to -0.358 and through the success zone (success at step 500: 0% against 100%).

Measured, `python -m benchmarks.metaworld_dynamics --tasks button_press` (metaworld's
scripted policy, 20 episodes a side, 500 steps, MJX port): success at step 500 100% vs 100%,
button down to -0.087 vs -0.084, hand-mocap 0.234 vs 0.223 m (x1.05). Target missed: the
return, 592 vs 445 (x1.33); the port presses earlier (first success at step 50 vs 63) and
the reward pays up to 10 per step once the fingers are within 5 cm of the pressed button.
The wrist's shape is part of it: with metaworld's arm, C MuJoCo, one episode from
metaworld's reset state, the return is 461 with metaworld's wrist mesh (metaworld: 461), 532
with a 24-point hull and 564 with the box; on the free hand a 12- or 24-point hull gives
x1.23 (10 episodes, C MuJoCo), not enough to keep its cost. Before the hand kept metaworld's
constraint weights (sawyer.py): return x1.02 but the button went to -0.101 and hand-mocap
x0.63.
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
        # claws x the cap cylinder (y = -0.183) and x the table top
        object_geoms=(("button", (2,)),),
        # the wrist x the button's rod, flange and cap, and x the box as one solid block
        wrist_geoms=(("button", (0, 1, 2)),),
        extra_pairs=(("wrist", "box_hull"), (("button", 2), "box_face"))
        + tuple((g, "table_top") for g in ("rightclaw_it", "leftclaw_it", "rightpad_geom",
                                          "leftpad_geom")),
        fixtures=(
            # the box's outer hull (its 4 slabs around the button hole): the wrist cannot
            # enter the hole, so one box stands for the 4 (1 box-box pair instead of 4)
            ("box_hull", "buttonbox", "BOX", (0.12, 0.102, 0.12), (0, 0.012, 0), (1, 0, 0, 0),
             ("buttonbox", 0)),
            # the slabs' front face (y = -0.09), normal -y: it stops the cap, the button's
            # only part wider than the hole; paired with the cap alone, so a plane is exact
            ("box_face", "buttonbox", "PLANE", (0.12, 0.12, 0.01), (0, -0.09, 0),
             (0.7071068, 0.7071068, 0, 0), ("buttonbox", 0)),
            # the table top (z = 0 over the whole reachable area) for the claws
            ("table_top", "tablelink", "PLANE", (0.7, 0.4, 0.01), (0, 0, 0), (1, 0, 0, 0),
             ("tablelink", 0)),
        ),
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
