"""Collision shapes and contact parameters of the simplified metaworld scenes: the wrist
collider that replaces the gripper-base mesh, MJX-collidable stand-ins for paired cylinders,
and the parameters MuJoCo mixes for a dynamic contact (see `tasks.metaworld.scene`)."""
from __future__ import annotations

import hashlib
import os
import tempfile
from pathlib import Path

import mujoco
import numpy as np


def mix_pair_params(model: mujoco.MjModel, g1: int, g2: int) -> dict:
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


def wrist_source(full: mujoco.MjModel) -> int:
    """metaworld's gripper-base collision mesh (on `right_hand`), which the wrist replaces."""
    return next(g for g in range(full.ngeom) if full.geom_bodyid[g] == full.body(
        "right_hand").id and full.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH
        and full.geom_contype[g])


def mesh_vertices(model: mujoco.MjModel, data: mujoco.MjData, g: int, body: int) -> np.ndarray:
    """Mesh geom g's vertices in `body`'s frame (at the pose in `data`)."""
    mid = model.geom_dataid[g]
    verts = model.mesh_vert[model.mesh_vertadr[mid]:model.mesh_vertadr[mid] + model.mesh_vertnum[mid]]
    world = data.geom_xpos[g] + verts @ data.geom_xmat[g].reshape(3, 3).T
    return (world - data.xpos[body]) @ data.xmat[body].reshape(3, 3)


def wrist_box(model: mujoco.MjModel, data: mujoco.MjData, g: int, body: int) -> tuple:
    """Box around mesh geom g's vertices with the axes of the `hand` frame (the gripper's own
    axes: fingers along y, approach along x), as (half sizes, pos, quat) in `body`'s frame."""
    hand = model.body("hand").id
    rot_h = data.xmat[hand].reshape(3, 3)
    local = mesh_vertices(model, data, g, hand)  # vertices in hand axes
    lo, hi = local.min(0), local.max(0)
    centre = data.xpos[hand] + rot_h @ ((lo + hi) / 2)
    rot_b = data.xmat[body].reshape(3, 3)
    pos = rot_b.T @ (centre - data.xpos[body])
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, (rot_b.T @ rot_h).ravel())
    return (hi - lo) / 2, pos, quat


def wrist_hull_points(model, data, g, body, k):
    """k vertices of mesh g's convex hull (farthest-point sampled), in `body`'s frame."""
    from scipy.spatial import ConvexHull
    local = mesh_vertices(model, data, g, body)
    return farthest_points(local[ConvexHull(local).vertices], k)


def farthest_points(points: np.ndarray, k: int) -> np.ndarray:
    """k of `points` spread out (farthest-point sampling from the one farthest from the mean)."""
    centre = points.mean(0)
    chosen = [int(np.argmax(np.linalg.norm(points - centre, axis=1)))]
    dist = np.linalg.norm(points - points[chosen[0]], axis=1)
    while len(chosen) < min(k, len(points)):
        i = int(np.argmax(dist))
        chosen.append(i)
        dist = np.minimum(dist, np.linalg.norm(points - points[i], axis=1))
    return points[chosen]


def parse_pieces(wrist) -> tuple[float, int, int, list[int] | None] | None:
    """"coacd[:THRESHOLD[:MAX_HULLS[:POINTS[:I,J,...]]]]" -> (CoACD's concavity threshold, its
    most pieces, hull points kept per piece, the pieces kept: None = all); None otherwise."""
    if not (isinstance(wrist, str) and wrist.startswith("coacd")):
        return None
    thr, hulls, points, keep = (wrist[len("coacd"):].split(":") + ["0.3", "8", "24", ""])[1:5]
    return float(thr), int(hulls), int(points), (
        [int(i) for i in keep.split(",")] if keep else None)


def wrist_coacd(model, data, g, body, threshold: float, max_hulls: int, points: int,
                keep: list[int] | None = None) -> list[np.ndarray]:
    """Mesh g's approximate convex decomposition (CoACD with coarse search settings: about
    10 s; its defaults took 9 min and gave 57 pieces), each piece on `points` of its hull
    points (farthest-point sampled), in `body`'s frame; `keep`: the pieces kept, by index.
    Unlike one hull of the whole mesh, the pieces keep the shape of its front."""
    import coacd  # a dependency; imported here, as only button_press's scene needs it
    from scipy.spatial import ConvexHull
    verts = mesh_vertices(model, data, g, body)
    mid = model.geom_dataid[g]
    faces = model.mesh_face[model.mesh_faceadr[mid]:model.mesh_faceadr[mid] + model.mesh_facenum[mid]]
    settings = (threshold, max_hulls, points, _coacd_version())
    path = _pieces_cache(verts, faces, settings)
    if path.exists():
        with np.load(path) as z:
            pieces = [z[f"piece_{i}"] for i in range(len(z.files))]
    else:
        coacd.set_log_level("error")
        parts = coacd.run_coacd(coacd.Mesh(verts, faces), threshold=threshold,
                                max_convex_hull=max_hulls, preprocess_resolution=20,
                                resolution=1000, mcts_nodes=10, mcts_iterations=60,
                                mcts_max_depth=2, seed=0)
        pieces = [farthest_points(v[ConvexHull(v).vertices], points) for v, _ in parts]
        _save_pieces(path, pieces)
    return pieces if keep is None else [pieces[i] for i in keep]


