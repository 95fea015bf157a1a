"""Body-tree edits of a metaworld scene: compiled inertials frozen, the arm's joint-less
bodies fused into their parents, the hand re-rooted on a free joint, and metaworld's
compile-time inverse weights copied onto the edited model (see `tasks.metaworld.scene`)."""
from __future__ import annotations

import mujoco
import numpy as np

HAND_QUAT = np.array([1.0, 0.0, 1.0, 0.0]) / np.sqrt(2.0)  # metaworld sets mocap_quat (1,0,1,0)
HAND_MASS, HAND_INERTIA = 1.0, 2e-3
# dof entries per joint, by mjtJoint (free, ball, slide, hinge)
DOF_SIZE = {0: 6, 1: 3, 2: 1, 3: 1}

# bodies of metaworld's Sawyer base that carry no joint and that nothing here reads: fused
# into their parent (mass and inertia combined exactly) or, when fixed to the world, deleted.
# Fewer bodies per tree level means fewer groups in MJX's per-level tree scans.
ARM_WORLD_FIXED = ("controller_box", "pedestal_feet", "torso", "pedestal")
ARM_LEAVES = ("head", "right_torso_itb", "right_arm_itb", "right_hand_camera", "right_wrist",
              "right_l4_2", "right_l2_2", "right_l1_2")


def freeze_inertials(spec: mujoco.MjSpec, full: mujoco.MjModel) -> None:
    """Sets every named body's inertial to its compiled value in `full`, so that deleting
    visual geoms leaves masses as metaworld has them."""
    for b in spec.bodies:
        bid = mujoco.mj_name2id(full, mujoco.mjtObj.mjOBJ_BODY, b.name) if b.name else -1
        if bid <= 0:  # world, or an unnamed wrapper body (inertial set below by name only)
            continue
        b.explicitinertial = True
        b.mass = full.body_mass[bid]
        b.ipos = full.body_ipos[bid]
        b.iquat = full.body_iquat[bid]
        b.inertia = full.body_inertia[bid]


def drop_arm_extras(spec: mujoco.MjSpec, full: mujoco.MjModel, full_data: mujoco.MjData) -> None:
    """Deletes the arm's world-fixed bodies and fuses its joint-less leaves into their
    parents (no joint changes: qpos and qvel keep metaworld's layout)."""
    for name in ARM_WORLD_FIXED:
        spec.delete(spec.body(name))
    fuse_into_parents(spec, full, full_data, ARM_LEAVES)


def reroot_hand(spec: mujoco.MjSpec, path: str, hand_init_pos, full: mujoco.MjModel,
                full_data: mujoco.MjData, wrist_body: bool, keep_materials: bool = False):
    """Deletes the arm (metaworld's `base` subtree) and puts a copy of its `hand` subtree on
    a free joint at `hand_init_pos`, with mass HAND_MASS, inertia HAND_INERTIA and gravity
    compensation on the whole gripper (the arm holds the gripper up in metaworld).

    wrist_body: add a rigid, massless child `right_hand` at the arm's `right_hand` pose, so
    the wrist collider keeps that body's inverse weight (`copy_invweights`).
    keep_materials: the copied geoms keep their material names (the render scene's; the
    physics scene has no materials)."""
    donor = mujoco.MjSpec.from_file(path)
    for coll in (donor.meshes, donor.textures, donor.materials):  # else names clash
        for item in list(coll):
            donor.delete(item)
    if not keep_materials:
        for g in donor.geoms:
            g.material = ""
    spec.delete(spec.body("base"))
    frame = spec.worldbody.add_frame(pos=list(hand_init_pos), quat=list(HAND_QUAT))
    hand = frame.attach_body(donor.body("hand"), "", "")  # (MuJoCo warns: empty prefix)
    hand.add_freejoint(name="hand_free")
    hand.explicitinertial = True
    hand.mass = HAND_MASS
    hand.inertia = [HAND_INERTIA] * 3
    hand.ipos = [0, 0, 0]
    for b in [hand] + _descendants(hand):
        b.gravcomp = 1.0
    if wrist_body:
        hid, rid = full.body("hand").id, full.body("right_hand").id
        rot_h = full_data.xmat[hid].reshape(3, 3)
        pos = rot_h.T @ (full_data.xpos[rid] - full_data.xpos[hid])
        quat = np.zeros(4)
        mujoco.mju_mat2Quat(quat, (rot_h.T @ full_data.xmat[rid].reshape(3, 3)).ravel())
        hand.add_body(name="right_hand", pos=list(pos), quat=list(quat),
                      explicitinertial=True, mass=0.0, inertia=[0, 0, 0])
    return hand


def copy_invweights(model: mujoco.MjModel, full: mujoco.MjModel) -> None:
    """Sets the compile-time inverse weights (body_invweight0, dof_invweight0) of every body
    and joint of `model` that `full` has by name to `full`'s values.

    MuJoCo (and MJX) scale a soft constraint's regulariser by these compile-time weights,
    not by the current mass matrix, so a weld or contact pulls with a force of about
    d/(1-d) k r / invweight0 at violation r: without the arm, the hand's own weights would
    make metaworld's mocap weld several times stiffer (docs/ports/metaworld.md). The
    dynamics of free motion (masses, gravity compensation) are unchanged."""
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


def fuse_into_parents(spec, full: mujoco.MjModel, full_data: mujoco.MjData, names) -> None:
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
