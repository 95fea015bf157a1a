"""The paper's per-task values in one table (appendix Tables 2-4), read by the presets and
the methods. A task without a row takes the values the appendix gives every MetaWorld task,
with its domain's λ: adding a task is its module, its registry line and, where its values
differ, a row here."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from hprior_jax.envs import task_info


@dataclass(frozen=True)
class TaskValues:
    sac_lr: float  # Table 2: SAC's learning rate
    paper_steps: int  # Table 2: environment steps of a paper run
    # Table 3 "Learning rate PEBBLE": equal to BPref's per-task SAC learning rates, so read as
    # the SAC learning rate of PbRL runs (the reward model keeps BPref's reward_lr 3e-4)
    pbrl_sac_lr: float
    pbrl_interact: int  # Table 3: steps between feedback rounds
    prior_lambda: float  # Table 4: λ of PRIOR's (and RVAR's) prior term


TASKS = {
    "cheetah_run": TaskValues(1e-3, 500_000, 5e-4, 20_000, 5.0),
    "walker_walk": TaskValues(5e-4, 500_000, 5e-4, 20_000, 5.0),
    "quadruped_walk": TaskValues(1e-4, 1_000_000, 1e-4, 30_000, 5.0),
    # Table 3's MetaWorld interval is 500 (BPref's MetaWorld scripts use 5000)
    "sweep_into": TaskValues(3e-4, 1_000_000, 3e-4, 500, 1000.0),
}
OTHER = TaskValues(3e-4, 500_000, 3e-4, 500, 1000.0)  # every other MetaWorld task
DOMAIN_LAMBDA = {"dm_control": 5.0, "metaworld": 1000.0}  # Table 4


def values(task: str) -> TaskValues:
    """The row of `task`, else MetaWorld's values with the λ of the task's domain."""
    if task in TASKS:
        return TASKS[task]
    return dataclasses.replace(OTHER, prior_lambda=DOMAIN_LAMBDA[task_info(task).domain])
