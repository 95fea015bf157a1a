"""Closed-loop dynamics parity of the MetaWorld ports: metaworld's scripted policy
drives metaworld's env and the MJX port; the port must *move* like metaworld, not only score
like it. Fast: one short MJX run of button_press, a short C MuJoCo run of drawer_open's
scene, and the constraint weights the scenes keep; the full six-task comparison (20 episodes
a side, 500 steps) is the slow test and `python -m benchmarks.ports.metaworld_dynamics`."""
import numpy as np
import pytest

import tasks
from tasks.metaworld.closed_loop import make_task, run_metaworld, run_port, run_port_c, targets
from tasks.metaworld.reference import ports
from tasks.metaworld.scene import load_full_model

STEPS = 100  # button_press: the press happens at steps ~50-70


@pytest.fixture(scope="module")
def button_runs():
    name = "button_press"
    mw = run_metaworld(name, episodes=2, seed=0, steps=STEPS)
    port = run_port(tasks.make(name), name, episodes=2, seed=0, steps=STEPS)
    return mw, port


def test_button_press_stays_in_its_box(button_runs):
    """The button must not go deeper than metaworld's own excursion + 2 cm (the closed-loop
    target is 1 cm, which the port meets over 20 episodes: -0.087 vs -0.084; 2 episodes
    here; this test is there to catch the pass-through, 27 cm deep). metaworld stops
    it with the cap against the box face at -0.083 (its joint range is [-0.06, 0], a soft
    limit that the push overpowers); the first port had no box, its gripper pushed the
    button to -0.35 and through the success zone, so success at the last step was 0%."""
    mw, port = button_runs
    assert port["joint_min"] >= mw["joint_min"] - 0.02, (port, mw)
    assert port["success_last"] == 1.0, port


def test_button_press_hand_trails_mocap_like_metaworld(button_runs):
    """Over these 100 steps (approach and press) the hand trails the mocap within 30% of
    metaworld's (the first port: 0.007 m against ~0.1, the hand went through the button).
    Over the whole 500 steps: 0.237 vs 0.223 m (x1.06; the slow test below)."""
    mw, port = button_runs
    assert 0.7 <= port["hand_mocap_mean"] / mw["hand_mocap_mean"] <= 1.3, (port, mw)


def test_scene_keeps_metaworld_constraint_weights():
    """MuJoCo scales a soft constraint's force by compile-time inverse weights; the free
    hand's own (0.97 against metaworld's arm-held 6.1) made the mocap weld 6x stiffer and
    the hand dragged the drawer 6 cm past metaworld's stop. The wrist keeps the weight of
    the arm body that carries it in metaworld (`right_hand`), not the hand's."""
    task = make_task("button_press", "free")
    m, full = task.mj_model, load_full_model(task.scene.xml)
    for scene in (m, tasks.make("button_press").mj_model):  # the free hand; the arm
        for body in ("hand", "rightclaw", "leftpad", "right_hand", "button"):
            np.testing.assert_allclose(scene.body_invweight0[scene.body(body).id],
                                       full.body_invweight0[full.body(body).id], rtol=1e-12)
        wrist = [g for g in range(scene.ngeom) if scene.geom(g).name.startswith("wrist")]
        assert wrist and set(scene.geom_bodyid[wrist]) == {scene.body("right_hand").id}
    # the free hand's own weights (without the copy)
    own = type(task)(arm=False, wrist="box", metaworld_invweights=False).mj_model
    assert own.body_invweight0[own.body("hand").id][0] < 0.2 * m.body_invweight0[
        m.body("hand").id][0]


