"""sweep-into-v3 (metaworld/envs/sawyer_sweep_into_goal_v3.py, sawyer_table_with_hole.xml).

The puck (`obj`, a 4 cm box on a free joint) must be pushed into the hole in the table at
the fixed goal (0, 0.84). Contacts, all box-box (each kind occurs in metaworld's own
scripted-policy episodes: contact census of 4 goal-observable scripted episodes on C MuJoCo):
  * 4 gripper geoms x the puck (4 pairs): the gripper cages and pushes it;
  * 4 gripper geoms x the 4 table-top slabs around the hole (16 pairs): the scripted policy
    lowers the hand to puck height + 1 cm, so the fingers rest on the table top (its top is
    at z = 0.05) while sweeping; without these pairs the fingers would sink 4 cm below
    the surface and the hand height, the caging terms and the push would all differ;
  * the puck x the same 4 slabs (4 pairs): it slides on them and starts on the centre strip
    or one of the side slabs (x up to +-0.1, the centre strip ends at +-0.08);
  * the puck x the big table block under the slabs (1 pair): it is the floor of the hole,
    where the puck comes to rest (z = 0.02) after falling in.
  * the puck x the room's floor (1 pair; metaworld's plane at z = -0.913 as a 20 x 20 m box):
    a puck pushed off the table lands there, as in metaworld (tested).
The lower inner table block (top at z = -0.053) is never reached (the big block covers it):
dropped. The wrist geom (`right_hand`'s mesh, which collides in metaworld) never touched
anything in the census: it has no pair here.

Reset: metaworld's `reset_model` draws the puck's x, y (rejecting draws within 0.15 of the
goal in x-y; the goal half of the random vector is unused, the goal is fixed) and moves the
puck there at the height it settled to during `_reset_hand` (the XML puts it 3 cm inside
the table top, the hand reset pushes it up to z ~ 0.07), keeping that settled orientation,
velocities zero. We take that settled height/orientation from our own hand-settling run
(z = 0.0699681, identical to metaworld's to 7 digits).

Measured closed loop, `python -m benchmarks.metaworld_dynamics --tasks sweep_into`
(metaworld's scripted policy, 20 episodes a side, 500 steps, MJX port with metaworld's arm):
all four targets met. Return 2083 vs 2160 (x0.96), success at step 500 30% vs 35%, first
success at step 55 vs 56, hand-mocap 0.071 vs 0.072 m (x1.00); the puck has no joint range.
metaworld's own policy fails often (6 of its episodes traced, C MuJoCo): in 3 the puck
overshoots the goal into the far corner of the hole (-0.06, 0.90; the target radius is 5 cm)
and the hand jams against the hole's far wall 11 cm short of the mocap; in 2 the fingers
press the puck into the table top and the policy drags it back; 1 succeeds. It takes the
arm's inertia and joint damping to do the same: the free hand (`arm=False`) followed the
mocap into the hole and put the puck on the goal every time (return x2.12, success 100%,
hand-mocap x0.10), with or without metaworld's constraint weights.

These 20-episode numbers are one sample of a chaotic process: the return's SD is 1650-1850,
so the mean's standard error is about 19%, and rounding alone changes the sample: adding the
floor pair (never touched by these episodes) changes them from step 2-14 on by 1e-11 to 2e-7
at first, with the same actions, and the 20-episode return read x1.17 with it (2026-12-03,
another machine) where it had read x0.96 without. With 100 episodes a side
(`--tasks sweep_into --episodes 100 --seed 1` -> `metaworld_dynamics_sweep_into_100.csv`), the
floor kept: return 1933 vs 2085 (x0.93), success at step 500 27% vs 31%, hand-mocap 0.081 vs
0.080 m (x1.01): all four targets met; the scene before the floor pair, the same 100
episodes: 1915 (x0.92), 26%, 0.081 m.

Found in a SAC run's replay (the reward lab's dataset, 100 episodes): in 3 episodes the hand
moved 5-8 cm in one step (the 99.9th percentile of a step is 1.6-2.0 cm) and in one it threw
the puck off the table at about 6 m/s. Not a port artefact: metaworld's own env, set to the
recorded states and given the recorded actions, makes the same steps. Measured on the 67
training episodes (`python -m benchmarks.metaworld_state_replay --task sweep_into` ->
`metaworld_state_replay.csv`): 9 steps over 3 cm in 2 episodes, each within 3.6 mm of
metaworld's own step from the same state (0.0544 vs 0.0544 m, 0.0777 vs 0.0774 m), with the
mocap 19-40 cm ahead of a hand held back by the table or puck, whose weld then swings the arm;
on 200 random steps the next hand position differs from metaworld's by 1.3e-5 m (median),
2.4 mm at most. Before the floor pair the thrown puck fell without end (z = -32.5 m by step
500) where metaworld's lands on its floor.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from tasks.metaworld import reward_utils as ru
from tasks.metaworld.sawyer import SawyerTask, SceneSpec

OBJ_RADIUS = 0.02
TARGET_RADIUS = 0.05
GOAL = (0.0, 0.84, 0.02)  # metaworld's self.goal, copied to _target_pos at every reset


class SweepInto(SawyerTask):
    name = "sweep_into"
    # MJX keeps the 72 deepest contacts per condim group (tasks.physics.with_max_contacts):
    # metaworld's scripted policy on this port left at most 56 of its 104 (condim-4) slots active
    # (`python -m benchmarks.metaworld_dynamics --sides port --max-contacts none`, 20 episodes)
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
