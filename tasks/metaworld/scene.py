"""The simplified Sawyer scene of a MetaWorld port, built at run time from the installed
metaworld XML with `mujoco.MjSpec` (never copied here).

`build_scene` keeps metaworld's bodies, joints, inertias, weld and compile-time inverse
weights (the arm's joint-less bodies fused, or the hand alone on a free joint with
`arm=False`), deletes every visual geom, mesh and material, replaces the gripper-base mesh by
a wrist collider and makes only the task's explicit contact pairs collide; what each choice
measured is in docs/ports/metaworld.md. `tasks.metaworld.render_scene` builds the scene a
person sees, beside this one."""
from __future__ import annotations

import dataclasses
import os

import mujoco
import numpy as np

from tasks.metaworld import colliders, scene_bodies
from tasks.physics import MAX_CONTACTS_NUMERIC

# metaworld's weld row (see SawyerMocapBase.reset_mocap_welds)
WELD_ROW = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, 5.0])
GRIPPER_GEOMS = ("rightclaw_it", "leftclaw_it", "rightpad_geom", "leftpad_geom")


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
    # (fixture name, (body, index or None)): a fixture that stands for those geoms as one solid
    # block against a box or hull wrist; the mesh wrist or its pieces, which reach into their
    # gaps, pair with the geoms themselves instead
    solid_stand_ins: tuple = ()
    # (wrist option, ((piece index, object geoms as in object_geoms), ...)): with that pieces
    # wrist, each listed piece pairs only with those geoms, the ones it touched in a contact
    # census of metaworld's scripted episodes (MJX evaluates every listed pair every step,
    # touching or not); pieces not listed keep every pair
    piece_partners: tuple = ()


def metaworld_xml_path(name: str) -> str:
    """Path of a scene XML inside the installed metaworld package (never copied here)."""
    try:
        import metaworld
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise ImportError("metaworld is needed to build MetaWorld tasks: pip install -e .") from e
    return os.path.join(os.path.dirname(metaworld.__file__), "assets", "sawyer_xyz", name)


def set_weld_rows(model: mujoco.MjModel) -> None:
    """metaworld's weld parameters on every weld of `model` (its reset writes them)."""
    for i in range(model.neq):
        if model.eq_type[i] == mujoco.mjtEq.mjEQ_WELD:
            model.eq_data[i, : WELD_ROW.size] = WELD_ROW


def load_full_model(xml: str) -> mujoco.MjModel:
    """metaworld's unchanged scene with metaworld's weld parameters (used for constants
    that metaworld reads off the full arm model, and by the kinematics speed guard)."""
    model = mujoco.MjModel.from_xml_path(metaworld_xml_path(xml))
    set_weld_rows(model)
    return model


def exact_shapes_for_c(wrist: str | int, keep_cylinders: bool) -> bool:
    """Whether a scene keeps metaworld's shapes that only C MuJoCo collides (the wrist mesh,
    paired cylinders against boxes)."""
    return wrist == "mesh" or keep_cylinders


class _GeomRefs:
    """Names of the compiled full scene's collision geoms, from the forms SceneSpec uses."""

    def __init__(self, full: mujoco.MjModel):
        self.full = full

    def of_body(self, body_name: str) -> list[int]:
        full, bid = self.full, self.full.body(body_name).id
        return [g for g in range(full.ngeom) if full.geom_bodyid[g] == bid
                and (full.geom_contype[g] or full.geom_conaffinity[g])]

    def resolve(self, ref) -> str:  # geom name, or (body, index among its collision geoms)
        return ref if isinstance(ref, str) else self.full.geom(self.of_body(ref[0])[ref[1]]).name

    def expand(self, entries) -> list[str]:
        out = []
        for body_name, index in entries:
            gids = self.of_body(body_name)
            if index is not None:
                gids = [gids[i] for i in index]
            out += [self.full.geom(g).name for g in gids]
        return out


def _pair_names(scene: SceneSpec, refs: _GeomRefs, exact_wrist: bool) -> list[tuple[str, str]]:
    pairs = [(hg, og) for og in refs.expand(scene.object_geoms) for hg in GRIPPER_GEOMS]
    pairs += [("wrist", og) for og in refs.expand(scene.wrist_geoms)]
    pairs += [tuple(refs.resolve(n) for n in pair) for pair in scene.extra_pairs]
    if exact_wrist:
        stand_ins = {name: refs.expand([geoms]) for name, geoms in scene.solid_stand_ins}
        pairs = [(a, g) for a, b in pairs for g in stand_ins.get(b, [b])]
    return pairs


def _wrist_pairs(pairs: list, wrist_geoms: list[str]) -> list[tuple[str, str]]:
    """Each pair with "wrist" as one pair per wrist geom."""
    out = []
    for a, b in pairs:
        if "wrist" not in (a, b):
            out.append((a, b))
        else:
            out += [(w, b) if a == "wrist" else (a, w) for w in wrist_geoms]
    return out


def _partners_only(pairs: list, partners: dict[str, set]) -> list[tuple[str, str]]:
    """`pairs` without those of a piece in `partners` ({piece geom: its partner geoms})
    with a geom that is not its partner."""
    return [(a, b) for a, b in pairs
            if not (a in partners and b not in partners[a] or b in partners and a not in partners[b])]


def _load_named(xml: str) -> tuple[mujoco.MjSpec, mujoco.MjModel, mujoco.MjData]:
    """The scene's spec with every geom named (so pairs can refer to it), and its compiled
    model and kinematics (the reference for masses, inertias, contact parameters)."""
    spec = mujoco.MjSpec.from_file(metaworld_xml_path(xml))
    for i, g in enumerate(spec.geoms):
        if not g.name:
            g.name = f"_geom{i}"
    full = spec.compile()
    full_data = mujoco.MjData(full)
    mujoco.mj_kinematics(full, full_data)
    return spec, full, full_data


