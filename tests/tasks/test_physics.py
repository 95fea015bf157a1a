"""The speed-ups of the DM Control ports that must not change their physics.

- `tasks.physics` traces MJX's constraint line search as a while loop: the result must be
  the scan's, bit for bit, on states with active contacts.
- `contacts="floor"` drops the self-collision pairs: every floor pair stays with the same
  contact parameters, and a C MuJoCo trajectory is unchanged (no self contact occurs).
- MJX's contact cap (`max_contacts`) keeps the deepest contacts only: with no more active
  than the cap, the same trajectory up to rounding.
"""
import itertools
import json

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

import tasks
from hprior_jax.config import RunConfig
from hprior_jax.envs import task_options
from tasks import physics
from tasks.dm_control.common import floor_contacts_only
from tasks.dm_control.reference import ports
from tests.xla_opt import AS_RUNS


def _collides(m: mujoco.MjModel, g1: int, g2: int) -> bool:
    """MuJoCo's contype/conaffinity filter for two geoms of different bodies."""
    return bool(m.geom_contype[g1] & m.geom_conaffinity[g2]
                or m.geom_contype[g2] & m.geom_conaffinity[g1])


@pytest.mark.parametrize("name", ports())
def test_floor_contacts_keep_every_floor_pair_and_no_other(name):
    full = tasks.make(name, contacts="all").mj_model
    floor = floor_contacts_only(full)
    world = set(np.flatnonzero(full.geom_bodyid == 0).tolist())
    pairs = [(a, b) for a, b in itertools.combinations(range(full.ngeom), 2)
             if full.geom_bodyid[a] != full.geom_bodyid[b]]
    kept = {p for p in pairs if _collides(floor, *p)}
    assert kept == {p for p in pairs if _collides(full, *p) and world & set(p)}
    assert kept, "the floor must still collide with the body"
    self_pairs = [p for p in pairs if _collides(full, *p) and not world & set(p)]
    if name != "walker_walk":  # walker's XML already has no self pairs
        assert self_pairs, "nothing was removed: the test would not see a change"


@pytest.mark.parametrize("name", ["cheetah_run", "quadruped_walk"])
def test_floor_contacts_leave_a_c_trajectory_unchanged(name):
    """C MuJoCo, 300 steps of bang-bang actions from the same state on both models: the
    same states bit for bit (same floor contacts, same mixed parameters)."""
    full = tasks.make(name, contacts="all").mj_model
    floor = floor_contacts_only(full)
    rng = np.random.RandomState(0)
    data = [mujoco.MjData(m) for m in (full, floor)]
    for d in data:
        d.qpos[:] = full.qpos0
        d.qpos[2] += 0.3 if name == "quadruped_walk" else 0.0  # let the body drop and land
    touched = 0
    for _ in range(300):
        ctrl = np.where(rng.rand(full.nu) < 0.5, *full.actuator_ctrlrange.T)
        for m, d in zip((full, floor), data):
            d.ctrl[:] = ctrl
            mujoco.mj_step(m, d)
        touched += data[0].ncon > 0
        np.testing.assert_array_equal(data[0].qpos, data[1].qpos)
        assert data[0].ncon == data[1].ncon
    assert touched > 100, "the trajectory must be in contact with the floor"


def test_linesearch_while_loop_equals_mjx_scan():
    """`physics.forward` (line search as a while loop) and MJX's own scan, on cheetah poses
    lowered until one or both feet are 2-17 cm into the floor: the same accelerations and
    constraint forces, bit for bit."""
    task = tasks.make("cheetah_run")
    rootz = task.mj_model.jnt_qposadr[mujoco.mj_name2id(task.mj_model, mujoco.mjtObj.mjOBJ_JOINT,
                                                         "rootz")]
    base = physics.mjx.make_data(task.model)
    data = jax.vmap(lambda z: base.replace(qpos=base.qpos.at[rootz].set(z)))(
        jax.numpy.linspace(-0.25, -0.1, 4))

    def forward(kind):
        with physics.linesearch_loop(kind):
            return jax.jit(jax.vmap(lambda d: physics.forward(task.model, d)),
                           compiler_options=AS_RUNS)(data)  # bit for bit as runs compile

    a, b = forward("while"), forward("scan")
    assert np.asarray(a._impl.contact.dist < 0).sum() >= 4, "no active contact to solve"
    assert np.abs(np.asarray(a._impl.efc_force)).max() > 1.0
    np.testing.assert_array_equal(np.asarray(a.qacc), np.asarray(b.qacc))
    np.testing.assert_array_equal(np.asarray(a._impl.efc_force), np.asarray(b._impl.efc_force))
    with pytest.raises(ValueError, match="linesearch loop"):
        with physics.linesearch_loop("fori"):
            pass


