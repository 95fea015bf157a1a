"""Shared pieces of the MetaWorld v3 ports: the simplified Sawyer scene, mocap actions, the
39-D observation, and the reset/step skeleton. Checked against metaworld 3.0.0.

Scene (built at run time from the installed metaworld XML with `mujoco.MjSpec`):
  * metaworld's 7-DOF arm is kept (`arm=True`, the default since 2026-12-02): its joints
    with damping, armature and limits, its link inertias and metaworld's mocap weld exactly
    as metaworld compiles them (joint-less bodies that nothing reads are fused into their
    parents, world-fixed ones deleted); only its geoms go. From metaworld's state, driven
    by metaworld's recorded mocap path and gripper control (C MuJoCo), this scene follows
    metaworld's hand to within 1e-7 m until the first contact; with metaworld's wrist mesh,
    4 of 6 door_unlock episodes stay identical to the end. With the arm, sweep_into,
    window_open, door_open and drawer_open meet issue 18's closed-loop targets (table in
    benchmarks/README.md). Cost under MJX, batch 64, this 2-core CPU, same run against the
    free hand: 0.73-0.89x its env steps/s (drawer 727 vs 813, button 385 vs 460, door_open
    613 vs 837, window 513 vs 701, door_unlock 609 vs 797, sweep 126 vs 171) and 47-66 s
    to compile the step instead of 32-44 s. (That the arm "did not compile in 8 minutes"
    at batch 64 was XLA constant-folding the reset's kinematics of the constant settled arm
    state; `reset` now makes that state depend on the key.)
  * `arm=False` (`hand="free"` in a run config) is the first ports' scene: the arm, pedestal
    and head are deleted, the `hand` subtree re-rooted on a free joint under metaworld's
    mocap weld (solref 0.02 1, anchor 0, identity relpose, torquescale 5), with mass 1 kg /
    inertia 2e-3 and gravity compensation on the whole gripper, so at rest it sits on the
    mocap target (metaworld's hand rests within 5 mm of it, held up by the arm).
  * Every kept body and joint keeps metaworld's compiled *inverse weights*
    (`body_invweight0`, `dof_invweight0`; `_copy_invweights`). MuJoCo and MJX scale each soft
    constraint's force by these compile-time numbers, so they decide how hard the mocap weld
    pulls the hand and how hard the gripper presses: the free hand's own weight (0.97 against
    metaworld's 6.1) made the weld 6x stiffer, and the hand overpowered the drawer's and
    the door's soft stops (drawer -0.262 vs metaworld's -0.203, door -2.16 vs -1.82 rad).
    Without the arm the wrist collider hangs on a massless child body named `right_hand`,
    rigid on the hand, so its contacts keep the weight of the arm link that carries the
    wrist in metaworld (0.67). With these weights the free hand meets the targets on
    drawer_open, door_open and window_open; what they do not give back is the arm's
    inertia and joint damping (sweep_into: metaworld's arm-held hand overshoots the puck in
    65% of its scripted episodes, the free hand never does).
  * Visual-only geoms (contype = conaffinity = 0, all meshes), meshes, textures and materials
    are deleted (with the arm, so are collision geoms that no pair below uses); every body
    keeps its compiled mass and inertia (set explicitly), so the dynamics of what remains are
    unchanged.
  * Every geom's contype/conaffinity is zeroed and each task lists explicit contact pairs:
    the 4 gripper geoms (claws, pads) x the object parts they touch, the *wrist* x the parts
    it touches (metaworld's scripted solutions push the button and the window handle with
    the wrist, i.e. the collision mesh of `right_hand`, the gripper base, and the lock lever
    too: door_unlock measured it and left it out),
    and object x fixture stops (button cap x box face, window pane x frame, door x safe
    wall), chosen from a contact census of metaworld's own scripted episodes. Pair
    parameters are computed from the two geoms as MuJoCo mixes them for dynamic contacts.
    MJX tests every candidate pair every step; this is the main speed lever.
  * The wrist mesh (6693 vertices, a convex hull of 883) becomes a box: its vertices'
    bounding box in the hand's axes (`wrist="box"`, the default; `wrist=k` gives a convex
    mesh on k of its hull vertices, which door_unlock uses). The shape matters where the
    wrist does the work: button_press (C MuJoCo, with the arm, 20 episodes; the wrist paired
    with the 4 slabs around the button's hole): return x0.99 of metaworld's with metaworld's
    own mesh, x1.17 with a 96-point hull, x1.20 with 32 points, x1.23 with the box; but
    under MJX the full mesh runs at 14 env steps/s at batch 64 (SAT over its hull), against
    385 with the box. MJX has no cylinder-box collision: paired cylinders that meet a box
    become capsules (long ones) or boxes (short, wide ones).
  * metaworld places the task object at reset by editing `model.body_pos` of one body
    (drawer, door, box, window). We do the same per environment: the placement lives in
    `info["placement"]` and `model_for(info)` swaps it into `body_pos` inside the jitted
    step, so a vmapped batch holds different placements. (A mocap body would be cheaper
    but MJX's kinematics does not carry a mocap body's pose to its child bodies.)

Closed-loop dynamics parity (metaworld's scripted policy on both sides; mean return, success
at the last step, object-joint excursion, hand-mocap distance):
`python -m benchmarks.metaworld_dynamics` -> benchmarks/results/metaworld_dynamics.csv.
"""
from __future__ import annotations

import dataclasses
import os
import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from tasks.base import Task, TaskState
from tasks.physics import (MAX_CONTACTS_NUMERIC, contacts_at_cap, mjx, put_model,
                            step as physics_step)

