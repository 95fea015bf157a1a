"""The one line the labelling page shows above a task's clips: what the teacher rewards, as
the task itself says it."""
from hprior_jax.envs import task_goal, task_names


def goal(task: str) -> str:
    """The task's goal in one line, or "" for a task without one (or not registered here)."""
    return task_goal(task) if task in task_names() else ""
