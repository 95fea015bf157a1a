"""The whole state of a run: one pytree, every leaf with a leading seed axis."""
from __future__ import annotations

from typing import Any

import jax
from flax import struct

from hprior_jax.agents.sac import SACState
from hprior_jax.buffers.replay import ReplayState
from hprior_jax.envs import EnvState


@struct.dataclass
class RunState:
    sac: SACState
    replay: ReplayState
    env: EnvState
    key: jax.Array  # raw uint32[2] key (checkpoint-friendly)
    method: Any = None  # the method's own state (its `init` says which type; None for SAC)