FRAME_SKIP = 5
EPISODE_LENGTH = 500  # SawyerXYZEnv.max_path_length
ACTION_SCALE = 1.0 / 100
HAND_QUAT = np.array([1.0, 0.0, 1.0, 0.0]) / np.sqrt(2.0)  # metaworld sets mocap_quat (1,0,1,0)
# metaworld's weld row (see SawyerMocapBase.reset_mocap_welds)
WELD_ROW = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, 5.0])
HAND_SPACE_LOW = np.array([-0.525, 0.348, -0.0525])
HAND_SPACE_HIGH = np.array([0.525, 1.025, 0.7])
GRIPPER_GEOMS = ("rightclaw_it", "leftclaw_it", "rightpad_geom", "leftpad_geom")
HAND_MASS, HAND_INERTIA = 1.0, 2e-3
RESET_HAND_STEPS = 50  # SawyerXYZEnv._reset_hand
# qpos / dof entries per joint, by mjtJoint (free, ball, slide, hinge)
QPOS_SIZE = {0: 7, 1: 4, 2: 1, 3: 1}
DOF_SIZE = {0: 6, 1: 3, 2: 1, 3: 1}


def metaworld_xml_path(name: str) -> str:
    """Path of a scene XML inside the installed metaworld package (never copied here)."""
    try:
        import metaworld
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise ImportError("metaworld is needed to build MetaWorld tasks: pip install -e .") from e
    return os.path.join(os.path.dirname(metaworld.__file__), "assets", "sawyer_xyz", name)


def load_full_model(xml: str) -> mujoco.MjModel:
    """metaworld's unchanged scene with metaworld's weld parameters (used for constants
    that metaworld reads off the full arm model, and by the kinematics speed guard)."""
    model = mujoco.MjModel.from_xml_path(metaworld_xml_path(xml))
    for i in range(model.neq):
        if model.eq_type[i] == mujoco.mjtEq.mjEQ_WELD:
            model.eq_data[i, : WELD_ROW.size] = WELD_ROW
    return model


# --------------------------------------------------------------------------------------
# scene building


def _mix_pair_params(model: mujoco.MjModel, g1: int, g2: int) -> dict:
    """Contact parameters MuJoCo would use for a dynamic contact between g1 and g2
    (mj_contactParam: max condim/friction/margin/gap, solmix-weighted solref/solimp)."""
    s1, s2 = model.geom_solmix[g1], model.geom_solmix[g2]
    mix = 0.5 if (s1 + s2) < mujoco.mjMINVAL else s1 / (s1 + s2)
    fr = np.maximum(model.geom_friction[g1], model.geom_friction[g2])
    solref1, solref2 = model.geom_solref[g1], model.geom_solref[g2]
    if solref1[0] > 0 and solref2[0] > 0:
        solref = mix * solref1 + (1 - mix) * solref2
    else:  # direct (negative) solref: MuJoCo takes the elementwise min
        solref = np.minimum(solref1, solref2)
    return dict(
        condim=int(max(model.geom_condim[g1], model.geom_condim[g2])),
        friction=[fr[0], fr[0], fr[1], fr[2], fr[2]],
        solref=list(solref),
        solimp=list(mix * model.geom_solimp[g1] + (1 - mix) * model.geom_solimp[g2]),
        margin=float(max(model.geom_margin[g1], model.geom_margin[g2])),
        gap=float(max(model.geom_gap[g1], model.geom_gap[g2])),
    )


@dataclasses.dataclass(frozen=True)
class SceneSpec:
    xml: str  # file under metaworld/assets/sawyer_xyz
    hand_init_pos: tuple  # metaworld's init_config["hand_init_pos"]
    # object geoms the gripper may touch: (body name, geom index within the body or None = all
    # collision geoms of that body); each gets a pair with each of the 4 gripper geoms
    object_geoms: tuple = ()
    # extra explicit pairs between object geoms (e.g. puck <-> table); each side is a geom
    # name or (body name, index among that body's collision geoms) for unnamed geoms
    extra_pairs: tuple = ()
    placed_body: str | None = None  # body metaworld moves at reset via model.body_pos
    # visual (mesh) geoms an observation reads, e.g. the door "handle": they are deleted but
    # their compiled pose relative to their body is returned so the pose can be recomputed
    virtual_geoms: tuple = ()
    # object geoms (same form as object_geoms) paired with the wrist: metaworld's collision
    # mesh of `right_hand` (the gripper base), replaced by its bounding box named "wrist"
    wrist_geoms: tuple = ()
    # primitive geoms added to the scene for pairs (e.g. a plane for a box face that only one
    # part can reach): (name, body, mjtGeom type name, size, pos, quat, params_like) with
    # params_like a geom name or (body, index) whose contact parameters the new geom takes
    fixtures: tuple = ()


def _mesh_vertices(model: mujoco.MjModel, data: mujoco.MjData, g: int, body: int) -> np.ndarray:
    """Mesh geom g's vertices in `body`'s frame (at the pose in `data`)."""
    mid = model.geom_dataid[g]
    verts = model.mesh_vert[model.mesh_vertadr[mid]:model.mesh_vertadr[mid] + model.mesh_vertnum[mid]]
    world = data.geom_xpos[g] + verts @ data.geom_xmat[g].reshape(3, 3).T
    return (world - data.xpos[body]) @ data.xmat[body].reshape(3, 3)