def test_exact_shape_scenes_build_for_c_mujoco():
    """`--wrist mesh` and `--keep-cylinders` (C MuJoCo diagnostics, benchmarks'
    port_c side): the cap stays a cylinder, the wrist is metaworld's mesh, and the MJX
    model (kinematics, reset) is the box-wrist scene's, body for body."""
    import mujoco

    exact = make_task("button_press", wrist="mesh")
    kept = make_task("button_press", wrist="box", keep_cylinders=True)
    registered = tasks.make("button_press")
    paired = lambda m: m.geom_type[np.r_[m.pair_geom1, m.pair_geom2]].tolist()
    for task in (exact, kept):
        assert mujoco.mjtGeom.mjGEOM_CYLINDER in paired(task.mj_model)
        assert task.model.nbody == task.mj_model.nbody and task.model.njnt == task.mj_model.njnt
    assert mujoco.mjtGeom.mjGEOM_CYLINDER not in paired(registered.mj_model)  # MJX's: a box
    assert exact.mj_model.geom_type[exact.mj_model.geom("wrist").id] == mujoco.mjtGeom.mjGEOM_MESH
    assert kept.mj_model.geom_type[kept.mj_model.geom("wrist").id] == mujoco.mjtGeom.mjGEOM_BOX


def test_wrist_pieces_span_the_mesh_and_meet_the_box_slab_by_slab():
    """`wrist="coacd:..."`: convex pieces of metaworld's wrist mesh, each on at most POINTS
    hull points, inside the mesh's hull and spanning its extent, paired with the box's 4
    slabs where the box wrist meets one solid stand-in."""
    import mujoco
    from scipy.spatial import ConvexHull

    from tasks.metaworld import colliders
    from tasks.metaworld.scene import _load_named

    task = make_task("button_press", wrist="coacd:0.3:8:24:0,1")
    m = task.mj_model
    names = [m.geom(g).name for g in range(m.ngeom)]
    pieces = [n for n in names if n.startswith("wrist_")]
    assert pieces == ["wrist_0", "wrist_1"] and "box_hull" not in names
    pairs = {(m.geom(a).name, m.geom(b).name) for a, b in zip(m.pair_geom1, m.pair_geom2)}
    slabs = [m.geom(g).name for g in range(m.ngeom) if m.geom_bodyid[g] == m.body("buttonbox").id
             and m.geom_type[g] == mujoco.mjtGeom.mjGEOM_BOX]
    assert len(slabs) == 4 and all((w, s) in pairs for w in pieces for s in slabs)
    for w in pieces:
        assert m.mesh_vertnum[m.geom_dataid[m.geom(w).id]] <= 24
    _, ref, ref_data = _load_named(task.scene.xml)
    src, body = colliders.wrist_source(ref), ref.body("right_hand").id
    every = np.concatenate(colliders.wrist_coacd(ref, ref_data, src, body, 0.3, 8, 24))
    mesh = colliders.mesh_vertices(ref, ref_data, src, body)
    hull = ConvexHull(mesh)  # inside: A·x + b <= 0 for every facet
    # CoACD approximates: its pieces stick out of the mesh by 1.4 mm at most here
    assert (every @ hull.equations[:, :3].T + hull.equations[:, 3]).max() < 2e-3
    np.testing.assert_allclose(every.min(0), mesh.min(0), atol=2e-3)
    np.testing.assert_allclose(every.max(0), mesh.max(0), atol=2e-3)


def test_button_press_registers_the_faithful_wrist_and_offers_the_box():
    """button_press's registered wrist: coacd pieces, uncapped, the front piece paired with
    the box's 4 slabs, the flange and the cap, the other with the cap alone (the census's
    partners; never the rod); `wrist="box"` builds the box wrist with its measured cap."""
    import mujoco

    task = tasks.make("button_press")
    m = task.mj_model
    assert task.max_contacts is None and str(task.wrist).startswith("coacd")
    pairs = {(m.geom(a).name, m.geom(b).name) for a, b in zip(m.pair_geom1, m.pair_geom2)}
    boxes = lambda body: {m.geom(g).name for g in range(m.ngeom) if m.geom_bodyid[g]
                          == m.body(body).id and m.geom_type[g] == mujoco.mjtGeom.mjGEOM_BOX}
    slabs = boxes("buttonbox")  # its planes are fixtures
    rod_flange_cap = {m.geom(g).name for g in range(m.ngeom)
                      if m.geom_bodyid[g] == m.body("button").id}
    cap = {b for a, b in pairs if a == "box_face"}
    flange = boxes("button") - cap
    partners = lambda piece: {b for a, b in pairs if a == piece} | {a for a, b in pairs
                                                                   if b == piece}
    assert len(slabs) == 4 and len(cap) == len(flange) == 1 and len(rod_flange_cap) == 3
    assert partners("wrist_0") == slabs | flange | cap and partners("wrist_1") == cap
    box = make_task("button_press", wrist="box")
    assert (box.wrist, box.max_contacts) == ("box", 18)
    names = {box.mj_model.geom(g).name for g in range(box.mj_model.ngeom)}
    assert "wrist" in names and "wrist_0" not in names


