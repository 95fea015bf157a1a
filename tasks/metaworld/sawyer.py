"""The reset/step skeleton shared by the MetaWorld v3 ports: mocap actions, the 39-D
observation, per-environment object placement; checked against metaworld 3.0.0.

The scene is `tasks.metaworld.scene.build_scene`'s (metaworld's arm kept by default, visual
geoms deleted, explicit contact pairs); the picture a person sees is
`tasks.metaworld.render_scene`'s. metaworld places the task object at reset by editing
`model.body_pos` of one body; each environment holds its placement in `info["placement"]`
and `model_for(info)` swaps it into `body_pos` inside the jitted step, so a vmapped batch
holds different placements. Parity (closed loop, metaworld's scripted policy, 20 episodes a
side): return x0.94-x1.09 of metaworld's on five of the six tasks, button_press x1.30;
tables and the command that regenerates them: docs/ports/metaworld.md.
"""
from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from tasks.base import Task, TaskState
from tasks.metaworld.render_scene import build_render_scene
from tasks.metaworld.scene import (SceneSpec, build_scene, exact_shapes_for_c,
                                   load_full_model)
from tasks.metaworld.scene_bodies import DOF_SIZE, HAND_QUAT
from tasks.physics import contacts_at_cap, mjx, put_model, step as physics_step
from tasks.render_scene import register_render_scene

__all__ = ["SawyerTask", "SceneSpec", "build_scene", "load_full_model"]

FRAME_SKIP = 5
EPISODE_LENGTH = 500  # SawyerXYZEnv.max_path_length
ACTION_SCALE = 1.0 / 100
HAND_SPACE_LOW = np.array([-0.525, 0.348, -0.0525])
HAND_SPACE_HIGH = np.array([0.525, 1.025, 0.7])
RESET_HAND_STEPS = 50  # SawyerXYZEnv._reset_hand
# qpos entries per joint, by mjtJoint (free, ball, slide, hinge)
QPOS_SIZE = {0: 7, 1: 4, 2: 1, 3: 1}


