"""JAX ports of metaworld.utils.reward_utils (tolerance, hamacher_product) and the small
geometric helpers the v3 reward functions need.

Unlike `tasks.rewards.tolerance` (dm_control, static margins), MetaWorld margins are often
distances measured at reset (e.g. `tcp_to_obj_init`), so `margin` may be a traced array.
"""
from __future__ import annotations

import math

import jax.numpy as jnp

_DEFAULT_VALUE_AT_MARGIN = 0.1


def _long_tail(x, value_at_1: float):
    scale = math.sqrt(1 / value_at_1 - 1)
    return 1 / ((x * scale) ** 2 + 1)


def _gaussian(x, value_at_1: float):
    scale = math.sqrt(-2 * math.log(value_at_1))
    return jnp.exp(-0.5 * (x * scale) ** 2)


_SIGMOIDS = {"long_tail": _long_tail, "gaussian": _gaussian}


def tolerance(x, bounds=(0.0, 0.0), margin=0.0, sigmoid: str = "gaussian",
              value_at_margin: float = _DEFAULT_VALUE_AT_MARGIN):
    """metaworld `tolerance`: 1 inside `bounds`, sigmoid decay outside, `margin` may be traced.

    margin == 0 gives a step (1 inside, 0 outside), as in metaworld. Only the sigmoids the
    v3 rewards use ("long_tail", "gaussian") are ported."""
    lower, upper = bounds
    if sigmoid not in _SIGMOIDS:
        raise ValueError(f"sigmoid {sigmoid!r} is not ported; add it to _SIGMOIDS")
    x = jnp.asarray(x, jnp.float32)
    margin = jnp.asarray(margin, jnp.float32)
    in_bounds = jnp.logical_and(lower <= x, x <= upper)
    safe_margin = jnp.where(margin > 0, margin, 1.0)  # avoid 0/0 in the unused branch
    d = jnp.where(x < lower, lower - x, x - upper) / safe_margin
    outside = jnp.where(margin > 0, _SIGMOIDS[sigmoid](d, value_at_margin), 0.0)
    return jnp.where(in_bounds, 1.0, outside)


def hamacher_product(a, b):
    """(a*b) / (a + b - a*b), 0 where the denominator is 0 (metaworld)."""
    denom = a + b - a * b
    safe = jnp.where(denom > 0, denom, 1.0)
    return jnp.where(denom > 0, a * b / safe, 0.0)


def mat_to_quat_scipy(mat):
    """scipy `Rotation.from_matrix(m).as_quat()` (x, y, z, w order, scipy's branch choice).

    metaworld reports some object orientations this way (door handle, sweep puck), so the
    observation only matches if we pick the same of the two signs as scipy."""
    m = mat.reshape(3, 3)
    decision = jnp.stack([m[0, 0], m[1, 1], m[2, 2], m[0, 0] + m[1, 1] + m[2, 2]])
    choice = jnp.argmax(decision)
    # branch i in (0, 1, 2): quat[i] = 1 - trace + 2 m_ii, others from off-diagonals
    def branch(i):
        j, k = (i + 1) % 3, (i + 2) % 3
        q = jnp.zeros(4)
        q = q.at[i].set(1 - decision[3] + 2 * m[i, i])
        q = q.at[j].set(m[j, i] + m[i, j])
        q = q.at[k].set(m[k, i] + m[i, k])
        q = q.at[3].set(m[k, j] - m[j, k])
        return q
    q_trace = jnp.stack([m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1],
                         1 + decision[3]])
    qs = jnp.stack([branch(0), branch(1), branch(2), q_trace])
    q = qs[choice]
    return q / jnp.linalg.norm(q)
