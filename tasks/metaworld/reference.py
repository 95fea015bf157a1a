"""Builds the reference metaworld (C MuJoCo) environments the parity checks compare against.

metaworld 3.0.0 writes 11-wide weld rows into `model.eq_data` (anchor 3, relpose pos 3,
relpose quat 4, torquescale 1). MuJoCo 3.17 has mjNEQDATA = 12 (a 12th column that MJX
and the weld constraint do not read), so the stock `reset_mocap_welds` raises on this pin.
We patch it to write the same 11 values into the first 11 columns and leave the 12th as
compiled: numerically that is exactly what metaworld intends.
Each port names its metaworld env and scripted policy (class attributes of its class, read
without building its scene). Imported only by tests and benchmarks (metaworld is not needed
to *run* a port).
"""
from __future__ import annotations

import mujoco
import numpy as np

import tasks

# metaworld's weld row: anchor 0, relpose identity (quat -1 0 0 0), torquescale 5
WELD_ROW = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, 5.0])

_patched = False


def _reset_mocap_welds(self) -> None:
    if self.model.nmocap > 0 and self.model.eq_data is not None:
        for i in range(self.model.eq_data.shape[0]):
            if self.model.eq_type[i] == mujoco.mjtEq.mjEQ_WELD:
                self.model.eq_data[i, : WELD_ROW.size] = WELD_ROW


def ports() -> list[str]:
    """The registered MetaWorld ports, by name."""
    return [n for n in tasks.names() if tasks.info(n).domain == "metaworld"]


def patch_metaworld() -> None:
    """Makes metaworld 3.0.0's weld reset work on MuJoCo builds with wider eq_data."""
    global _patched
    if _patched:
        return
    from metaworld.sawyer_xyz_env import SawyerMocapBase

    SawyerMocapBase.reset_mocap_welds = _reset_mocap_welds
    _patched = True


def metaworld_version() -> str:
    from importlib.metadata import version

    return version("metaworld")


def make_env(task: str, seed: int = 0, partially_observable: bool = True):
    """The metaworld v3 env for one of our task names, configured like BPref.

    BPref: `_freeze_rand_vec = False` (new object/goal positions at every reset) and
    `_set_task_called = True`; `seed` seeds the env's own generator, and we switch
    `seeded_rand_vec` on so resets draw from it (not from global np.random)."""
    patch_metaworld()
    from metaworld.env_dict import ALL_V3_ENVIRONMENTS

    env = ALL_V3_ENVIRONMENTS[tasks.task_class(task).metaworld_env]()
    env._freeze_rand_vec = False
    env._set_task_called = True
    env.seeded_rand_vec = True
    env._partially_observable = partially_observable
    # the observation space (and so the clip of the goal slots in `step`) is a cached_property
    # that construction already computed with the default; drop it as metaworld's set_task does
    env.__dict__.pop("sawyer_observation_space", None)
    env.seed(seed)
    return env


def policy_env(name: str, seed: int):
    """The metaworld env whose observations the scripted policy is run on: goal-observable
    where the policy steers by the goal (`policy_reads_goal` of the port; the port's
    observation then gets the goal from its info)."""
    return make_env(name, seed=seed,
                    partially_observable=not tasks.task_class(name).policy_reads_goal)


def scripted_policy(task: str):
    """metaworld's scripted policy for the task (metaworld.policies)."""
    from metaworld import policies

    return getattr(policies, tasks.task_class(task).scripted_policy)()


def explore_action(policy, obs, rng: np.random.Generator, noise: float, random: bool):
    """An action of the states the parity checks visit: uniform in [-1, 1]^4 (a random
    episode), or metaworld's scripted action with Gaussian noise, clipped."""
    if random:
        return rng.uniform(-1, 1, 4)
    return np.clip(policy.get_action(obs) + noise * rng.standard_normal(4), -1, 1)