def _coacd_version() -> str:
    from importlib import metadata

    return metadata.version("coacd")


def _pieces_cache(verts: np.ndarray, faces: np.ndarray, settings: tuple) -> Path:
    """Where a decomposition is kept: CoACD takes about 10 s and gives the same pieces for the
    same mesh, settings and version (seed 0), so each process need not run it again.
    $HPRIOR_COACD_CACHE, default ~/.cache/hprior_jax/coacd."""
    h = hashlib.sha256()
    for array in (verts, faces):
        h.update(np.ascontiguousarray(array).tobytes())
    h.update(repr(settings).encode())
    root = Path(os.environ.get("HPRIOR_COACD_CACHE",
                               Path.home() / ".cache" / "hprior_jax" / "coacd"))
    return root / f"{h.hexdigest()[:20]}.npz"


def _save_pieces(path: Path, pieces: list[np.ndarray]) -> None:
    """Written whole or not at all (another process may read it meanwhile)."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=path.parent, suffix=".npz", delete=False) as f:
            np.savez(f, **{f"piece_{i}": p for i, p in enumerate(pieces)})
        os.replace(f.name, path)
    except OSError:  # a read-only or full cache: the next process decomposes again
        pass


def add_wrist(spec: mujoco.MjSpec, full: mujoco.MjModel, full_data: mujoco.MjData,
              wrist: str | int, src: int) -> list[str]:
    """The wrist geoms on `right_hand`: metaworld's mesh itself ("mesh"), a convex mesh on
    `wrist` of its hull points (an int), convex pieces of it ("coacd...", `parse_pieces`), or
    its bounding box in the hand's axes ("box"). -> their names."""
    settings = parse_pieces(wrist)
    if settings is not None:
        pieces = wrist_coacd(full, full_data, src, full.body("right_hand").id, *settings)
        for i, pts in enumerate(pieces):
            spec.add_mesh(name=f"wrist_hull_{i}", uservert=pts.ravel().tolist())
            spec.body("right_hand").add_geom(name=f"wrist_{i}", type=mujoco.mjtGeom.mjGEOM_MESH,
                                             meshname=f"wrist_hull_{i}")
        return [f"wrist_{i}" for i in range(len(pieces))]
    if wrist == "mesh":
        spec.geom(full.geom(src).name).name = "wrist"
    elif not isinstance(wrist, str):
        pts = wrist_hull_points(full, full_data, src, full.body("right_hand").id, wrist)
        spec.add_mesh(name="wrist_hull", uservert=pts.ravel().tolist())
        spec.body("right_hand").add_geom(name="wrist", type=mujoco.mjtGeom.mjGEOM_MESH,
                                         meshname="wrist_hull")
    else:
        size, pos, quat = wrist_box(full, full_data, src, full.body("right_hand").id)
        spec.body("right_hand").add_geom(name="wrist", type=mujoco.mjtGeom.mjGEOM_BOX,
                                         size=list(size), pos=list(pos), quat=list(quat))
    return ["wrist"]


# partners with which MJX collides a cylinder exactly
_CYLINDER_PARTNERS = {mujoco.mjtGeom.mjGEOM_PLANE, mujoco.mjtGeom.mjGEOM_SPHERE,
                      mujoco.mjtGeom.mjGEOM_CAPSULE, mujoco.mjtGeom.mjGEOM_CYLINDER}


def cylinders_for_mjx(spec: mujoco.MjSpec, pair_names: list) -> None:
    """MJX has no cylinder-box collision: a paired cylinder becomes a capsule of the same
    radius and end-to-end length (long cylinders: handle rods), or a box with the cylinder's
    bounding extents (short, wide ones: the button cap, which a capsule would lengthen by its
    radius towards the gripper) -- unless every partner is a plane, a sphere, a capsule or a
    cylinder, which MJX collides with cylinders exactly."""
    used = {n for p in pair_names for n in p}
    kinds = {g.name: g.type for g in spec.geoms}
    for g in spec.geoms:
        if g.type != mujoco.mjtGeom.mjGEOM_CYLINDER or g.name not in used:
            continue
        partners = [b if a == g.name else a for a, b in pair_names if g.name in (a, b)]
        if all(kinds[p] in _CYLINDER_PARTNERS for p in partners):
            continue
        r, hl = g.size[0], g.size[1]
        if hl > r:
            g.type, g.size = mujoco.mjtGeom.mjGEOM_CAPSULE, [r, hl - r, 0]
        else:
            g.type, g.size = mujoco.mjtGeom.mjGEOM_BOX, [r, r, hl]
