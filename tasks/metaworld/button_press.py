"""button-press-v3 (metaworld/envs/sawyer_button_press_v3.py) on MJX.

metaworld's solution presses the button with the *wrist*; the button stops when its cap meets
the box's front face. Contacts (13 pairs): claws/pads x the cap (a box) and x the table top;
the wrist (a box) x the button's rod, flange and cap and x the box as one block; the cap x
the box's front face (a plane).

Parity (`python -m benchmarks.ports.metaworld_dynamics --tasks button_press [--wrist box]`): the
registered scene (the wrist as convex pieces of metaworld's wrist mesh, every contact slot)
meets all four targets at 100 episodes of metaworld's scripted policy (return x1.025, success
100% vs 100%, button 0.4 cm deeper, hand-mocap x1.02). `wrist="box"` (the wrist as its
bounding box, 18 contact slots per condim group) is the faster scene: success at step 500
100% vs 100%, button down to -0.087 vs -0.084, hand-mocap x1.06, but returns x1.30
metaworld's (579 vs 445, 20 episodes), because metaworld's wrist mesh has a tapered front
that enters the button's hole. Same states: observation within 1.1e-6, reward within
1.6e-6. Details: docs/ports/metaworld.md.
"""
from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from tasks.metaworld import reward_utils as ru
from tasks.metaworld.sawyer import SawyerTask
from tasks.metaworld.scene import SceneSpec


# convex pieces of metaworld's wrist mesh (tasks.metaworld.colliders.parse_pieces): with the
# wrist's bounding box the button returns x1.3 metaworld's, with these pieces x1.025
FAITHFUL_WRIST = "coacd:0.3:8:64:0,1"


class ButtonPress(SawyerTask):
    name = "button_press"
    goal_text = "Press the button in with the gripper."
    metaworld_env = "button-press-v3"
    scripted_policy = "SawyerButtonPressV3Policy"
    object_joint = "btnbox_joint"
    wrist = FAITHFUL_WRIST
    max_contacts = None  # the pieces' parity was measured with every contact slot
    # the box wrist keeps the 18 deepest contacts per condim group
    # (tasks.physics.with_max_contacts): metaworld's scripted policy on that scene left at
    # most 16 of its 18 condim-3 and 9 of its 32 condim-4 slots active (`python -m
    # benchmarks.ports.metaworld_dynamics --wrist box --sides port --max-contacts none`,
    # 20 episodes)
    wrist_caps = {"box": 18}
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
        # the mesh wrist or its pieces (wrist="coacd...") reach into the hole: the 4 slabs
        solid_stand_ins=(("box_hull", ("buttonbox", None)),),
        # FAITHFUL_WRIST's pieces in metaworld's scripted episodes (C MuJoCo, 10 episodes):
        # the front piece touches the 4 slabs, the flange and the cap, the other the cap
        # only, and neither the rod: 7 of its 14 pairs (x1.7 env steps/s under MJX)
        piece_partners=((FAITHFUL_WRIST, ((0, (("buttonbox", None), ("button", (1, 2)))),
                                          (1, (("button", (2,)),)))),),
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
