"""The one line the labelling page shows above a task's clips: what the teacher rewards."""

GOALS = {
    "cheetah_run": "Run forward (to the right) as fast as possible.",
    "walker_walk": "Walk forward while staying upright, torso high.",
    "quadruped_walk": "Walk forward.",
    "drawer_open": "Pull the drawer open.",
    "button_press": "Press the button in with the gripper.",
    "door_open": "Swing the door open.",
    "window_open": "Slide the window open.",
    "door_unlock": "Turn the lock's lever to unlock the door.",
    "sweep_into": "Sweep the puck into the hole.",
}


def goal(task: str) -> str:
    """The task's goal in one line, or "" for a task without one here."""
    return GOALS.get(task, "")
