"""Offscreen MuJoCo rendering of task states and video files (host side).

Rendering needs an OpenGL backend without a display: OSMesa (Debian: `libosmesa6`, the
default here) or EGL (`HPRIOR_GL=egl`, a GPU driver's libEGL). The project imports mujoco
with MUJOCO_GL=disable (MJX needs no GL), so the backend's context class is handed to
mujoco's renderer here, on first use.

Frames are drawn from a task's render scene (`tasks.render_scene`): a render-only model with
the physics model's joints (MetaWorld: metaworld's own scene with its meshes, table and
floor, which the physics model leaves out), posed by the recorded states."""
from __future__ import annotations

import copy
import os
import warnings
from pathlib import Path

import mujoco
import numpy as np

from tasks.base import RENDER_FIELDS as FIELDS  # noqa: F401  (what positions a frame)
from tasks.render_scene import render_scene

# The MP4 encoder is an ffmpeg child process (fork, then exec at once), which JAX's warning
# about forking a multithreaded process does not concern (a filter, not a context manager:
# clips are written from a background thread while a run waits for labels).
warnings.filterwarnings("ignore", message=r"os\.fork\(\) was called", category=RuntimeWarning)


def _install_gl_context() -> None:
    from mujoco.rendering.classic import gl_context

    if getattr(gl_context, "GLContext", None) is not None:
        return
    backend = os.environ.get("HPRIOR_GL", "osmesa")
    try:
        if backend == "egl":
            from mujoco.egl import GLContext
        else:
            from mujoco.osmesa import GLContext
    except (ImportError, AttributeError) as e:
        raise RuntimeError(
            f"offscreen rendering needs the {backend} OpenGL library ({e}); on Debian or "
            "Ubuntu: apt-get install libosmesa6 (or HPRIOR_GL=egl with a GPU driver)") from None
    gl_context.GLContext = GLContext


def default_camera(mj_model: mujoco.MjModel, lookat: np.ndarray | None = None):
    """The camera a task's frames are drawn from (`mj_model`: the task's physics model):
    its render scene's (a named camera, or a fixed free camera on the whole scene, e.g.
    MetaWorld's table; `lookat` is then unused), else the model's first camera, else a free
    camera from three quarters above, looking at `lookat` (closer) or the model's centre."""
    scene = render_scene(mj_model)
    model = scene.model
    if isinstance(scene.camera, str):
        return model.camera(scene.camera).id
    camera = mujoco.MjvCamera()
    if isinstance(scene.camera, dict):
        camera.type = mujoco.mjtCamera.mjCAMERA_FREE
        camera.lookat[:] = scene.camera["lookat"]
        for name in ("distance", "azimuth", "elevation"):
            setattr(camera, name, scene.camera[name])
        return camera
    if model.ncam:
        return 0
    mujoco.mjv_defaultFreeCamera(model, camera)
    camera.azimuth, camera.elevation = 135.0, -30.0
    camera.distance *= 0.6
    if lookat is not None:
        camera.lookat[:] = lookat
        camera.distance *= 0.5
    return camera


def hand_start(states: dict[str, np.ndarray]) -> np.ndarray | None:
    """MetaWorld's mocap (hand) target at a segment's first step: where to look."""
    pos = states.get("mocap_pos")
    return None if pos is None or not pos.size else pos[0, 0]


def render_frames(mj_model: mujoco.MjModel, states: dict[str, np.ndarray], width: int = 320,
                  height: int = 240, camera=None, segmentation: bool = False) -> np.ndarray:
    """uint8[T, height, width, 3]: one frame per row of `states` (`Task.render_state`'s
    fields, each [T, ...]) of the task whose physics model is `mj_model`, drawn from its
    render scene (`tasks.render_scene`), from `camera` (default: `default_camera` at the
    hand's start). segmentation: int32[T, height, width, 2] instead, each pixel's (object
    id, mjtObj type) in the render scene's model, (-1, -1) where nothing is drawn."""
    _install_gl_context()
    scene = render_scene(mj_model)
    if camera is None:
        camera = default_camera(mj_model, hand_start(states))
    model = copy.copy(scene.model)  # the placement edits body_pos
    model.vis.global_.offwidth = max(model.vis.global_.offwidth, width)
    model.vis.global_.offheight = max(model.vis.global_.offheight, height)
    data = mujoco.MjData(model)
    frames = []
    with mujoco.Renderer(model, height, width) as renderer:
        if segmentation:
            renderer.enable_segmentation_rendering()
        for t in range(len(states["qpos"])):
            scene.pose(model, data, states, t)
            renderer.update_scene(data, camera=camera)
            frames.append(renderer.render())
    return np.stack(frames)


def write_video(frames: np.ndarray, path: Path, fps: float) -> Path:
    """MP4 (H.264, playable in browsers) or GIF, by the suffix of `path`."""
    import imageio.v3 as iio

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix == ".gif":
        iio.imwrite(path, frames, duration=1000 / fps, loop=0)
        return path
    iio.imwrite(path, frames, fps=fps, codec="libx264", macro_block_size=8)
    return path
