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
Removed: the flange's contacts with the slabs around the hole (it enters them only in the
last 1.6 cm of the stroke; as capsule pairs: return x1.31 with them, x1.30 without, C
MuJoCo) and the arm's geoms (sawyer.py). Tried and not kept (same benchmark, 20 episodes): only wrist x cap
(10 pairs): the wrist slides past the cap and drags the button out (+0.35 m, success at step
500 0%); without the claws x table pairs (9 pairs): return x1.24, button to -0.096.

Speed (`python -m benchmarks.metaworld_throughput --tasks button_press`, batch 64): 385 env
steps/s with the arm (460 with the free hand in the same run; the first port, claws x cap
only, 1188 on 2026-12-01; the 3 box-box wrist pairs and 4 plane-box table pairs add ~34
contact slots to the first port's 16). MJX's contact cap (`max_contacts = 18`, 2026-12-04)
cuts the 50 slots to 36: 808 against 526 env steps/s uncapped in the same run (1.53x), and
the same scripted episodes (return 579.0 against 579.1 uncapped). The first port
pushed the button to -0.358 and through the success zone (success at step 500: 0% against
100%).

Measured, `python -m benchmarks.metaworld_dynamics --tasks button_press` (metaworld's
scripted policy, 20 episodes a side, 500 steps, MJX port with metaworld's arm): success at
step 500 100% vs 100%, button down to -0.087 vs -0.084, hand-mocap 0.237 vs 0.223 m (x1.06).
Target missed: the return, 579 vs 445 (x1.30; the free hand x1.33). Why (C MuJoCo, the
same scene, 2 episodes in lockstep from metaworld's state): the observations stay within
1e-6 until step 40, then in the press metaworld's hand goes about 1 cm deeper into the box's
recess and its fingers close while they rest on the table and the cap (gripper opening 0.79
at step 70 -> 0.38 at step 500; here 0.82 -> 0.74); the reward's 2 * hamacher(opening,
near) term then pays more here at every step (1.25 vs 0.69 at step 500). The wrist's shape decides it: with
metaworld's own wrist mesh and the box's 4 slabs as separate pairs (instead of one block)
the return is x0.99 (20 episodes, C MuJoCo), with 32- or 96-point hulls of that mesh x1.20
and x1.17, with the box x1.23; under MJX the full mesh runs at 14 env steps/s at batch 64
(SAT over its 883-vertex hull), against 385 with the box, so the box stays.
Tried on 2026-12-02 and not kept (commit b56a11c holds the code and scripts): where the wrist
meets the box, metaworld's mesh enters the button's hole by a few mm (its front tapers from
5.4 x 5.1 cm to 1.3 x 0.2 cm over its last 8 mm; the hole is 5.2 x 4.8 cm) and touches the hole's
rim. A second wrist collider for that front (support points of the mesh's hull in {32, 64}
directions, the part ahead of 3 cm from the wrist's centre) against the box's 4 slabs, the
box still meeting the button: under MJX (20 episodes) return x1.14 / x1.10, but the button
then goes to -0.093 / -0.096 (past metaworld's -0.084 + 1 cm for 64), at 272 / 215 env
steps/s at batch 64 against 615 with the box in the same run (a lab run shared the
machine; the 385 above is an earlier measurement). C MuJoCo was as sensitive to
the shape: x1.09 with 64 directions, x1.01 with 128 but the button at -0.095.
Before the free hand kept metaworld's constraint weights (sawyer.py): return x1.02 but the
button went to -0.101 and hand-mocap x0.63.
Ruled out on 2026-12-03 (C MuJoCo, the registered pairs, box as one block, 20 episodes:
`python -m benchmarks.metaworld_dynamics --tasks button_press --sides metaworld port_c
--wrist W [--keep-cylinders]`): the hull's size, x1.22 / x1.21 / x1.22 with 96 / 250 / 500
of its points; the cap made a box, x1.29 with the wrist box and x1.24 with metaworld's mesh
when the cap stays a cylinder. What brings x0.99 is the mesh against the 4 slabs, i.e. the
wrist's tapered front entering the hole.
"""
from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from tasks.metaworld import reward_utils as ru
from tasks.metaworld.sawyer import SawyerTask, SceneSpec


class ButtonPress(SawyerTask):
    name = "button_press"
    # MJX keeps the 18 deepest contacts per condim group (tasks.physics.with_max_contacts):
    # metaworld's scripted policy on this port left at most 16 of its 18 condim-3 and 9 of its 32
    # condim-4 slots active (`python -m benchmarks.metaworld_dynamics --sides port --max-contacts
    # none`, 20 episodes)
    max_contacts = 18
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
