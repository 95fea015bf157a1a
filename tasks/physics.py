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
import threading

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

with contextlib.redirect_stdout(io.StringIO()):
    # mujoco.mjx prints "Failed to import warp" when the optional Warp backend is absent;
    # we only use the JAX backend, so the line is noise for our users.
    from mujoco import mjx  # noqa: E402
from mujoco.mjx._src import collision_driver as _collision_driver  # noqa: E402
from mujoco.mjx._src import solver as _mjx_solver  # noqa: E402

__all__ = ["mjx", "step1", "step2", "legacy_substeps", "substeps_from_pose", "put_model", "solve",
           "forward", "step", "linesearch_loop", "with_max_contacts", "max_contacts_of",
           "contacts_at_cap"]


# -- the constraint solver's line search: a while loop, not a scan of ls_iterations ------
# MJX runs the line search of every Newton iteration as a `lax.scan` of `opt.ls_iterations`
# (50 in dm_control's models) whose body is a `lax.cond` that stops doing work once the
# search has converged: the scan keeps reverse-mode autodiff possible. Under `vmap` the cond
# becomes a select, so all 50 bodies run for every env on every Newton iteration, although
# C MuJoCo needs 1.7-2.6 line-search evaluations per iteration on these tasks. That was
# 78% of a cheetah substep at batch 128. A `lax.while_loop` on the same condition runs
# only until every env of the batch has converged and returns the same values bit for bit
# (the finished iterations of the scan are no-ops); it is not reverse-differentiable, which
# no task needs. The swap holds only while the solver is traced through `solve`, `forward`
# or `step` below, under a lock so concurrent traces through them do not undo each other's
# swap (a plain `mjx.solve` traced in another thread at that moment would see it).
_MJX_LINESEARCH_LOOP = _mjx_solver._while_loop_scan
_LINESEARCH_LOCK = threading.RLock()


def _while_loop(cond_fun, body_fun, init_val, max_iter):
    del max_iter  # the condition itself stops at opt.ls_iterations
    return jax.lax.while_loop(cond_fun, body_fun, init_val)


_LINESEARCH_LOOPS = {"while": _while_loop, "scan": _MJX_LINESEARCH_LOOP}
_linesearch_loop = "while"


@contextlib.contextmanager
def linesearch_loop(kind: str):
    """Traces `solve`/`forward`/`step` inside the block with the line search as `kind`:
    "while" (the default) or "scan" (MJX's own), for benchmarks and the equality test."""
    global _linesearch_loop
    if kind not in _LINESEARCH_LOOPS:
        raise ValueError(f"linesearch loop {kind!r}: one of {sorted(_LINESEARCH_LOOPS)}")
    previous, _linesearch_loop = _linesearch_loop, kind
    try:
        yield
    finally:
        _linesearch_loop = previous


@contextlib.contextmanager
def _traced_linesearch():
    with _LINESEARCH_LOCK:
        previous = _mjx_solver._while_loop_scan
        _mjx_solver._while_loop_scan = _LINESEARCH_LOOPS[_linesearch_loop]
        try:
            yield
        finally:
            _mjx_solver._while_loop_scan = previous


def solve(m: mjx.Model, d: mjx.Data) -> mjx.Data:
    """`mjx.solve` with the line search as a while loop (same result, see above)."""
    with _traced_linesearch():
        return mjx.solve(m, d)


def forward(m: mjx.Model, d: mjx.Data) -> mjx.Data:
    """`mjx.forward` with the line search as a while loop."""
    with _traced_linesearch():
        return mjx.forward(m, d)


def step(m: mjx.Model, d: mjx.Data) -> mjx.Data:
    """`mjx.step` with the line search as a while loop."""
    with _traced_linesearch():
        return mjx.step(m, d)


def put_model(model: mujoco.MjModel) -> mjx.Model:
    return mjx.put_model(model, impl="jax")


# MJX's collision reads this custom numeric: after the narrow phase it keeps only the K
# deepest contacts of each condim group (`lax.top_k` on the distance) and allocates contact
# slots and constraint rows for those K alone. While no more than K contacts are active at
# once, the kept set holds every active one and the dynamics are the same up to rounding
# (the rows come in another order); inactive slots carry no force but cost solver work.
MAX_CONTACTS_NUMERIC = "max_contact_points"


def with_max_contacts(xml: str | bytes, max_contacts: int | None) -> str:
    """`xml` (a whole MJCF document) with MJX's contact cap set to `max_contacts` (None:
    unchanged, a slot for every candidate contact). C MuJoCo ignores the numeric."""
    xml = xml.decode() if isinstance(xml, bytes) else xml
    if max_contacts is None:
        return xml
    if max_contacts < 1:
        raise ValueError(f"max_contacts={max_contacts}: at least 1, or None for no cap")
    end = xml.rindex("</mujoco>")
    numeric = f'<numeric name="{MAX_CONTACTS_NUMERIC}" data="{int(max_contacts)}"/>'
    return xml[:end] + f"<custom>{numeric}</custom>" + xml[end:]


def max_contacts_of(model: mujoco.MjModel) -> int | None:
    """The contact cap MJX applies to `model` (`with_max_contacts`), None if uncapped."""
    i = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_NUMERIC, MAX_CONTACTS_NUMERIC)
    return None if i < 0 else int(model.numeric_data[model.numeric_adr[i]])


def contacts_at_cap(m: mjx.Model, d: mjx.Data, max_contacts: int | None) -> jax.Array:
    """bool[]: some condim group with `max_contacts` slots (the cap's, or exactly that many
    candidates: then a false alarm) has all of them active in `d`, i.e. MJX may have dropped
    shallower contacts (only the last collision before `d` is seen; None: no cap, never)."""
    if max_contacts is None or d._impl.contact.dist.shape[-1] == 0:
        return jnp.zeros((), bool)
    dims = _collision_driver.make_condim(m)  # static: the condim of every slot
    c = d._impl.contact
    active = c.dist - c.includemargin < 0
    full = [jnp.all(active[dims == k]) for k in np.unique(dims)
            if (dims == k).sum() == max_contacts]
    return jnp.any(jnp.stack(full)) if full else jnp.zeros((), bool)


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
        d = solve(m, d)
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


def substeps_from_pose(m: mjx.Model, d: mjx.Data, n: int) -> mjx.Data:
    """`legacy_substeps(m, step1(m, d), n)` for data whose qpos/qvel were just set (not
    step1-fresh), with one copy of each stage in the program: a scan of n + 1 (step1, step2)
    whose last step2 is skipped (a `lax.cond` on the scan's own counter, so a real branch
    under vmap too). A step1 before the loop would be a second copy of the position stage
    (collision, constraint rows): on cheetah's reset, vmapped over 16 keys, that copy was
    half the compile (12.0 -> 6.0 s). The same operations in the same order; XLA rounds the
    loop's first step1 differently from one outside it (float32 rounding after the settle)."""
    def body(d, i):
        d = step1(m, d)
        return jax.lax.cond(i < n, lambda d: step2(m, d), lambda d: d, d), None

    return jax.lax.scan(body, d, jnp.arange(n + 1))[0]