def _wrist_box(model: mujoco.MjModel, data: mujoco.MjData, g: int, body: int) -> tuple:
    """Box around mesh geom g's vertices with the axes of the `hand` frame (the gripper's own
    axes: fingers along y, approach along x), as (half sizes, pos, quat) in `body`'s frame."""
    hand = model.body("hand").id
    rot_h = data.xmat[hand].reshape(3, 3)
    local = _mesh_vertices(model, data, g, hand)  # vertices in hand axes
    lo, hi = local.min(0), local.max(0)
    centre = data.xpos[hand] + rot_h @ ((lo + hi) / 2)
    rot_b = data.xmat[body].reshape(3, 3)
    pos = rot_b.T @ (centre - data.xpos[body])
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, (rot_b.T @ rot_h).ravel())
    return (hi - lo) / 2, pos, quat


def _wrist_hull_points(model, data, g, body, k):
    """k vertices of mesh g's convex hull (farthest-point sampled), in `body`'s frame."""
    from scipy.spatial import ConvexHull
    local = _mesh_vertices(model, data, g, body)
    hull = local[ConvexHull(local).vertices]
    centre = hull.mean(0)
    chosen = [int(np.argmax(np.linalg.norm(hull - centre, axis=1)))]
    dist = np.linalg.norm(hull - hull[chosen[0]], axis=1)
    while len(chosen) < k:
        i = int(np.argmax(dist))
        chosen.append(i)
        dist = np.minimum(dist, np.linalg.norm(hull - hull[i], axis=1))
    return hull[chosen]


def exact_shapes_for_c(wrist: str | int, keep_cylinders: bool) -> bool:
    """Whether a scene keeps metaworld's shapes that only C MuJoCo collides (the wrist mesh,
    paired cylinders against boxes)."""
    return wrist == "mesh" or keep_cylinders