def test_drawer_stops_where_metaworld_stops():
    """Closed loop, the port's scene stepped by C MuJoCo (no MJX compile; the MJX port runs
    the same model, see the slow test): over the first 150 steps (reach, hook, pull to the
    stop) the drawer goes no further than metaworld's to within 1 cm and the hand trails the
    mocap within 30% of metaworld's (before the weights were copied: -0.262 vs -0.203 m,
    hand-mocap x0.40)."""
    mw = run_metaworld("drawer_open", episodes=2, seed=0, steps=150)
    port = run_port_c(make_task("drawer_open"), "drawer_open", episodes=2, seed=0, steps=150)
    assert port["joint_min"] >= mw["joint_min"] - 0.01, (port, mw)
    assert 0.7 <= port["hand_mocap_mean"] / mw["hand_mocap_mean"] <= 1.3, (port, mw)


# tasks that miss a target today, with the measured miss (each task's docstring says why);
# strict: a fix that meets every target turns the xfail into a failure to be removed here
MISSES = {
    "door_unlock": "the lever flips over its upper stop in some episodes (metaworld: 12 of 100)",
}


@pytest.mark.slow
@pytest.mark.parametrize("name", [
    pytest.param(n, marks=pytest.mark.xfail(reason=MISSES[n], strict=True)) if n in MISSES
    else n for n in ports()])
def test_closed_loop_targets(name):
    """The closed-loop targets (`closed_loop.targets`) per task, 20 episodes a side, 500
    steps."""
    mw = run_metaworld(name, episodes=20, seed=0)
    port = run_port(tasks.make(name), name, episodes=20, seed=0)
    res = targets(port, mw)
    assert res["all_met"], (res, port, mw)


def test_each_reset_keeps_its_own_placement():
    """`info_from_metaworld` copies the placement: it once returned a view of metaworld's
    model, so every recorded episode of a replay got the last reset's placement."""
    from tasks.metaworld.reference import policy_env

    task, env = tasks.make("door_unlock"), policy_env("door_unlock", 0)
    placements = []
    for _ in range(2):
        env.reset()
        placements.append(task.info_from_metaworld(env)["placement"])
    assert not np.array_equal(*placements)


def test_the_wrist_decomposition_is_kept_and_reused(tmp_path, monkeypatch):
    """CoACD (about 10 s) runs once per mesh, settings and version: the next build reads the
    kept pieces, equal to a fresh decomposition's."""
    from tasks.metaworld import colliders
    from tasks.metaworld.scene import _load_named

    monkeypatch.setenv("HPRIOR_COACD_CACHE", str(tmp_path))
    _, ref, ref_data = _load_named(make_task("button_press").scene.xml)
    src, body = colliders.wrist_source(ref), ref.body("right_hand").id
    fresh = colliders.wrist_coacd(ref, ref_data, src, body, 0.3, 8, 24)
    assert len(list(tmp_path.glob("*.npz"))) == 1
    import coacd

    calls, run = [], coacd.run_coacd
    monkeypatch.setattr(coacd, "run_coacd", lambda *a, **k: calls.append(1) or run(*a, **k))
    kept = colliders.wrist_coacd(ref, ref_data, src, body, 0.3, 8, 24)
    assert calls == [] and len(kept) == len(fresh)
    for a, b in zip(kept, fresh):
        np.testing.assert_array_equal(a, b)
    # other settings are another decomposition
    colliders.wrist_coacd(ref, ref_data, src, body, 0.3, 8, 16)
    assert len(calls) == 1
