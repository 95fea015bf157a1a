import numpy as np
from scipy.spatial import ConvexHull
from tasks.metaworld import sawyer

def support_front(model, data, g, body, cuts, ndir=48):
    local = sawyer._mesh_vertices(model, data, g, body)
    hull = ConvexHull(local)
    c0 = cuts[0]
    pts = local[hull.vertices]
    a = local[hull.simplices]; b = np.roll(a, 1, axis=1)
    a, b = a.reshape(-1, 3), b.reshape(-1, 3)
    cr = (a[:, 1] - c0) * (b[:, 1] - c0) < 0
    t = (c0 - a[cr, 1]) / (b[cr, 1] - a[cr, 1])
    pts = np.vstack([pts[pts[:, 1] >= c0], a[cr] + t[:, None] * (b[cr] - a[cr])])
    # fibonacci directions
    i = np.arange(ndir) + 0.5
    phi = np.arccos(1 - 2 * i / ndir); th = np.pi * (1 + 5 ** 0.5) * i
    dirs = np.stack([np.cos(th) * np.sin(phi), np.sin(th) * np.sin(phi), np.cos(phi)], 1)
    idx = np.unique(np.argmax(pts @ dirs.T, axis=0))
    sel = pts[idx]
    return sel[ConvexHull(sel).vertices]