def test_runs_before_the_contacts_option_restore_with_all_contacts():
    d = RunConfig(task="cheetah_run", algo="sac").to_json()
    old = {k: v for k, v in json.loads(d).items() if k != "contacts"}
    assert RunConfig.from_dict(old).contacts == "all"
    assert RunConfig.from_dict(json.loads(d)).contacts == "floor"
    assert task_options(RunConfig(task="cheetah_run", algo="sac")) == {}  # the ports' default
    assert task_options(RunConfig(task="cheetah_run", algo="sac", contacts="all")) == {
        "contacts": "all"}
    assert task_options(RunConfig(task="drawer_open", algo="sac")) == {}
    with pytest.raises(ValueError, match="only the DM Control ports"):
        task_options(RunConfig(task="drawer_open", algo="sac", contacts="all"))


def test_runs_before_the_hand_option_restore_with_the_free_hand():
    """A MetaWorld run written before `hand` restores with the free hand (and the contacts
    default: MetaWorld ports have only explicit pairs); a DM Control one is unaffected."""
    d = json.loads(RunConfig(task="drawer_open", algo="sac").to_json())
    old = {k: v for k, v in d.items() if k not in ("hand", "contacts")}
    assert (RunConfig.from_dict(old).hand, RunConfig.from_dict(old).contacts) == ("free", "floor")
    assert task_options(RunConfig.from_dict(old)) == {"arm": False, "wrist": "box"}
    assert RunConfig.from_dict(d).hand == "arm"
    dmc = json.loads(RunConfig(task="cheetah_run", algo="sac").to_json())
    assert RunConfig.from_dict({k: v for k, v in dmc.items() if k != "hand"}).hand == "arm"
    with pytest.raises(ValueError, match="only the MetaWorld ports"):
        task_options(RunConfig(task="cheetah_run", algo="sac", hand="free"))


def test_button_press_runs_before_format_3_restore_with_the_wrist_they_trained_on():
    """Before format 3 button_press's registered arm scene had the box wrist and the faithful
    one was `wrist: faithful`; today `task` is the faithful wrist and `box` an option of
    button_press alone."""
    d = json.loads(RunConfig(task="button_press", algo="sac").to_json())
    assert d["format"] == 3 and RunConfig.from_dict(d).wrist == "task"
    old = {**d, "format": 2}
    assert RunConfig.from_dict(old).wrist == "box"
    assert RunConfig.from_dict({**old, "wrist": "faithful"}).wrist == "task"
    assert RunConfig.from_dict({**old, "hand": "free"}).wrist == "task"  # free: the box anyway
    drawer = {**json.loads(RunConfig(task="drawer_open", algo="sac").to_json()), "format": 2}
    assert RunConfig.from_dict(drawer).wrist == "task"
    assert task_options(RunConfig.from_dict(old)) == {"wrist": "box"}
    with pytest.raises(ValueError, match="registered wrist is not the box"):
        task_options(RunConfig(task="drawer_open", algo="sac", wrist="box"))


def _forward(task, q):
    return physics.forward(task.model, physics.mjx.make_data(task.model).replace(qpos=q))


def _sunk_poses(task, n: int = 8, seed: int = 0) -> jax.Array:
    """`n` poses of `task` with random joint angles, each sunk until its lowest point is
    2-20 cm under the floor."""
    m, rng = task.mj_model, np.random.RandomState(seed)
    qpos = np.tile(m.qpos0, (n, 1))
    for j in range(m.njnt):
        if m.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE and m.jnt_limited[j]:
            qpos[:, m.jnt_qposadr[j]] = rng.uniform(*m.jnt_range[j], size=n)
    free = m.jnt_type[0] == mujoco.mjtJoint.mjJNT_FREE
    z = int(m.jnt_qposadr[0]) + 2 if free else int(m.jnt_qposadr[m.joint("rootz").id])
    lowest = jax.jit(jax.vmap(lambda q: _forward(task, q)._impl.contact.dist.min()))
    q = jnp.asarray(qpos, jnp.float32)
    return q.at[:, z].add(-lowest(q) - jnp.asarray(rng.uniform(0.02, 0.2, size=n), q.dtype))