def build_scene(scene: SceneSpec, arm: bool = True, wrist: str | int = "box",
                metaworld_invweights: bool = True, keep_cylinders: bool = False,
                max_contacts: int | None = None) -> tuple[mujoco.MjModel, dict]:
    """The simplified MuJoCo model of a metaworld scene (see module docstring).

    arm=True: metaworld's arm kept with its joints, inertias and damping (only its geoms go);
    arm=False: the hand on a free joint (arm deleted), the scene of the first ports.
    wrist: the wrist collider that replaces metaworld's gripper-base mesh: "box" (its
    bounding box in the hand's axes), an int k (a convex mesh on k of its hull vertices), or
    "mesh" (the original 6693-vertex mesh, and paired cylinders stay cylinders: metaworld's
    exact shapes for C MuJoCo diagnostics only; MJX has no cylinder-box collision and the
    mesh is far too big for it).
    metaworld_invweights: give every kept body and joint metaworld's compiled inverse weights
    (see `_copy_invweights`); False keeps the simplified scene's own (the first ports).
    keep_cylinders: paired cylinders stay cylinders with any wrist (C MuJoCo diagnostics
    only, as with the mesh).
    max_contacts: MJX's contact cap (`tasks.physics.with_max_contacts`), per condim group."""
    exact_shapes = exact_shapes_for_c(wrist, keep_cylinders)
    path = metaworld_xml_path(scene.xml)
    spec = mujoco.MjSpec.from_file(path)
    # name every geom so pairs can refer to it
    for i, g in enumerate(spec.geoms):
        if not g.name:
            g.name = f"_geom{i}"
    full = spec.compile()  # compiled reference: masses, inertias, contact parameters
    full_data = mujoco.MjData(full)
    mujoco.mj_kinematics(full, full_data)
    # freeze compiled inertials so deleting visual geoms leaves masses as metaworld has them
    for b in spec.bodies:
        bid = mujoco.mj_name2id(full, mujoco.mjtObj.mjOBJ_BODY, b.name) if b.name else -1
        if bid <= 0:  # world, or an unnamed wrapper body (inertial set below by name only)
            continue
        b.explicitinertial = True
        b.mass = full.body_mass[bid]
        b.ipos = full.body_ipos[bid]
        b.iquat = full.body_iquat[bid]
        b.inertia = full.body_inertia[bid]

    def collision_geoms(body_name):
        bid = full.body(body_name).id
        return [g for g in range(full.ngeom) if full.geom_bodyid[g] == bid
                and (full.geom_contype[g] or full.geom_conaffinity[g])]

    def resolve(ref):  # geom name, or (body, index among its collision geoms)
        return ref if isinstance(ref, str) else full.geom(collision_geoms(ref[0])[ref[1]]).name

    def expand(entries):
        out = []
        for body_name, index in entries:
            gids = collision_geoms(body_name)
            if index is not None:
                gids = [gids[i] for i in index]
            out += [full.geom(g).name for g in gids]
        return out

    # where each pair geom takes its contact parameters from (a geom of the full model)
    wrist_src = next(g for g in range(full.ngeom) if full.geom_bodyid[g] == full.body(
        "right_hand").id and full.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH
        and full.geom_contype[g])
    param_src = {"wrist": wrist_src}
    for name, _, _, _, _, _, like in scene.fixtures:
        param_src[name] = full.geom(resolve(like)).id

    pair_names = []
    for og in expand(scene.object_geoms):
        for hg in GRIPPER_GEOMS:
            pair_names.append((hg, og))
    for og in expand(scene.wrist_geoms):
        pair_names.append(("wrist", og))
    for pair in scene.extra_pairs:
        pair_names.append(tuple(resolve(n) for n in pair))

    # the wrist collider: metaworld's gripper-base mesh -> its bounding box, on the arm's
    # `right_hand` (without the arm: a rigid, massless child of the re-rooted hand that takes
    # its name, so the wrist's contacts keep metaworld's inverse weight, see _copy_invweights)
    wrist_size, wrist_pos, wrist_quat = _wrist_box(full, full_data, wrist_src,
                                                   full.body("right_hand").id)

    if not arm:
        if wrist == "mesh":
            raise ValueError('wrist="mesh" needs the arm (the mesh hangs on right_hand)')
        # re-root the hand: copy its subtree from a second spec onto a world frame, delete arm
        donor = mujoco.MjSpec.from_file(path)
        for coll in (donor.meshes, donor.textures, donor.materials):  # else names clash
            for item in list(coll):
                donor.delete(item)
        for g in donor.geoms:
            g.material = ""
        spec.delete(spec.body("base"))
        frame = spec.worldbody.add_frame(pos=list(scene.hand_init_pos), quat=list(HAND_QUAT))
        hand = frame.attach_body(donor.body("hand"), "", "")  # (MuJoCo warns: empty prefix)
        hand.add_freejoint(name="hand_free")
        hand.explicitinertial = True
        hand.mass = HAND_MASS
        hand.inertia = [HAND_INERTIA] * 3
        hand.ipos = [0, 0, 0]
        for b in [hand] + _descendants(hand):
            b.gravcomp = 1.0  # the arm holds the gripper up in metaworld
        if any("wrist" in pair for pair in pair_names):
            hid, rid = full.body("hand").id, full.body("right_hand").id
            rot_h = full_data.xmat[hid].reshape(3, 3)
            pos = rot_h.T @ (full_data.xpos[rid] - full_data.xpos[hid])
            quat = np.zeros(4)
            mujoco.mju_mat2Quat(quat, (rot_h.T @ full_data.xmat[rid].reshape(3, 3)).ravel())
            hand.add_body(name="right_hand", pos=list(pos), quat=list(quat),
                          explicitinertial=True, mass=0.0, inertia=[0, 0, 0])
    else:
        for name in _ARM_WORLD_FIXED:
            spec.delete(spec.body(name))
        _fuse_into_parents(spec, full, full_data, _ARM_LEAVES)
    for cam in list(spec.cameras):
        spec.delete(cam)

    virtual = {n: (full.body(int(full.geom(n).bodyid[0])).name, full.geom(n).pos.copy(),
                   full.geom(n).quat.copy()) for n in scene.virtual_geoms}
    used = {n for p in pair_names for n in p}
    for g in list(spec.geoms):
        visual = g.type == mujoco.mjtGeom.mjGEOM_MESH or (g.contype == 0 and g.conaffinity == 0)
        if g.name == "wrist" or (wrist == "mesh" and g.name == full.geom(wrist_src).name):
            continue
        if g.name in used:
            if g.type == mujoco.mjtGeom.mjGEOM_MESH:
                raise ValueError(f"geom {g.name} is a mesh; pick a primitive collision geom")
            continue
        if visual or g.name == "floor" or arm:  # with the arm: only paired geoms stay
            spec.delete(g)
    if "wrist" in used and wrist == "mesh":
        spec.geom(full.geom(wrist_src).name).name = "wrist"
    elif "wrist" in used and not isinstance(wrist, str):
        pts = _wrist_hull_points(full, full_data, wrist_src, full.body("right_hand").id, wrist)
        spec.add_mesh(name="wrist_hull", uservert=pts.ravel().tolist())
        spec.body("right_hand").add_geom(name="wrist", type=mujoco.mjtGeom.mjGEOM_MESH,
                                         meshname="wrist_hull")
    elif "wrist" in used:
        spec.body("right_hand").add_geom(name="wrist", type=mujoco.mjtGeom.mjGEOM_BOX,
                                         size=list(wrist_size), pos=list(wrist_pos),
                                         quat=list(wrist_quat))
    for name, body, gtype, size, pos, quat, _ in scene.fixtures:
        spec.body(body).add_geom(name=name, type=getattr(mujoco.mjtGeom, f"mjGEOM_{gtype}"),
                                 size=list(size), pos=list(pos), quat=list(quat))
    for g in spec.geoms:
        g.contype, g.conaffinity = 0, 0  # only the explicit pairs below collide
    for coll in (spec.meshes, spec.textures, spec.materials):
        for item in list(coll):
            if item.name in {"mesh": ("eGripperBase",), "box": ()}.get(wrist, ("wrist_hull",)):
                continue  # the mesh the wrist geom uses
            spec.delete(item)
    for g in spec.geoms:
        g.material = ""

    # MJX has no cylinder-box collision: a paired object cylinder becomes a capsule of the
    # same radius and end-to-end length (long cylinders: handle rods), or a box with the
    # cylinder's bounding extents (short, wide ones: the button cap, which a capsule would
    # lengthen by its radius towards the gripper) -- unless every partner is a plane,
    # a sphere, a capsule or a cylinder, which MJX collides with cylinders exactly
    kinds = {g.name: g.type for g in spec.geoms}
    exact = {mujoco.mjtGeom.mjGEOM_PLANE, mujoco.mjtGeom.mjGEOM_SPHERE,
             mujoco.mjtGeom.mjGEOM_CAPSULE, mujoco.mjtGeom.mjGEOM_CYLINDER}
    for g in spec.geoms:
        if g.type != mujoco.mjtGeom.mjGEOM_CYLINDER or g.name not in used or exact_shapes:
            continue
        partners = [b if a == g.name else a for a, b in pair_names if g.name in (a, b)]
        if all(kinds[p] in exact for p in partners):
            continue
        r, hl = g.size[0], g.size[1]
        if hl > r:
            g.type, g.size = mujoco.mjtGeom.mjGEOM_CAPSULE, [r, hl - r, 0]
        else:
            g.type, g.size = mujoco.mjtGeom.mjGEOM_BOX, [r, r, hl]

    for n1, n2 in pair_names:
        i1 = param_src.get(n1, None)
        i2 = param_src.get(n2, None)
        i1 = full.geom(n1).id if i1 is None else i1
        i2 = full.geom(n2).id if i2 is None else i2
        spec.add_pair(geomname1=n1, geomname2=n2, **_mix_pair_params(full, i1, i2))

    if max_contacts is not None:
        spec.add_numeric(name=MAX_CONTACTS_NUMERIC, data=[max_contacts])
    model = spec.compile()
    for i in range(model.neq):
        if model.eq_type[i] == mujoco.mjtEq.mjEQ_WELD:
            model.eq_data[i, : WELD_ROW.size] = WELD_ROW
    if metaworld_invweights:
        _copy_invweights(model, full)
    return model, {"npairs": len(pair_names), "virtual_geoms": virtual}


