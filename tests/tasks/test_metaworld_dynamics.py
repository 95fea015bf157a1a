"""Closed-loop dynamics parity of the MetaWorld ports (issue 18): metaworld's scripted policy
drives metaworld's env and the MJX port; the port must *move* like metaworld, not only score
like it. The fast tests share one short run of one task; the full six-task comparison
(20 episodes a side, 500 steps) is the slow test and `python -m benchmarks.metaworld_dynamics`."""
import pytest

import tasks
from benchmarks.metaworld_dynamics import TASKS, run_metaworld, run_port, targets

STEPS = 100  # button_press: the press happens at steps ~50-70


@pytest.fixture(scope="module")
def button_runs():
    name = "button_press"
    mw = run_metaworld(name, episodes=2, seed=0, steps=STEPS)
    port = run_port(tasks.make(name), name, episodes=2, seed=0, steps=STEPS)
    return mw, port


def test_button_press_stays_in_its_box(button_runs):
    """The button must not go deeper than metaworld's own excursion + 2 cm (issue 18's
    target is 1 cm; the port misses it by 0.7 cm over 20 episodes, see the task's
    docstring; this test is there to catch the pass-through, 27 cm deep). metaworld stops
    it with the cap against the box face at -0.083 (its joint range is [-0.06, 0], a soft
    limit that the push overpowers); the first port had no box, its gripper pushed the
    button to -0.35 and through the success zone, so success at the last step was 0%."""
    mw, port = button_runs
    assert port["joint_min"] >= mw["joint_min"] - 0.02, (port, mw)
    assert port["success_last"] == 1.0, port


def test_button_press_hand_trails_mocap_like_metaworld(button_runs):
    """Over these 100 steps (approach and press) the hand trails the mocap within 30% of
    metaworld's (the first port: 0.007 m against ~0.1, the hand went through the button).
    Over the whole 500 steps the port's hand still trails less: 0.141 vs 0.223 m (x0.63,
    button_press docstring; checked by the slow test below)."""
    mw, port = button_runs
    assert 0.7 <= port["hand_mocap_mean"] / mw["hand_mocap_mean"] <= 1.3, (port, mw)


@pytest.mark.slow
@pytest.mark.parametrize("name", TASKS)
def test_closed_loop_targets(name):
    """Issue 18's targets per task, 20 episodes a side, 500 steps."""
    mw = run_metaworld(name, episodes=20, seed=0)
    port = run_port(tasks.make(name), name, episodes=20, seed=0)
    res = targets(port, mw)
    assert res["all_met"], (res, port, mw)
