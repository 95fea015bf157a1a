"""sweep-into-v3 (metaworld/envs/sawyer_sweep_into_goal_v3.py, sawyer_table_with_hole.xml).

The puck (`obj`, a 4 cm box on a free joint) must be pushed into the table's hole at the
fixed goal (0, 0.84). Contacts, all box-box: the 4 gripper geoms x the puck and x the 4
table-top slabs around the hole; the puck x those slabs, x the hole's floor and x the room's
floor (a puck pushed off the table lands there, as in metaworld). Reset: the puck's x, y
drawn away from the goal as metaworld does, at the height and orientation it settles to
during the hand reset.

Parity (`python -m benchmarks.ports.metaworld_dynamics --tasks sweep_into`): 20 episodes a side,
return 2358 vs 2160 (x1.09), success at step 500 40% vs 35%, hand-mocap x0.93; 100 episodes
(`--episodes 100 --seed 1`): x0.93, 27% vs 31%, x1.01; all four targets met. Same states:
observation within 1.2e-6, reward within 8.2e-6. Details: docs/ports/metaworld.md.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from tasks.metaworld import reward_utils as ru
from tasks.metaworld.sawyer import SawyerTask
from tasks.metaworld.scene import SceneSpec

OBJ_RADIUS = 0.02
TARGET_RADIUS = 0.05
GOAL = (0.0, 0.84, 0.02)  # metaworld's self.goal, copied to _target_pos at every reset


class SweepInto(SawyerTask):
    name = "sweep_into"
    goal_text = "Sweep the puck into the hole."
    metaworld_env = "sweep-into-v3"
    scripted_policy = "SawyerSweepIntoV3Policy"
    object_joint = None  # the puck is free: no range to watch
    policy_reads_goal = True
    # MJX keeps the 72 deepest contacts per condim group (tasks.physics.with_max_contacts):
    # metaworld's scripted policy on this port left at most 56 of its 104 (condim-4) slots active
    # (`python -m benchmarks.ports.metaworld_dynamics --sides port --max-contacts none`,
    # 20 episodes)
    max_contacts = 72
    scene = SceneSpec(
        xml="sawyer_table_with_hole.xml",
        hand_init_pos=(0.0, 0.6, 0.2),
        # gripper x puck, gripper x the table-top slabs (tablelink collision geoms 2..5)
        object_geoms=(("obj", None), ("tablelink", (2, 3, 4, 5))),
        # puck x hole floor (tablelink collision geom 0) and x the table-top slabs, and x the
        # room's floor (a puck pushed off the table lands there, as in metaworld)
        extra_pairs=tuple(("objGeom", ("tablelink", i)) for i in (0, 2, 3, 4, 5))
        + (("objGeom", "floor_block"),),
        # metaworld's floor plane (top z = -0.913) as a 20 x 20 m block: a box-box pair joins
        # the scene's other box-box pairs (a plane-box pair read 19% slower in one
        # back-to-back pair, inside this machine's drift: not resolved, the box kept)
        fixtures=(("floor_block", "world", "BOX", (10.0, 10.0, 0.1), (0, 0, -1.013),
                   (1, 0, 0, 0), "floor"),),
    )
    obj_low = (-0.1, 0.6, 0.02)
    obj_high = (0.1, 0.7, 0.02)
    goal_low = (-0.001, 0.8399, 0.0199)
    goal_high = (0.001, 0.8401, 0.0201)

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        m = self.mj_model
        jid = m.joint("objjoint").id
        self._obj_qadr = int(m.jnt_qposadr[jid])
        self._obj_vadr = int(m.jnt_dofadr[jid])
        self._obj_body = m.body("obj").id
        self._obj_geom = m.geom("objGeom").id
        self._pad_ids = (m.body("leftpad").id, m.body("rightpad").id)
        settled = self._settled["qpos"][self._obj_qadr:self._obj_qadr + 7]
        self.obj_init_z = float(settled[2])  # metaworld: get_body_com("obj")[2] after _reset_hand
        self._obj_init_quat = jnp.asarray(settled[3:], jnp.float32)

    def _place(self, key, data):
        goal = jnp.asarray(GOAL, jnp.float32)

        # metaworld: `while norm(rand[:2] - target[:2]) < 0.15: redraw` (rand[:3] is the puck)
        def draw(k):
            return self.sample_uniform(k, self.obj_low, self.obj_high)

        def cond(c):
            return jnp.linalg.norm(c[1][:2] - goal[:2]) < 0.15

        def body(c):
            k, sub = jax.random.split(c[0])
            return k, draw(sub)

        key, sub = jax.random.split(key)
        _, xyz = jax.lax.while_loop(cond, body, (key, draw(sub)))
        obj_init = jnp.array([xyz[0], xyz[1], self.obj_init_z], jnp.float32)
        a, v = self._obj_qadr, self._obj_vadr
        qpos = data.qpos.at[a:a + 3].set(obj_init).at[a + 3:a + 7].set(self._obj_init_quat)
        qvel = data.qvel.at[v:v + 6].set(0.0)  # _set_obj_xyz zeroes qvel[9:15]
        return data.replace(qpos=qpos, qvel=qvel), {"obj_init_pos": obj_init,
                                                    "target_pos": goal}

    @staticmethod
    def goal_sites(data):
        return {"goal": GOAL}

    def _objects(self, data):
        # get_body_com("obj") is xpos; the orientation is scipy's quaternion of objGeom's xmat
        return data.xpos[self._obj_body], ru.mat_to_quat_scipy(data.geom_xmat[self._obj_geom])

    def _caging(self, action, obj, data, info):
        """metaworld SawyerSweepIntoGoalEnvV3._gripper_caging_reward (its own override)."""
        pad_success_margin = 0.05
        grip_success_margin = OBJ_RADIUS + 0.005
        x_z_success_margin = 0.01
        tcp = self.tcp_center(data)
        left_pad, right_pad = data.xpos[self._pad_ids[0]], data.xpos[self._pad_ids[1]]
        delta_left = left_pad[1] - obj[1]
        delta_right = obj[1] - right_pad[1]
        # metaworld's init_right/left_pad are `data.body(...).xpos` *views* taken at
        # construction, so they always hold the current pad positions (checked: the logged
        # margins equal | |obj_y - pad_y| - 0.05 | with the current pads); we match that,
        # not the arm-at-qpos0 constants in SawyerTask.init_*_pad
        right_margin = jnp.abs(jnp.abs(obj[1] - right_pad[1]) - pad_success_margin)
        left_margin = jnp.abs(jnp.abs(obj[1] - left_pad[1]) - pad_success_margin)

        def tol(x, upper, margin):
            return ru.tolerance(x, bounds=(OBJ_RADIUS, upper), margin=margin,
                                sigmoid="long_tail")

        y_caging = ru.hamacher_product(tol(delta_right, pad_success_margin, right_margin),
                                       tol(delta_left, pad_success_margin, left_margin))
        y_gripping = ru.hamacher_product(tol(delta_right, grip_success_margin, right_margin),
                                         tol(delta_left, grip_success_margin, left_margin))
        xz = jnp.array([1.0, 0.0, 1.0])
        tcp_obj_xz = jnp.linalg.norm((tcp - obj) * xz)
        xz_margin = jnp.linalg.norm((info["obj_init_pos"] - info["init_tcp"]) * xz) \
            - x_z_success_margin
        x_z_caging = ru.tolerance(tcp_obj_xz, bounds=(0, x_z_success_margin), margin=xz_margin,
                                  sigmoid="long_tail")
        caging = ru.hamacher_product(y_caging, x_z_caging)
        gripping = jnp.where(caging > 0.95, y_gripping, 0.0)
        return (caging + gripping) / 2

    def _reward(self, obs, action, data, info):
        """compute_reward, reward_function_version "v2" (metaworld's default)."""
        obj = obs[4:7]
        target = jnp.array([info["target_pos"][0], info["target_pos"][1], obj[2]])
        obj_to_target = jnp.linalg.norm(obj - target)
        in_place_margin = jnp.linalg.norm(info["obj_init_pos"] - target)
        in_place = ru.tolerance(obj_to_target, bounds=(0, TARGET_RADIUS), margin=in_place_margin,
                                sigmoid="long_tail")
        grasped = self._caging(action, obj, data, info)
        reward = 2 * grasped + 6 * ru.hamacher_product(grasped, in_place)
        reward = jnp.where(obj_to_target < TARGET_RADIUS, 10.0, reward)
        return reward, (obj_to_target <= TARGET_RADIUS).astype(jnp.float32)

    def _task_info_from_metaworld(self, env):
        return {"obj_init_pos": np.asarray(env.obj_init_pos),
                "target_pos": np.asarray(env._target_pos)}
