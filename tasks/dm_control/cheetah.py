"""dm_control `cheetah` `run` on MJX (dm_control/suite/cheetah.py).

Observation (17): qpos[1:] (horizontal root position dropped), qvel. Reward:
tolerance(torso subtree linear velocity x, bounds=(10, inf), margin=10, value_at_margin=0,
sigmoid='linear'). Control timestep 0.01 s = 1 substep, 10 s -> 1000 steps. Reset: limited
joints uniform in their range, then 200 zero-control settling substeps, as dm_control (the
first substep's step2 reads the drawn pose, dm_control's the default one: the same
distribution, not the same draw).

Parity (`python -m benchmarks.ports.dm_control_parity --tasks cheetah_run`): same state, obs within
3.9e-7, reward within 4.1e-8; same actions from dm_control's reset, return within 2.6e-7
over 20 steps, 5.5e-6 over 100; random-policy return 2.88 vs 3.44 (10 episodes). Details:
docs/ports/dm_control.md.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from tasks.dm_control.common import DMControlTask, load_suite_model
from tasks.physics import mjx
from tasks.rewards import tolerance

RUN_SPEED = 10.0
TIME_LIMIT = 10.0
SETTLE_STEPS = 200
# MJX's contact cap (tasks.physics.with_max_contacts): 16 candidate floor contacts; C MuJoCo
# held at most 6 at once over 60 episodes of random, bang-bang and held actions
# (`python -m benchmarks.ports.env_profile --census-counts`; on its back, 4); 8 steps 1.7x faster
# at batch 128
MAX_CONTACTS = 8


class CheetahRun(DMControlTask):
    name = "cheetah_run"
    goal_text = "Run forward (to the right) as fast as possible."
    suite = ("cheetah", "run")
    obs_size = 17

    def __init__(self, contacts: str = "floor", max_contacts: int | None = MAX_CONTACTS):
        model = load_suite_model("cheetah", max_contacts)
        super().__init__(model, control_timestep=model.opt.timestep, time_limit=TIME_LIMIT,
                         contacts=contacts)
        assert model.nq == model.njnt, "cheetah: every joint has one DOF"
        limited = np.flatnonzero(model.jnt_limited == 1)
        self._limited_qpos = jnp.asarray(model.jnt_qposadr[limited])
        self._limited_lo = jnp.asarray(model.jnt_range[limited, 0], jnp.float32)
        self._limited_hi = jnp.asarray(model.jnt_range[limited, 1], jnp.float32)

    def _initial_data(self, key: jax.Array) -> mjx.Data:
        data = mjx.make_data(self.model)
        sample = jax.random.uniform(key, self._limited_lo.shape,
                                    minval=self._limited_lo, maxval=self._limited_hi)
        data = data.replace(qpos=data.qpos.at[self._limited_qpos].set(sample))
        data = self.settle(data, SETTLE_STEPS)
        return data.replace(time=jnp.zeros_like(data.time))

    def _observation(self, data: mjx.Data) -> jax.Array:
        return jnp.concatenate([data.qpos[1:], data.qvel]).astype(jnp.float32)

    def speed(self, data: mjx.Data) -> jax.Array:
        return self.sensor(data, "torso_subtreelinvel")[0]

    def _reward(self, data: mjx.Data) -> jax.Array:
        return tolerance(self.speed(data), bounds=(RUN_SPEED, float("inf")), margin=RUN_SPEED,
                         value_at_margin=0.0, sigmoid="linear")