class SawyerTask(Task):
    """Reset/step/observation shared by the MetaWorld ports.

    Subclasses set `scene`, the bounds, and implement `_place` (reset randomisation),
    `_objects` (object pos/quat for the observation) and `_reward`."""

    domain = "metaworld"
    has_success = True
    action_size = 4
    obs_size = 39
    episode_length = EPISODE_LENGTH

    scene: SceneSpec
    hand_low: tuple = (-0.5, 0.40, 0.05)  # the hand_low/hand_high of every task here
    hand_high: tuple = (0.5, 1.0, 0.5)
    obj_low: tuple = ()
    obj_high: tuple = ()
    goal_low: tuple | None = None  # goal_space; None -> hand bounds (metaworld default)
    goal_high: tuple | None = None
    wrist: str | int = "box"  # the task's wrist collider (build_scene); a task may pick a hull
    max_contacts: int | None = None  # MJX's contact cap (build_scene); None: every slot
    # the contact cap measured for a wrist other than the registered one (`wrist="box"` on a
    # task whose registered wrist is not the box)
    wrist_caps: dict = {}

    # the metaworld task a port reproduces, read by the checks against it (reference.py,
    # closed_loop.py): its v3 env id and the class of its scripted policy (metaworld.policies)
    metaworld_env: str = ""
    scripted_policy: str = ""
    # the object joint whose range the closed-loop check watches: a joint name, a 1-tuple
    # naming the body whose first joint it is, or None (nothing to watch)
    object_joint: str | tuple[str] | None = None
    # the scripted policy steers by the goal slots obs[36:39] (metaworld runs its policies on
    # goal-observable envs), which the default hidden goal zeroes: with it, the policy would
    # head for (0, 0, 0), so the checks give it the goal
    policy_reads_goal: bool = False

    def __init__(self, partially_observable: bool = True, solver_iterations: int = 5,
                 ls_iterations: int = 10, arm: bool = True, wrist: str | int | None = None,
                 metaworld_invweights: bool = True, keep_cylinders: bool = False,
                 max_contacts: int | None | str = "task"):
        """partially_observable=True (default) zeroes the 3 goal slots of the observation.

        That is metaworld v3's own default (`_partially_observable = True`) and what BPref
        and every PbRL baseline the paper compares with used: BPref's `make_metaworld_env`
        never changes it, so its goal slots are zeros (GitHub rll-research/BPref issue 8);
        pass False for metaworld's "goal observable" variant.

        solver_iterations / ls_iterations: metaworld's scene asks for 50 Newton iterations at
        tolerance 1e-10; MJX runs its solver loop until the tolerance is met, i.e. nearly all
        50 every substep. Newton converges in a few iterations on these small contact sets;
        5 / 10 roughly doubled batch-64 throughput on drawer_open and kept its scripted-policy
        success and drift (benchmarks/ports/metaworld_parity.py). Pass 50, 50 for metaworld's.

        wrist="mesh" or keep_cylinders=True build metaworld's exact shapes for C MuJoCo
        diagnostics (`mj_model`); MJX cannot collide them, so `model` (the MJX step's) is
        then the box-wrist scene's: right for kinematics, not for contacts.
        max_contacts="task": the cap measured for the wrist built (`wrist_caps`), else the
        registered one."""
        self.partially_observable = partially_observable
        self.arm = arm
        self.wrist = self.wrist if wrist is None else wrist
        if max_contacts == "task":
            max_contacts = self.wrist_caps.get(self.wrist, type(self).max_contacts)
        self.max_contacts = max_contacts
        self._build_models(solver_iterations, ls_iterations, metaworld_invweights,
                           keep_cylinders)
        self.control_timestep = FRAME_SKIP * float(self.mj_model.opt.timestep)
        m = self.mj_model
        self._mocap_low = jnp.asarray(self.hand_low, jnp.float32)
        self._mocap_high = jnp.asarray(self.hand_high, jnp.float32)
        self._hand_mocap = int(m.body_mocapid[m.body("mocap").id])
        self._placed_body = m.body(self.scene.placed_body).id if self.scene.placed_body else None
        # the placed body hangs on the world body: its position in `data` is the placement
        assert self._placed_body is None or m.body_parentid[self._placed_body] == 0
        if not arm:
            self._hand_qadr = int(m.jnt_qposadr[m.joint("hand_free").id])
            self._hand_vadr = int(m.jnt_dofadr[m.joint("hand_free").id])
        self._ids = {
            "hand": m.body("hand").id, "rightclaw": m.body("rightclaw").id,
            "leftclaw": m.body("leftclaw").id, "rightpad": m.body("rightpad").id,
            "leftpad": m.body("leftpad").id,
            "rightEE": m.site("rightEndEffector").id, "leftEE": m.site("leftEndEffector").id,
        }
        self._obs_low, self._obs_high = self._obs_bounds(partially_observable)
        self._settled = self._settle_hand()
        # metaworld reads init_left/right_pad once at construction, with the *arm* at qpos0
        # (they are views of data.xpos, so inside metaworld they later track the current pads:
        # a reward that reads them must use the current pads, see sweep_into._caging)
        full = load_full_model(self.scene.xml)
        fd = mujoco.MjData(full)
        mujoco.mj_forward(full, fd)
        self.init_left_pad = jnp.asarray(fd.body("leftpad").xpos, jnp.float32)
        self.init_right_pad = jnp.asarray(fd.body("rightpad").xpos, jnp.float32)
        # what a renderer draws for this model: metaworld's own look, built on first use
        register_render_scene(self.mj_model, functools.partial(
            build_render_scene, self.scene, arm, type(self).goal_sites))

    def _build_models(self, solver_iterations, ls_iterations, metaworld_invweights,
                      keep_cylinders) -> None:
        """`mj_model` (C MuJoCo's) and `model` (the MJX step's), see `__init__`."""
        self.mj_model, self.scene_info = build_scene(
            self.scene, arm=self.arm, wrist=self.wrist,
            metaworld_invweights=metaworld_invweights, keep_cylinders=keep_cylinders,
            max_contacts=self.max_contacts)
        self.mj_model.opt.iterations = solver_iterations
        self.mj_model.opt.ls_iterations = ls_iterations
        mjx_scene = self.mj_model
        if exact_shapes_for_c(self.wrist, keep_cylinders):  # MJX cannot collide them: its model
            # (kinematics, reset) is the scene with the box wrist, same bodies, joints, sites
            mjx_scene, _ = build_scene(self.scene, arm=self.arm, wrist="box",
                                       metaworld_invweights=metaworld_invweights,
                                       max_contacts=self.max_contacts)
            mjx_scene.opt.iterations, mjx_scene.opt.ls_iterations = (solver_iterations,
                                                                     ls_iterations)
        self.model = put_model(mjx_scene)

    def _obs_bounds(self, partially_observable: bool) -> tuple[np.ndarray, np.ndarray]:
        """metaworld's observation space (`step` clips to it)."""
        goal_low = self.goal_low if self.goal_low is not None else self.hand_low
        goal_high = self.goal_high if self.goal_high is not None else self.hand_high
        low = np.concatenate([HAND_SPACE_LOW, [-1.0], np.full(14, -np.inf)] * 2
                             + [np.zeros(3) if partially_observable else goal_low])
        high = np.concatenate([HAND_SPACE_HIGH, [1.0], np.full(14, np.inf)] * 2
                              + [np.zeros(3) if partially_observable else goal_high])
        return low, high

    # -- construction-time constants ------------------------------------------------
    def _settle_hand(self) -> dict:
        """metaworld's `_reset_hand`: 50 control steps with the mocap at hand_init_pos and the
        gripper open (ctrl -1, 1). It starts from the same state every reset (mj_resetData),
        so the result is a constant: we compute it once here with C MuJoCo on our scene."""
        m = self.mj_model
        d = mujoco.MjData(m)
        d.mocap_pos[self._hand_mocap] = self.scene.hand_init_pos
        d.mocap_quat[self._hand_mocap] = HAND_QUAT
        d.ctrl[:] = [-1.0, 1.0]
        for _ in range(RESET_HAND_STEPS * FRAME_SKIP):
            mujoco.mj_step(m, d)
        mujoco.mj_forward(m, d)
        tcp = (d.site_xpos[self._ids["rightEE"]] + d.site_xpos[self._ids["leftEE"]]) / 2
        return {"qpos": d.qpos.copy(), "qvel": d.qvel.copy(), "init_tcp": tcp.copy()}

    # -- subclass hooks -----------------------------------------------------------------
    def _place(self, key: jax.Array, data: mjx.Data) -> tuple[mjx.Data, dict]:
        """Randomise the object like metaworld's reset_model; returns data (qpos/mocap
        edited, not yet forwarded) and `info` constants for the episode."""
        raise NotImplementedError

    def _after_forward(self, data: mjx.Data, info: dict) -> dict:
        """Episode constants metaworld reads off the placed scene (after mj_forward)."""
        return info

    def _objects(self, data: mjx.Data) -> tuple[jax.Array, jax.Array]:
        raise NotImplementedError

    def _reward(self, obs, action, data, info) -> tuple[jax.Array, jax.Array]:
        raise NotImplementedError

    # -- helpers --------------------------------------------------------------------------
    def sample_uniform(self, key, low, high):
        low, high = jnp.asarray(low, jnp.float32), jnp.asarray(high, jnp.float32)
        return jax.random.uniform(key, low.shape, minval=low, maxval=high)

    def tcp_center(self, data: mjx.Data) -> jax.Array:
        return (data.site_xpos[self._ids["rightEE"]] + data.site_xpos[self._ids["leftEE"]]) / 2

    def body_pos(self, data: mjx.Data, name: str) -> jax.Array:
        return data.xpos[self.mj_model.body(name).id]

    def site_pos(self, data: mjx.Data, name: str) -> jax.Array:
        return data.site_xpos[self.mj_model.site(name).id]

    def virtual_geom_pose(self, data: mjx.Data, name: str) -> tuple[jax.Array, jax.Array]:
        """World position and rotation matrix of a deleted visual geom (see SceneSpec)."""
        body, pos, quat = self.scene_info["virtual_geoms"][name]
        bid = self.mj_model.body(body).id
        mat = np.zeros(9)
        mujoco.mju_quat2Mat(mat, quat)
        rot = data.xmat[bid]
        return data.xpos[bid] + rot @ jnp.asarray(pos, jnp.float32), rot @ jnp.asarray(
            mat.reshape(3, 3), jnp.float32)

    def current_obs(self, data: mjx.Data) -> jax.Array:
        """metaworld `_get_curr_obs_combined_no_goal` (18 values)."""
        hand = data.xpos[self._ids["hand"]]
        apart = jnp.linalg.norm(data.xpos[self._ids["rightclaw"]] - data.xpos[self._ids["leftclaw"]])
        apart = jnp.clip(apart / 0.1, 0.0, 1.0)
        pos, quat = self._objects(data)
        n_obj = pos.shape[0] // 3
        objs = jnp.concatenate([jnp.concatenate([pos[3 * i:3 * i + 3], quat[4 * i:4 * i + 4]])
                                for i in range(n_obj)])
        objs = jnp.pad(objs, (0, 14 - objs.shape[0]))
        return jnp.concatenate([hand, apart[None], objs]).astype(jnp.float32)

    def observe(self, curr, prev, goal) -> jax.Array:
        """metaworld `_get_obs` followed by the clip to the observation space in `step`."""
        goal = jnp.zeros(3) if self.partially_observable else goal
        obs = jnp.concatenate([curr, prev, goal]).astype(jnp.float32)
        return jnp.clip(obs, self._obs_low, self._obs_high)

    def contacts_at_cap(self, data: mjx.Data) -> jax.Array:
        return contacts_at_cap(self.model, data, self.max_contacts)

    def render_state(self, data: mjx.Data) -> dict[str, jax.Array]:
        """RENDER_FIELDS and, where the task places its object at reset, `placement`: that
        body's position (metaworld's `model.body_pos` edit, which qpos does not hold)."""
        state = super().render_state(data)
        if self._placed_body is not None:
            state["placement"] = data.xpos[self._placed_body]
        return state

    @staticmethod
    def goal_sites(data: mujoco.MjData) -> dict[str, np.ndarray]:
        """metaworld's goal markers (`_target_site_config`: site name -> world position) in
        the render scene `data`, placed and forwarded; none by default."""
        return {}

    def model_for(self, info: dict) -> mjx.Model:
        """The model with this episode's object placement (metaworld edits model.body_pos)."""
        if self._placed_body is None:
            return self.model
        body_pos = self.model.body_pos.at[self._placed_body].set(info["placement"])
        return self.model.replace(body_pos=body_pos)

    def kinematics(self, data: mjx.Data, info: dict) -> mjx.Data:
        """Positions for observation and reward (metaworld calls mj_forward after stepping;
        only the position stage is read)."""
        return mjx.kinematics(self.model_for(info), data)

    # -- contract ---------------------------------------------------------------------------
    def reset(self, key: jax.Array) -> TaskState:
        data = mjx.make_data(self.model)
        data = data.replace(
            qpos=jnp.asarray(self._settled["qpos"], jnp.float32),
            qvel=jnp.asarray(self._settled["qvel"], jnp.float32),
            mocap_pos=data.mocap_pos.at[self._hand_mocap].set(
                jnp.asarray(self.scene.hand_init_pos, jnp.float32)),
            mocap_quat=data.mocap_quat.at[self._hand_mocap].set(jnp.asarray(HAND_QUAT, jnp.float32)),
            ctrl=jnp.asarray([-1.0, 1.0], jnp.float32),
        )
        info = {"init_tcp": jnp.asarray(self._settled["init_tcp"], jnp.float32)}
        data, placed = self._place(key, data)
        info.update(placed)
        if self.arm:
            # qpos made to depend on the key (+ 0 · u, exact): under vmap it is then batched
            # like the placed model. With the unbatched constant qpos, XLA's constant folding
            # of the arm scene's reset ran over 5 minutes at batch 64 (8 s at batch 8; 10 s
            # this way)
            data = data.replace(qpos=data.qpos + 0.0 * jax.random.uniform(
                jax.random.fold_in(key, 0x71706F73), data.qpos.shape))
        # positions only: obs and episode constants read nothing else, and mjx.step recomputes
        # every derived quantity from qpos/qvel (cheaper to compile and to auto-reset)
        data = mjx.kinematics(self.model_for(info), data)
        info = self._after_forward(data, info)
        curr = self.current_obs(data)
        info["prev_obs"] = curr  # metaworld v3 reset: obs[18:36] = obs[:18]
        obs = self.observe(curr, curr, info["target_pos"])
        zero = jnp.zeros((), jnp.float32)
        return TaskState(data=data, obs=obs, true_reward=zero, success=zero,
                         terminated=jnp.zeros((), bool), info=info)

    def step(self, state: TaskState, action: jax.Array) -> TaskState:
        action = jnp.clip(action, -1.0, 1.0)  # BPref's NormalizedBoxEnv clips to [-1, 1]
        data = state.data
        mocap = jnp.clip(data.mocap_pos[self._hand_mocap] + action[:3] * ACTION_SCALE,
                         self._mocap_low, self._mocap_high)
        data = data.replace(
            mocap_pos=data.mocap_pos.at[self._hand_mocap].set(mocap),
            ctrl=jnp.stack([action[3], -action[3]]),
        )
        model = self.model_for(state.info)
        data = jax.lax.fori_loop(0, FRAME_SKIP, lambda _, d: physics_step(model, d), data)
        data = mjx.kinematics(model, data)
        curr = self.current_obs(data)
        obs = self.observe(curr, state.info["prev_obs"], state.info["target_pos"])
        reward, success = self._reward(obs, action, data, state.info)
        info = dict(state.info, prev_obs=curr)
        return TaskState(data=data, obs=obs, true_reward=reward.astype(jnp.float32),
                         success=success.astype(jnp.float32),
                         terminated=jnp.zeros((), bool), info=info)

    # -- parity support ----------------------------------------------------------------------
    def data_from_metaworld(self, env) -> mjx.Data:
        """MJX data holding a metaworld env's current state: hand pose from metaworld's hand
        body, fingers and object joints from its qpos (the arm joints are dropped)."""
        md, mm = env.data, env.model
        m = self.mj_model
        qpos = np.zeros(m.nq)
        qvel = np.zeros(m.nv)
        # named joints (fingers, arm) by name; the task object's joints (some unnamed) in
        # their model order; without the arm, the hand pose from metaworld's hand body
        named = [m.joint(j).name for j in range(m.njnt)
                 if m.joint(j).name and m.joint(j).name != "hand_free"]
        ours = [m.joint(n).id for n in named] + [
            j for j in range(m.njnt) if not m.joint(j).name]
        theirs = [mm.joint(n).id for n in named] + [
            j for j in range(mm.njnt) if not mm.joint(j).name]
        if not self.arm:
            qpos[self._hand_qadr:self._hand_qadr + 3] = md.body("hand").xpos
            qpos[self._hand_qadr + 3:self._hand_qadr + 7] = md.body("hand").xquat
            qvel[self._hand_vadr:self._hand_vadr + 3] = md.body("hand").cvel[3:]  # approx.
        assert len(ours) == len(theirs), "joint lists of port and metaworld differ"
        for j, jm in zip(ours, theirs):
            mj = mm.joint(jm)
            n = QPOS_SIZE[int(m.jnt_type[j])]
            nvj = DOF_SIZE[int(m.jnt_type[j])]
            qpos[m.jnt_qposadr[j]:m.jnt_qposadr[j] + n] = md.qpos[mj.qposadr[0]:mj.qposadr[0] + n]
            qvel[m.jnt_dofadr[j]:m.jnt_dofadr[j] + nvj] = md.qvel[mj.dofadr[0]:mj.dofadr[0] + nvj]
        data = mjx.make_data(self.model)
        mocap_pos = np.array(data.mocap_pos)
        mocap_quat = np.array(data.mocap_quat)
        mocap_pos[self._hand_mocap] = md.mocap_pos[0]
        mocap_quat[self._hand_mocap] = md.mocap_quat[0] / np.linalg.norm(md.mocap_quat[0])
        return data.replace(qpos=jnp.asarray(qpos, jnp.float32),
                            qvel=jnp.asarray(qvel, jnp.float32),
                            mocap_pos=jnp.asarray(mocap_pos, jnp.float32),
                            mocap_quat=jnp.asarray(mocap_quat, jnp.float32),
                            ctrl=jnp.asarray(md.ctrl, jnp.float32))

    def info_from_metaworld(self, env) -> dict:
        """Episode constants of a metaworld env (after its reset) in this port's `info` form."""
        info = {"init_tcp": np.asarray(env.init_tcp), **self._task_info_from_metaworld(env)}
        if self._placed_body is not None:
            # a copy: `body(...).pos` is a view of the model, which the next reset rewrites
            info["placement"] = np.array(env.model.body(self.scene.placed_body).pos)
        return info

    def _task_info_from_metaworld(self, env) -> dict:
        raise NotImplementedError

