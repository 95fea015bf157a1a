"""The scene a person sees for a MetaWorld port: metaworld's own, beside the physics scene.

The physics scene (`tasks.metaworld.scene.build_scene`) keeps no visual geom, table or floor,
and its arm has no geoms. The render scene is metaworld's XML compiled as metaworld compiles
it (the arm's meshes, the object's visual meshes, the table, floor, sky, lights and
materials), with the hand re-rooted on a free joint where the port's is (`arm=False`); its
joints and mocap body are the physics scene's, in the same order (joint-less bodies the
physics scene fuses or deletes carry no state), so a port's qpos, qvel and mocap pose draw
as they are. Nothing in it collides. The placed object moves with the render state's
`placement`, and metaworld's goal markers are put where the task's `goal_sites` says.
"""
from __future__ import annotations

import mujoco

from tasks.metaworld.scene import SceneSpec, metaworld_xml_path
from tasks.metaworld.scene_bodies import reroot_hand
from tasks.render_scene import RenderScene, subtree

# a free camera on the table's far half from the robot's right, above: the object, the
# gripper and the goal in view wherever the task places them
CAMERA = dict(lookat=(0.05, 0.75, 0.12), distance=1.1, azimuth=130.0, elevation=-30.0)


def build_render_scene(scene: SceneSpec, arm: bool, goal_sites,
                       mj_model: mujoco.MjModel | None = None) -> RenderScene:
    """metaworld's scene of `scene.xml` for a port built with `arm` (see module docstring);
    `goal_sites`: the task's markers ((forwarded data) -> {site: world position});
    `mj_model`: the physics model (unused: `tasks.render_scene` checks the layout)."""
    path = metaworld_xml_path(scene.xml)
    spec = mujoco.MjSpec.from_file(path)
    if not arm:
        reroot_hand(spec, path, scene.hand_init_pos, None, None, wrist_body=False,
                    keep_materials=True)
    model = spec.compile()
    model.geom_contype[:] = 0  # drawn, never collided (mj_forward finds no contact)
    model.geom_conaffinity[:] = 0
    obj = model.body(scene.object_geoms[0][0]).id  # the manipulated object
    placed = model.body(scene.placed_body).id if scene.placed_body else None
    return RenderScene(model=model, object_bodies=subtree(model, obj), camera=CAMERA,
                       placed_body=placed, goal_sites=goal_sites)
