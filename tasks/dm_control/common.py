"""Shared pieces of the DM Control ports: model loading, action scaling, stepping."""
from __future__ import annotations

import contextlib
import copy
import functools
import importlib.util
import warnings
from pathlib import Path

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from tasks.base import Task, TaskState
from tasks.batching import CPU_GROUP
from tasks.physics import (contacts_at_cap, forward, legacy_substeps, max_contacts_of, mjx,
                            put_model, substeps_from_pose, with_max_contacts)
from tasks.render_scene import plain_scene, register_render_scene


def load_suite_model(domain: str, max_contacts: int | None = None) -> mujoco.MjModel:
    """Compiles dm_control's own XML (and assets) for `domain` at run time, with MJX's
    contact cap `max_contacts` (`tasks.physics.with_max_contacts`; C MuJoCo ignores it).

    We never copy dm_control's files: the installed package is the source of the model and
    the reference the parity tests compare against."""
    xml, assets = suite_model_files(domain)
    with _without_deprecation_notes():
        return mujoco.MjModel.from_xml_string(with_max_contacts(xml, max_contacts), assets)


# MuJoCo's notes on dm_control's own XML (cheetah's <compiler settotalmass>), not ours to fix:
# the model must stay dm_control's, bit for bit (tests/tasks/test_model_warnings.py)
DEPRECATION_NOTES = ("compiler attribute 'settotalmass' is deprecated",)


@contextlib.contextmanager
def _without_deprecation_notes():
    """MuJoCo's warnings while compiling, less DEPRECATION_NOTES: the rest as Python
    warnings. (MuJoCo's own handler prints each and appends it to MUJOCO_LOG.TXT in the
    current directory.)"""
    previous = mujoco.get_mju_user_warning()

    def note(message: str) -> None:
        if not message.startswith(DEPRECATION_NOTES):
            warnings.warn(f"MuJoCo: {message}", stacklevel=2)

    mujoco.set_mju_user_warning(note)
    try:
        yield
    finally:
        mujoco.set_mju_user_warning(previous)


# what `get_model_and_assets()` of dm_control's cheetah and walker return: the domain's XML
# and the suite's common assets, read from the installed package. Read here without
# importing `dm_control.suite`, which imports every domain (0.3 s of a run's start-up).
SUITE_COMMON_ASSETS = ("./common/materials.xml", "./common/skybox.xml", "./common/visual.xml")


def suite_model_files(domain: str) -> tuple[bytes, dict[str, bytes]]:
    """dm_control's `suite.<domain>.get_model_and_assets()` for cheetah and walker."""
    spec = importlib.util.find_spec("dm_control")
    if spec is None:  # pragma: no cover - depends on the environment
        raise ImportError(f"dm_control is needed to build the {domain} task: pip install -e . "
                          "(it is a core dependency of hprior_jax)")
    suite = Path(spec.submodule_search_locations[0]) / "suite"
    return ((suite / f"{domain}.xml").read_bytes(),
            {name: (suite / name).read_bytes() for name in SUITE_COMMON_ASSETS})


CONTACTS = ("floor", "all")


def floor_contacts_only(model: mujoco.MjModel) -> mujoco.MjModel:
    """A copy of `model` whose geoms collide with the world body's geoms (the floor) only.

    Only the contype/conaffinity filter changes: every pair with the floor that the model
    had is kept with the same mixed contact parameters, and pairs of two body geoms go.
    MJX allocates a contact slot for every candidate pair on every step, active or not
    (quadruped: 191 slots and 316 constraint rows, 35 and 160 without the self pairs), while
    C MuJoCo on dm_control's tasks never made a self contact in 20 episodes of random and
    bang-bang actions (`python -m benchmarks.ports.env_profile --census`)."""
    model = copy.copy(model)
    contype, conaffinity = model.geom_contype.copy(), model.geom_conaffinity.copy()
    floor = np.flatnonzero(model.geom_bodyid == 0)
    free_bit = 1 << int(contype.max() | conaffinity.max()).bit_length()  # a bit no geom uses
    for g in np.flatnonzero(model.geom_bodyid != 0):
        touches_floor = any(contype[g] & conaffinity[f] or contype[f] & conaffinity[g]
                            for f in floor)
        model.geom_contype[g] = free_bit if touches_floor else 0
        model.geom_conaffinity[g] = 0
    model.geom_conaffinity[floor] |= free_bit
    return model


