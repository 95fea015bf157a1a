"""MJX stepping helpers shared by the task ports.

dm_control's `Physics.step` (legacy mode, the default) runs `mj_step2` then `mj_step1`, so
after a control step every position- and velocity-dependent quantity (xpos, sensors of the
position and velocity stages, subtree velocities) is up to date with the *new* qpos/qvel.
`mjx.step` instead does forward-then-integrate, which leaves those quantities one substep
stale. `step2`/`step1` below split MJX's forward the same way MuJoCo does, so a port can keep
its data "step1-fresh" at the same cost as `mjx.step` (one forward per substep).
"""
from __future__ import annotations

import contextlib
import io

import jax
import mujoco

with contextlib.redirect_stdout(io.StringIO()):
    # mujoco.mjx prints "Failed to import warp" when the optional Warp backend is absent;
    # we only use the JAX backend, so the line is noise for our users.
    from mujoco import mjx  # noqa: E402

__all__ = ["mjx", "step1", "step2", "legacy_substeps", "put_model"]


def put_model(model: mujoco.MjModel) -> mjx.Model:
    return mjx.put_model(model, impl="jax")


def step1(m: mjx.Model, d: mjx.Data) -> mjx.Data:
    """Position and velocity stages (MuJoCo's `mj_step1`)."""
    d = mjx.fwd_position(m, d)
    d = mjx.sensor_pos(m, d)
    d = mjx.fwd_velocity(m, d)
    d = mjx.sensor_vel(m, d)
    return d


def step2(m: mjx.Model, d: mjx.Data) -> mjx.Data:
    """Actuation, acceleration, constraints and integration (MuJoCo's `mj_step2`).

    Assumes `step1` has been run on the current qpos/qvel (so the ctrl set just before is
    what drives this substep, as in MuJoCo)."""
    d = mjx.fwd_actuation(m, d)
    d = mjx.fwd_acceleration(m, d)
    if d._impl.efc_J.size == 0:  # no constraint rows: same shortcut as mjx.forward
        d = d.replace(qacc=d.qacc_smooth)
    else:
        d = mjx.solve(m, d)
        d = mjx.sensor_acc(m, d)
    integrator = mujoco.mjtIntegrator(int(m.opt.integrator))
    if integrator == mujoco.mjtIntegrator.mjINT_EULER:
        return mjx.euler(m, d)
    if integrator == mujoco.mjtIntegrator.mjINT_IMPLICITFAST:
        return mjx.implicit(m, d)
    raise NotImplementedError(
        f"integrator {integrator.name} is not supported by step2; dm_control's RK4 models "
        "use plain mj_step, port them with mjx.step instead"
    )


def legacy_substeps(m: mjx.Model, d: mjx.Data, n: int) -> mjx.Data:
    """`n` substeps with dm_control's legacy stepping: (step2, step1) n times.

    Input data must be step1-fresh (e.g. after `mjx.forward`); so is the output."""

    def body(d, _):
        return step1(m, step2(m, d)), None

    if n == 1:
        return body(d, None)[0]
    return jax.lax.scan(body, d, None, length=n)[0]
