"""C MuJoCo port_c runs of button_press scene variants vs metaworld (cached)."""
import tasks  # noqa
import dataclasses, json, os, sys
import numpy as np
from scipy.spatial import ConvexHull
from benchmarks import metaworld_dynamics as md
from tasks.metaworld import sawyer
from tasks.metaworld.button_press import ButtonPress

EP = int(os.environ.get("EP", 20))
cache = f"/tmp/exp/mw_button_{EP}.json"
if False:
    mw = json.load(open(cache))
else:
    mw = None


_orig_hull = sawyer._wrist_hull_points

def slice_points(model, data, g, body, levels):
    """corners of the bounding rectangles of the mesh's slices along the approach axis"""
    mid = model.geom_dataid[g]
    verts = model.mesh_vert[model.mesh_vertadr[mid]:model.mesh_vertadr[mid] + model.mesh_vertnum[mid]]
    world = data.geom_xpos[g] + verts @ data.geom_xmat[g].reshape(3, 3).T
    rot_b = data.xmat[body].reshape(3, 3)
    local = (world - data.xpos[body]) @ rot_b
    hull = local[ConvexHull(local).vertices]
    ys = np.sort(hull[:, 1])
    edges = [hull[:, 1].min()] + list(levels) + [hull[:, 1].max() + 1e-9]
    pts = []
    for a, b in zip(edges[:-1], edges[1:]):
        s = hull[(hull[:, 1] >= a) & (hull[:, 1] <= b)]
        if len(s) == 0:
            continue
        for y in (s[:, 1].min(), s[:, 1].max()):
            for x in (s[:, 0].min(), s[:, 0].max()):
                for z in (s[:, 2].min(), s[:, 2].max()):
                    pts.append((x, y, z))
    pts = np.unique(np.array(pts), axis=0)
    return pts[ConvexHull(pts).vertices]

def variant(shape, stop, shift=0.0, levels=None, flange=False):
    scene = ButtonPress.scene
    fixtures = list(scene.fixtures)
    extra = [p for p in scene.extra_pairs if p != ("wrist", "box_hull")]
    if flange:
        extra += [(("button", 1), ("buttonbox", i)) for i in range(4)]
    if stop == "block":
        f = list(fixtures[0]); pos = list(f[4]); pos[1] += shift; f[4] = tuple(pos)
        fixtures[0] = tuple(f)
        extra.append(("wrist", "box_hull"))
    elif stop == "front" and os.environ.get("SUPPORT"):
        import importlib.util
        sp = importlib.util.spec_from_file_location("sup", "/tmp/exp/bp_variants_support.py")
        sup = importlib.util.module_from_spec(sp); sp.loader.exec_module(sup)
        sawyer._wrist_slice_hull = lambda m, d, g, b, c: sup.support_front(m, d, g, b, c, int(os.environ["SUPPORT"]))
        fixtures = fixtures[1:]
        sc = dataclasses.replace(scene, fixtures=tuple(fixtures), extra_pairs=tuple(extra),
                                 wrist_front_geoms=tuple(("buttonbox", i) for i in range(4)),
                                 wrist_front_cuts=tuple(levels))
        return type("BP", (ButtonPress,), {"scene": sc})(wrist=shape)
    elif stop == "front":  # the 4 slabs x a front hull, the box for the button parts
        fixtures = fixtures[1:]
        sc = dataclasses.replace(scene, fixtures=tuple(fixtures), extra_pairs=tuple(extra),
                                 wrist_front_geoms=tuple(("buttonbox", i) for i in range(4)),
                                 wrist_front_cuts=tuple(levels))
        cls = type("BP", (ButtonPress,), {"scene": sc})
        sawyer._wrist_hull_points = _orig_hull
        return cls(wrist=shape)
    else:  # the 4 slabs
        fixtures = fixtures[1:]
        extra += [("wrist", ("buttonbox", i)) for i in range(4)]
    sc = dataclasses.replace(scene, fixtures=tuple(fixtures), extra_pairs=tuple(extra))
    cls = type("BP", (ButtonPress,), {"scene": sc})
    if shape == "slices":
        sawyer._wrist_hull_points = lambda m, d, g, b, k: slice_points(m, d, g, b, levels)
        t = cls(wrist=999)
    else:
        sawyer._wrist_hull_points = _orig_hull
        t = cls(wrist=int(shape) if shape.isdigit() else shape)
    return t