def _copy_invweights(model: mujoco.MjModel, full: mujoco.MjModel) -> None:
    """Sets the compile-time inverse weights (body_invweight0, dof_invweight0) of every body
    and joint of `model` that `full` has by name to `full`'s values.

    Why: MuJoCo (and MJX) scale a soft constraint's regulariser by these compile-time
    weights, not by the current mass matrix, so a weld or contact pulls with a force of about
    d/(1-d) k r / invweight0 at violation r. Deleting the arm drops the hand's translational
    invweight from metaworld's 6.1 to 0.97 (drawer scene): the mocap weld then pulls 6x
    harder per metre and the free hand drags the drawer to -0.262 where metaworld's stops at
    -0.203 (its joint limit is soft too). With metaworld's weights the port's drawer, replaying
    metaworld's mocap path in C MuJoCo, stops at -0.2026 like metaworld's
    (benchmarks/metaworld_mocap_replay.py). The dynamics of free motion (masses, gravity
    compensation) are unchanged."""
    for b in range(model.nbody):
        name = model.body(b).name
        fid = mujoco.mj_name2id(full, mujoco.mjtObj.mjOBJ_BODY, name) if name else -1
        if fid > 0:
            model.body_invweight0[b] = full.body_invweight0[fid]
    for j in range(model.njnt):
        name = model.joint(j).name
        fid = mujoco.mj_name2id(full, mujoco.mjtObj.mjOBJ_JOINT, name) if name else -1
        if fid < 0 or full.jnt_type[fid] != model.jnt_type[j]:
            continue
        n = DOF_SIZE[int(model.jnt_type[j])]
        a, fa = model.jnt_dofadr[j], full.jnt_dofadr[fid]
        model.dof_invweight0[a:a + n] = full.dof_invweight0[fa:fa + n]


# bodies of metaworld's Sawyer base that carry no joint and that nothing here reads: fused
# into their parent (mass and inertia combined exactly) or, when fixed to the world, deleted.
# Fewer bodies per tree level means fewer groups in MJX's per-level tree scans.
_ARM_WORLD_FIXED = ("controller_box", "pedestal_feet", "torso", "pedestal")
_ARM_LEAVES = ("head", "right_torso_itb", "right_arm_itb", "right_hand_camera", "right_wrist",
               "right_l4_2", "right_l2_2", "right_l1_2")


def _fuse_into_parents(spec, full: mujoco.MjModel, full_data: mujoco.MjData, names) -> None:
    """Deletes the bodies `names` (and their subtrees) after adding their masses and inertias
    to their parents; the subtrees must have no joints (they move rigidly with the parent)."""
    by_parent = {}
    for name in names:
        by_parent.setdefault(int(full.body_parentid[full.body(name).id]), []).append(name)
    for pid, group in by_parent.items():
        _fuse(spec, full, full_data, pid, [full.body(n).id for n in group])
        for name in group:
            spec.delete(spec.body(name))


def _fuse(spec, full, full_data, pid: int, leaves: list) -> None:
    for leaf in leaves:
        assert not any(full.body_jntnum[b] for b in range(full.nbody)
                       if _is_in_subtree(full, b, leaf)), full.body(leaf).name
    members = [pid] + [b for b in range(full.nbody)
                       if any(_is_in_subtree(full, b, leaf) for leaf in leaves)]
    mass = sum(full.body_mass[b] for b in members)
    com = sum(full.body_mass[b] * full_data.xipos[b] for b in members) / max(mass, 1e-12)
    tensor = np.zeros((3, 3))
    for b in members:
        rot = full_data.ximat[b].reshape(3, 3)
        d = full_data.xipos[b] - com
        tensor += rot @ np.diag(full.body_inertia[b]) @ rot.T
        tensor += full.body_mass[b] * (d @ d * np.eye(3) - np.outer(d, d))
    rot_p = full_data.xmat[pid].reshape(3, 3)
    local = rot_p.T @ tensor @ rot_p
    vals, vecs = np.linalg.eigh(local)
    if np.linalg.det(vecs) < 0:
        vecs[:, 0] = -vecs[:, 0]
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, vecs.ravel())
    parent = spec.body(full.body(pid).name)
    parent.explicitinertial = True
    parent.mass = mass
    parent.ipos = rot_p.T @ (com - full_data.xpos[pid])
    parent.iquat = quat
    parent.inertia = np.maximum(vals, 1e-12)


def _is_in_subtree(model: mujoco.MjModel, body: int, root: int) -> bool:
    while body > 0:
        if body == root:
            return True
        body = int(model.body_parentid[body])
    return False


def _descendants(body) -> list:
    out = []
    for c in body.bodies:
        out.append(c)
        out.extend(_descendants(c))
    return out