@pytest.mark.parametrize("name", ports())
def test_contact_cap_keeps_every_active_contact(name):
    """The capped port (the default) and the uncapped one, `forward` on 8 poses sunk 2-20 cm
    into the floor with random joint angles: the cap allocates its slots only, every active
    contact is among them, and the accelerations agree to float32 rounding. (Trajectories
    against dm_control: the parity tests in test_dm_control_tasks.py run the capped ports.)"""
    capped = tasks.make(name)
    if capped.max_contacts is None:
        pytest.skip(f"{name} keeps a slot for every candidate contact")
    full = tasks.make(name, max_contacts=None)
    assert full.max_contacts is None
    q = _sunk_poses(full)
    a, b = (jax.jit(jax.vmap(lambda q, t=t: _forward(t, q)))(q) for t in (capped, full))
    assert a._impl.contact.dist.shape[-1] == capped.max_contacts < b._impl.contact.dist.shape[-1]
    active_a, active_b = (np.asarray(d._impl.contact.dist < 0).sum(-1) for d in (a, b))
    assert active_b.max() >= 3, "the poses must make several contacts"
    assert active_b.max() <= capped.max_contacts
    np.testing.assert_array_equal(active_a, active_b)
    # The constraint solve rounds relative to a pose's largest acceleration (up to ~1e4 here),
    # so a small component may differ by more than 1e-3 of itself.
    for qacc_a, qacc_b in zip(np.asarray(a.qacc), np.asarray(b.qacc)):
        np.testing.assert_allclose(qacc_a, qacc_b, rtol=1e-3, atol=1e-5 * np.abs(qacc_b).max())
    assert not np.any(jax.jit(jax.vmap(capped.contacts_at_cap))(a)), "the cap was not full"
    assert not np.any(jax.jit(jax.vmap(full.contacts_at_cap))(b)), "no cap, never full"


def test_contacts_at_cap_flags_a_full_cap():
    """cheetah with a cap of 2 on the sunk poses: flagged exactly where 2 or more contacts
    are active (then the deepest 2 fill the slots and any others are dropped)."""
    full, tight = tasks.make("cheetah_run", max_contacts=None), tasks.make("cheetah_run",
                                                                          max_contacts=2)
    q = _sunk_poses(full)
    active = np.asarray(jax.jit(jax.vmap(lambda q: (_forward(full, q)._impl.contact.dist < 0)
                                         .sum()))(q))
    flagged = np.asarray(jax.jit(jax.vmap(lambda q: tight.contacts_at_cap(_forward(tight, q))))(q))
    assert active.min() < 2 <= active.max(), active
    np.testing.assert_array_equal(flagged, active >= 2)


def test_contact_cap_numeric():
    xml = "<mujoco><worldbody><geom size='1 1 1' type='plane'/></worldbody></mujoco>"
    assert physics.with_max_contacts(xml, None) == xml
    model = mujoco.MjModel.from_xml_string(physics.with_max_contacts(xml.encode(), 5))
    assert physics.max_contacts_of(model) == 5
    assert physics.max_contacts_of(mujoco.MjModel.from_xml_string(xml)) is None
    with pytest.raises(ValueError, match="at least 1"):
        physics.with_max_contacts(xml, 0)


def test_runs_before_the_contact_cap_restore_uncapped():
    d = json.loads(RunConfig(task="quadruped_walk", algo="sac").to_json())
    assert RunConfig.from_dict(d).contact_cap == "task"
    old = RunConfig.from_dict({k: v for k, v in d.items() if k != "contact_cap"})
    assert old.contact_cap == "none"
    assert task_options(old) == {"max_contacts": None}
    mw = json.loads(RunConfig(task="drawer_open", algo="sac").to_json())
    old = RunConfig.from_dict({k: v for k, v in mw.items() if k != "contact_cap"})
    assert old.contact_cap == "none"
    assert task_options(old) == {"max_contacts": None}