class DMControlTask(Task):
    """A DM Control task on MJX: `control.Environment` semantics with legacy stepping.

    Subclasses provide `_observation(data)`, `_reward(data)` and `_initial_data(key)`.

    contacts: "floor" (default) keeps only the contacts of body geoms with the floor (see
    `floor_contacts_only`; at batch 128 quadruped steps 2.9x faster, cheetah 2.2x); "all"
    keeps dm_control's self-collision pairs too, for a policy that folds the body onto itself.

    Each port compiles its model with MJX's contact cap (`max_contacts` of the subclass,
    `tasks.physics.with_max_contacts`; None: a slot for every candidate contact), read
    back here as `self.max_contacts`.
    """

    domain = "dm_control"
    has_success = False
    cpu_group = CPU_GROUP  # batch 128: 1.7x (cheetah) to 3.6x (walker) the env steps/s
    render_camera: str | None = None  # the model's camera a video shows; None: its first
    # the dm_control suite's (domain, task) a port reproduces, which the parity checks load
    # (reference.py)
    suite: tuple[str, str] = ("", "")

    def __init__(self, model: mujoco.MjModel, control_timestep: float, time_limit: float,
                 contacts: str = "floor"):
        if contacts not in CONTACTS:
            raise ValueError(f"contacts={contacts!r}: one of {CONTACTS}")
        self.contacts = contacts
        self.max_contacts = max_contacts_of(model)
        if contacts == "floor":
            model = floor_contacts_only(model)
        self.mj_model = model
        register_render_scene(model, functools.partial(plain_scene, camera=self.render_camera))
        self.model = put_model(model)
        # opt.disableflags is static in MJX, so reset's actuation-free forward needs its own
        # model copy (built here: put_model inside a traced reset would leak tracers)
        noact = copy.copy(model)
        noact.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_ACTUATION)
        self._model_noact = put_model(noact)
        self.control_timestep = control_timestep
        # dm_control: n_sub_steps = control_timestep / physics timestep (must divide evenly)
        n_sub = control_timestep / model.opt.timestep
        if abs(n_sub - round(n_sub)) > 1e-6:
            raise ValueError("control timestep must be a multiple of the physics timestep")
        self.n_sub_steps = int(round(n_sub))
        # dm_control counts steps until time_limit / control_timestep (rounded up)
        self.episode_length = int(round(time_limit / control_timestep))
        self.action_size = model.nu
        lo, hi = model.actuator_ctrlrange[:, 0], model.actuator_ctrlrange[:, 1]
        self._ctrl_mid = jnp.asarray((hi + lo) / 2, jnp.float32)
        self._ctrl_half = jnp.asarray((hi - lo) / 2, jnp.float32)

    # -- subclass hooks -------------------------------------------------------------
    def _observation(self, data: mjx.Data) -> jax.Array:
        raise NotImplementedError

    def _reward(self, data: mjx.Data) -> jax.Array:
        raise NotImplementedError

    def _initial_data(self, key: jax.Array) -> mjx.Data:
        raise NotImplementedError

    # -- contract ---------------------------------------------------------------------
    def ctrl_from_action(self, action: jax.Array) -> jax.Array:
        """Agent actions live in [-1, 1] (as with dmc2gym); map them to the actuator range."""
        action = jnp.clip(action, -1.0, 1.0)
        return self._ctrl_mid + self._ctrl_half * action

    def reset(self, key: jax.Array) -> TaskState:
        data = self._initial_data(key)
        obs = self._observation(data)
        zero = jnp.zeros((), jnp.float32)
        return TaskState(data=data, obs=obs, true_reward=zero, success=zero,
                         terminated=jnp.zeros((), bool))

    def step(self, state: TaskState, action: jax.Array) -> TaskState:
        # keep ctrl's dtype (float64 under jax_enable_x64, used for precision checks)
        data = state.data.replace(ctrl=self.ctrl_from_action(action).astype(state.data.ctrl.dtype))
        data = legacy_substeps(self.model, data, self.n_sub_steps)
        return state.replace(
            data=data,
            obs=self._observation(data),
            true_reward=self._reward(data).astype(jnp.float32),
        )

    def settle(self, data: mjx.Data, n: int) -> mjx.Data:
        """`n` zero-control substeps from a pose just set (qpos/qvel, not yet step1-fresh), as
        dm_control's `physics.step(nstep=n)` in resets; returns step1-fresh data."""
        data = data.replace(ctrl=jnp.zeros_like(data.ctrl))
        return substeps_from_pose(self.model, data, n)

    def contacts_at_cap(self, data: mjx.Data) -> jax.Array:
        return contacts_at_cap(self.model, data, self.max_contacts)

    def forward(self, data: mjx.Data) -> mjx.Data:
        return forward(self.model, data)

    def reset_forward(self, data: mjx.Data) -> mjx.Data:
        """`mj_forward` with actuation disabled, as dm_control's `reset_context` ends.

        Matters for acceleration-stage sensors in the first observation (e.g. quadruped's
        accelerometer and force/torque): dm_control computes them with zero actuator force."""
        return forward(self._model_noact, data)

    def sensor(self, data: mjx.Data, name: str) -> jax.Array:
        sid = mujoco.mj_name2id(self.mj_model, mujoco.mjtObj.mjOBJ_SENSOR, name)
        if sid < 0:
            raise KeyError(f"sensor {name!r} not in model")
        adr, dim = self.mj_model.sensor_adr[sid], self.mj_model.sensor_dim[sid]
        return data.sensordata[adr : adr + dim]