# --------------------------------------------------------------------------------------
# the task skeleton


class SawyerTask(Task):
    """Reset/step/observation shared by the MetaWorld ports.

    Subclasses set `scene`, the bounds, and implement `_place` (reset randomisation),
    `_objects` (object pos/quat for the observation) and `_reward`."""

    domain = "metaworld"
    has_success = True
    action_size = 4
    obs_size = 39
    episode_length = EPISODE_LENGTH

    scene: SceneSpec
    hand_low: tuple = (-0.5, 0.40, 0.05)  # the hand_low/hand_high of every task here
    hand_high: tuple = (0.5, 1.0, 0.5)
    obj_low: tuple = ()
    obj_high: tuple = ()
    goal_low: tuple | None = None  # goal_space; None -> hand bounds (metaworld default)
    goal_high: tuple | None = None
    wrist: str | int = "box"  # the task's wrist collider (build_scene); a task may pick a hull
    max_contacts: int | None = None  # MJX's contact cap (build_scene); None: every slot

    def __init__(self, partially_observable: bool = True, solver_iterations: int = 5,
                 ls_iterations: int = 10, arm: bool = True, wrist: str | int | None = None,
                 metaworld_invweights: bool = True, keep_cylinders: bool = False,
                 max_contacts: int | None | str = "task"):
        """partially_observable=True (default) zeroes the 3 goal slots of the observation.

        That is metaworld v3's own default (`_partially_observable = True`) and what BPref
        and every PbRL baseline the paper compares with used (spec §7.2, BPref issue #8);
        pass False for metaworld's "goal observable" variant.

        solver_iterations / ls_iterations: metaworld's scene asks for 50 Newton iterations at
        tolerance 1e-10; MJX runs its solver loop until the tolerance is met, i.e. nearly all
        50 every substep. Newton converges in a few iterations on these small contact sets;
        5 / 10 roughly doubled batch-64 throughput on drawer_open and kept its scripted-policy
        success and drift (benchmarks/metaworld_parity.py). Pass 50, 50 for metaworld's.

        wrist="mesh" or keep_cylinders=True build metaworld's exact shapes for C MuJoCo
        diagnostics (`mj_model`); MJX cannot collide them, so `model` (the MJX step's) is
        then the box-wrist scene's: right for kinematics, not for contacts."""
        self.partially_observable = partially_observable
        self.arm = arm
        self.wrist = self.wrist if wrist is None else wrist
        self.max_contacts = self.max_contacts if max_contacts == "task" else max_contacts
        self.mj_model, self.scene_info = build_scene(
            self.scene, arm=arm, wrist=self.wrist, metaworld_invweights=metaworld_invweights,
            keep_cylinders=keep_cylinders, max_contacts=self.max_contacts)
        self.mj_model.opt.iterations = solver_iterations
        self.mj_model.opt.ls_iterations = ls_iterations
        mjx_scene = self.mj_model
        if exact_shapes_for_c(self.wrist, keep_cylinders):  # MJX cannot collide them: its model
            # (kinematics, reset) is the scene with the box wrist, same bodies, joints, sites
            mjx_scene, _ = build_scene(self.scene, arm=arm, wrist="box",
                                       metaworld_invweights=metaworld_invweights,
                                       max_contacts=self.max_contacts)
            mjx_scene.opt.iterations, mjx_scene.opt.ls_iterations = (solver_iterations,
                                                                     ls_iterations)
        self.model = put_model(mjx_scene)
        self.control_timestep = FRAME_SKIP * float(self.mj_model.opt.timestep)
        m = self.mj_model
        self._mocap_low = jnp.asarray(self.hand_low, jnp.float32)
        self._mocap_high = jnp.asarray(self.hand_high, jnp.float32)
        self._hand_mocap = int(m.body_mocapid[m.body("mocap").id])
        self._placed_body = m.body(self.scene.placed_body).id if self.scene.placed_body else None
        if not arm:
            self._hand_qadr = int(m.jnt_qposadr[m.joint("hand_free").id])
            self._hand_vadr = int(m.jnt_dofadr[m.joint("hand_free").id])
        self._ids = {
            "hand": m.body("hand").id, "rightclaw": m.body("rightclaw").id,
            "leftclaw": m.body("leftclaw").id, "rightpad": m.body("rightpad").id,
            "leftpad": m.body("leftpad").id,
            "rightEE": m.site("rightEndEffector").id, "leftEE": m.site("leftEndEffector").id,
        }
        goal_low = self.goal_low if self.goal_low is not None else self.hand_low
        goal_high = self.goal_high if self.goal_high is not None else self.hand_high
        self._obs_low = np.concatenate([HAND_SPACE_LOW, [-1.0], np.full(14, -np.inf)] * 2
                                       + [np.zeros(3) if partially_observable else goal_low])
        self._obs_high = np.concatenate([HAND_SPACE_HIGH, [1.0], np.full(14, np.inf)] * 2
                                        + [np.zeros(3) if partially_observable else goal_high])
        self._settled = self._settle_hand()
        # metaworld reads init_left/right_pad once at construction, with the *arm* at qpos0
        # (they are views of data.xpos, so inside metaworld they later track the current pads:
        # a reward that reads them must use the current pads, see sweep_into._caging)
        full = load_full_model(self.scene.xml)
        fd = mujoco.MjData(full)
        mujoco.mj_forward(full, fd)
        self.init_left_pad = jnp.asarray(fd.body("leftpad").xpos, jnp.float32)
        self.init_right_pad = jnp.asarray(fd.body("rightpad").xpos, jnp.float32)

    # -- construction-time constants ------------------------------------------------
    def _settle_hand(self) -> dict:
        """metaworld's `_reset_hand`: 50 control steps with the mocap at hand_init_pos and the
        gripper open (ctrl -1, 1). It starts from the same state every reset (mj_resetData),
        so the result is a constant: we compute it once here with C MuJoCo on our scene."""
        m = self.mj_model
        d = mujoco.MjData(m)
        d.mocap_pos[self._hand_mocap] = self.scene.hand_init_pos
        d.mocap_quat[self._hand_mocap] = HAND_QUAT
        d.ctrl[:] = [-1.0, 1.0]
        for _ in range(RESET_HAND_STEPS * FRAME_SKIP):
            mujoco.mj_step(m, d)
        mujoco.mj_forward(m, d)
        tcp = (d.site_xpos[self._ids["rightEE"]] + d.site_xpos[self._ids["leftEE"]]) / 2
        return {"qpos": d.qpos.copy(), "qvel": d.qvel.copy(), "init_tcp": tcp.copy()}

    # -- subclass hooks -----------------------------------------------------------------
    def _place(self, key: jax.Array, data: mjx.Data) -> tuple[mjx.Data, dict]:
        """Randomise the object like metaworld's reset_model; returns data (qpos/mocap
        edited, not yet forwarded) and `info` constants for the episode."""
        raise NotImplementedError

    def _after_forward(self, data: mjx.Data, info: dict) -> dict:
        """Episode constants metaworld reads off the placed scene (after mj_forward)."""
        return info

    def _objects(self, data: mjx.Data) -> tuple[jax.Array, jax.Array]:
        raise NotImplementedError

    def _reward(self, obs, action, data, info) -> tuple[jax.Array, jax.Array]:
        raise NotImplementedError

    # -- helpers --------------------------------------------------------------------------
    def sample_uniform(self, key, low, high):
        low, high = jnp.asarray(low, jnp.float32), jnp.asarray(high, jnp.float32)
        return jax.random.uniform(key, low.shape, minval=low, maxval=high)

    def tcp_center(self, data: mjx.Data) -> jax.Array:
        return (data.site_xpos[self._ids["rightEE"]] + data.site_xpos[self._ids["leftEE"]]) / 2

    def body_pos(self, data: mjx.Data, name: str) -> jax.Array:
        return data.xpos[self.mj_model.body(name).id]

    def site_pos(self, data: mjx.Data, name: str) -> jax.Array:
        return data.site_xpos[self.mj_model.site(name).id]

    def virtual_geom_pose(self, data: mjx.Data, name: str) -> tuple[jax.Array, jax.Array]:
        """World position and rotation matrix of a deleted visual geom (see SceneSpec)."""
        body, pos, quat = self.scene_info["virtual_geoms"][name]
        bid = self.mj_model.body(body).id
        mat = np.zeros(9)
        mujoco.mju_quat2Mat(mat, quat)
        rot = data.xmat[bid]
        return data.xpos[bid] + rot @ jnp.asarray(pos, jnp.float32), rot @ jnp.asarray(
            mat.reshape(3, 3), jnp.float32)

    def current_obs(self, data: mjx.Data) -> jax.Array:
        """metaworld `_get_curr_obs_combined_no_goal` (18 values)."""
        hand = data.xpos[self._ids["hand"]]
        apart = jnp.linalg.norm(data.xpos[self._ids["rightclaw"]] - data.xpos[self._ids["leftclaw"]])
        apart = jnp.clip(apart / 0.1, 0.0, 1.0)
        pos, quat = self._objects(data)
        n_obj = pos.shape[0] // 3
        objs = jnp.concatenate([jnp.concatenate([pos[3 * i:3 * i + 3], quat[4 * i:4 * i + 4]])
                                for i in range(n_obj)])
        objs = jnp.pad(objs, (0, 14 - objs.shape[0]))
        return jnp.concatenate([hand, apart[None], objs]).astype(jnp.float32)

    def observe(self, curr, prev, goal) -> jax.Array:
        """metaworld `_get_obs` followed by the clip to the observation space in `step`."""
        goal = jnp.zeros(3) if self.partially_observable else goal
        obs = jnp.concatenate([curr, prev, goal]).astype(jnp.float32)
        return jnp.clip(obs, self._obs_low, self._obs_high)

    def contacts_at_cap(self, data: mjx.Data) -> jax.Array:
        return contacts_at_cap(self.model, data, self.max_contacts)

    def model_for(self, info: dict) -> mjx.Model:
        """The model with this episode's object placement (metaworld edits model.body_pos)."""
        if self._placed_body is None:
            return self.model
        body_pos = self.model.body_pos.at[self._placed_body].set(info["placement"])
        return self.model.replace(body_pos=body_pos)

    def kinematics(self, data: mjx.Data, info: dict) -> mjx.Data:
        """Positions for observation and reward (metaworld calls mj_forward after stepping;
        only the position stage is read)."""
        return mjx.kinematics(self.model_for(info), data)

    # -- contract ---------------------------------------------------------------------------
    def reset(self, key: jax.Array) -> TaskState:
        data = mjx.make_data(self.model)
        data = data.replace(
            qpos=jnp.asarray(self._settled["qpos"], jnp.float32),
            qvel=jnp.asarray(self._settled["qvel"], jnp.float32),
            mocap_pos=data.mocap_pos.at[self._hand_mocap].set(
                jnp.asarray(self.scene.hand_init_pos, jnp.float32)),
            mocap_quat=data.mocap_quat.at[self._hand_mocap].set(jnp.asarray(HAND_QUAT, jnp.float32)),
            ctrl=jnp.asarray([-1.0, 1.0], jnp.float32),
        )
        info = {"init_tcp": jnp.asarray(self._settled["init_tcp"], jnp.float32)}
        data, placed = self._place(key, data)
        info.update(placed)
        if self.arm:
            # qpos made to depend on the key (+ 0 · u, exact): under vmap it is then batched
            # like the placed model. With the unbatched constant qpos, XLA's constant folding
            # of the arm scene's reset ran over 5 minutes at batch 64 (8 s at batch 8; 10 s
            # this way)
            data = data.replace(qpos=data.qpos + 0.0 * jax.random.uniform(
                jax.random.fold_in(key, 0x71706F73), data.qpos.shape))
        # positions only: obs and episode constants read nothing else, and mjx.step recomputes
        # every derived quantity from qpos/qvel (cheaper to compile and to auto-reset)
        data = mjx.kinematics(self.model_for(info), data)
        info = self._after_forward(data, info)
        curr = self.current_obs(data)
        info["prev_obs"] = curr  # metaworld v3 reset: obs[18:36] = obs[:18]
        obs = self.observe(curr, curr, info["target_pos"])
        zero = jnp.zeros((), jnp.float32)
        return TaskState(data=data, obs=obs, true_reward=zero, success=zero,
                         terminated=jnp.zeros((), bool), info=info)

    def step(self, state: TaskState, action: jax.Array) -> TaskState:
        action = jnp.clip(action, -1.0, 1.0)  # BPref's NormalizedBoxEnv clips to [-1, 1]
        data = state.data
        mocap = jnp.clip(data.mocap_pos[self._hand_mocap] + action[:3] * ACTION_SCALE,
                         self._mocap_low, self._mocap_high)
        data = data.replace(
            mocap_pos=data.mocap_pos.at[self._hand_mocap].set(mocap),
            ctrl=jnp.stack([action[3], -action[3]]),
        )
        model = self.model_for(state.info)
        data = jax.lax.fori_loop(0, FRAME_SKIP, lambda _, d: physics_step(model, d), data)
        data = mjx.kinematics(model, data)
        curr = self.current_obs(data)
        obs = self.observe(curr, state.info["prev_obs"], state.info["target_pos"])
        reward, success = self._reward(obs, action, data, state.info)
        info = dict(state.info, prev_obs=curr)
        return TaskState(data=data, obs=obs, true_reward=reward.astype(jnp.float32),
                         success=success.astype(jnp.float32),
                         terminated=jnp.zeros((), bool), info=info)

    # -- parity support ----------------------------------------------------------------------
    def data_from_metaworld(self, env) -> mjx.Data:
        """MJX data holding a metaworld env's current state: hand pose from metaworld's hand
        body, fingers and object joints from its qpos (the arm joints are dropped)."""
        md, mm = env.data, env.model
        m = self.mj_model
        qpos = np.zeros(m.nq)
        qvel = np.zeros(m.nv)
        # named joints (fingers, arm) by name; the task object's joints (some unnamed) in
        # their model order; without the arm, the hand pose from metaworld's hand body
        named = [m.joint(j).name for j in range(m.njnt)
                 if m.joint(j).name and m.joint(j).name != "hand_free"]
        ours = [m.joint(n).id for n in named] + [
            j for j in range(m.njnt) if not m.joint(j).name]
        theirs = [mm.joint(n).id for n in named] + [
            j for j in range(mm.njnt) if not mm.joint(j).name]
        if not self.arm:
            qpos[self._hand_qadr:self._hand_qadr + 3] = md.body("hand").xpos
            qpos[self._hand_qadr + 3:self._hand_qadr + 7] = md.body("hand").xquat
            qvel[self._hand_vadr:self._hand_vadr + 3] = md.body("hand").cvel[3:]  # approx.
        assert len(ours) == len(theirs), "joint lists of port and metaworld differ"
        for j, jm in zip(ours, theirs):
            mj = mm.joint(jm)
            n = QPOS_SIZE[int(m.jnt_type[j])]
            nvj = DOF_SIZE[int(m.jnt_type[j])]
            qpos[m.jnt_qposadr[j]:m.jnt_qposadr[j] + n] = md.qpos[mj.qposadr[0]:mj.qposadr[0] + n]
            qvel[m.jnt_dofadr[j]:m.jnt_dofadr[j] + nvj] = md.qvel[mj.dofadr[0]:mj.dofadr[0] + nvj]
        data = mjx.make_data(self.model)
        mocap_pos = np.array(data.mocap_pos)
        mocap_quat = np.array(data.mocap_quat)
        mocap_pos[self._hand_mocap] = md.mocap_pos[0]
        mocap_quat[self._hand_mocap] = md.mocap_quat[0] / np.linalg.norm(md.mocap_quat[0])
        return data.replace(qpos=jnp.asarray(qpos, jnp.float32),
                            qvel=jnp.asarray(qvel, jnp.float32),
                            mocap_pos=jnp.asarray(mocap_pos, jnp.float32),
                            mocap_quat=jnp.asarray(mocap_quat, jnp.float32),
                            ctrl=jnp.asarray(md.ctrl, jnp.float32))

    def info_from_metaworld(self, env) -> dict:
        """Episode constants of a metaworld env (after its reset) in this port's `info` form."""
        info = {"init_tcp": np.asarray(env.init_tcp), **self._task_info_from_metaworld(env)}
        if self._placed_body is not None:
            # a copy: `body(...).pos` is a view of the model, which the next reset rewrites
            info["placement"] = np.array(env.model.body(self.scene.placed_body).pos)
        return info

    def _task_info_from_metaworld(self, env) -> dict:
        raise NotImplementedError