def _prune_geoms(spec, used: set, keep: set, arm: bool) -> None:
    """Deletes visual geoms and the floor (with the arm: every geom no pair uses)."""
    for g in list(spec.geoms):
        visual = g.type == mujoco.mjtGeom.mjGEOM_MESH or (g.contype == 0 and g.conaffinity == 0)
        if g.name in keep:
            continue
        if g.name in used:
            if g.type == mujoco.mjtGeom.mjGEOM_MESH:
                raise ValueError(f"geom {g.name} is a mesh; pick a primitive collision geom")
            continue
        if visual or g.name == "floor" or arm:
            spec.delete(g)


def _strip_looks(spec, wrist: str | int) -> None:
    """No geom collides but through the explicit pairs; meshes (but the wrist's),
    textures and materials go."""
    for g in spec.geoms:
        g.contype, g.conaffinity = 0, 0
    keep = {"mesh": ("eGripperBase",), "box": ()}.get(wrist, ("wrist_hull",))
    for coll in (spec.meshes, spec.textures, spec.materials):
        for item in list(coll):
            if item.name not in keep and not item.name.startswith("wrist_hull_"):
                spec.delete(item)
    for g in spec.geoms:
        g.material = ""


def build_scene(scene: SceneSpec, arm: bool = True, wrist: str | int = "box",
                metaworld_invweights: bool = True, keep_cylinders: bool = False,
                max_contacts: int | None = None) -> tuple[mujoco.MjModel, dict]:
    """The simplified MuJoCo model of a metaworld scene (see module docstring).

    arm=True: metaworld's arm kept with its joints, inertias and damping (only its geoms go);
    arm=False: the hand on a free joint (arm deleted), the scene of the first ports.
    wrist: the wrist collider that replaces metaworld's gripper-base mesh: "box" (its
    bounding box in the hand's axes), an int k (a convex mesh on k of its hull vertices),
    "coacd[:...]" (convex pieces of the mesh, `colliders.parse_pieces`; the task's solid
    stand-ins give way to the geoms they stand for), or "mesh" (the original mesh, and paired
    cylinders stay cylinders: C MuJoCo diagnostics only; MJX has no cylinder-box collision
    and the mesh is far too big for it).
    metaworld_invweights: give every kept body and joint metaworld's compiled inverse weights
    (`scene_bodies.copy_invweights`); False keeps the simplified scene's own.
    keep_cylinders: paired cylinders stay cylinders with any wrist (C MuJoCo only).
    max_contacts: MJX's contact cap (`tasks.physics.with_max_contacts`), per condim group."""
    spec, full, full_data = _load_named(scene.xml)
    scene_bodies.freeze_inertials(spec, full)
    refs = _GeomRefs(full)
    pair_names = _pair_names(scene, refs, wrist == "mesh"
                             or colliders.parse_pieces(wrist) is not None)
    used = {n for p in pair_names for n in p}
    wrist_src = colliders.wrist_source(full)
    param_src = {"wrist": wrist_src}  # where a pair geom takes its contact parameters from
    for name, *_, like in scene.fixtures:
        param_src[name] = full.geom(refs.resolve(like)).id

    if not arm:
        if wrist == "mesh":
            raise ValueError('wrist="mesh" needs the arm (the mesh hangs on right_hand)')
        scene_bodies.reroot_hand(spec, metaworld_xml_path(scene.xml), scene.hand_init_pos,
                                 full, full_data, wrist_body="wrist" in used)
    else:
        scene_bodies.drop_arm_extras(spec, full, full_data)
    for cam in list(spec.cameras):
        spec.delete(cam)
    virtual = {n: (full.body(int(full.geom(n).bodyid[0])).name, full.geom(n).pos.copy(),
                   full.geom(n).quat.copy()) for n in scene.virtual_geoms}
    keep = {"wrist"} | ({full.geom(wrist_src).name} if wrist == "mesh" else set())
    _prune_geoms(spec, used, keep, arm)
    if "wrist" in used:
        wrist_geoms = colliders.add_wrist(spec, full, full_data, wrist, wrist_src)
        pair_names = _wrist_pairs(pair_names, wrist_geoms)
        partners = dict(scene.piece_partners).get(wrist, ())
        pair_names = _partners_only(pair_names, {
            wrist_geoms[i]: set(refs.expand(geoms)) for i, geoms in partners})
        param_src.update({w: wrist_src for w in wrist_geoms})
    for name, body, gtype, size, pos, quat, _ in scene.fixtures:
        if name not in used:  # a stand-in the wrist does without
            continue
        spec.body(body).add_geom(name=name, type=getattr(mujoco.mjtGeom, f"mjGEOM_{gtype}"),
                                 size=list(size), pos=list(pos), quat=list(quat))
    _strip_looks(spec, wrist)
    if not exact_shapes_for_c(wrist, keep_cylinders):
        colliders.cylinders_for_mjx(spec, pair_names)
    def src(n):
        return param_src[n] if n in param_src else full.geom(n).id

    for n1, n2 in pair_names:
        spec.add_pair(geomname1=n1, geomname2=n2,
                      **colliders.mix_pair_params(full, src(n1), src(n2)))
    if max_contacts is not None:
        spec.add_numeric(name=MAX_CONTACTS_NUMERIC, data=[max_contacts])
    model = spec.compile()
    set_weld_rows(model)
    if metaworld_invweights:
        scene_bodies.copy_invweights(model, full)
    return model, {"npairs": len(pair_names), "virtual_geoms": virtual}
