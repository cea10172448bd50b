"""A dense scan simplified once, by vertex clustering, to the detail the fit can use.

The template's finest level places its centres 2 mm apart; a scanner's 1M-vertex head is sampled
every 0.3-0.5 mm. Clustering its vertices on a cubic grid (each cell's vertices merged into their
mean, the triangles kept that still have three corners, each once) gives a mesh with the same surface
up to the cell's noise-averaging (the mean of a cell's points lies off a surface of curvature radius R
by about cell^2 / (8 R): 0.01 mm for a 1 mm cell on a 10 mm lip) at a fraction of the vertices (the
1M bench head: 252k clusters at 1 mm), so that the scan's preparation (normals, border, curvature,
spatial tree) and its queries cost what such a scan costs. A kept triangle keeps its corners' order;
a few slivers fold over where a cell's mean lands past its neighbours' (0.7% of the triangles, 0.2%
of the area of a clustered sphere).
"""

from __future__ import annotations

import numpy as np

from .. import threads
from ..exceptions import MeshError
from . import geometry

BITS = 21           # grid coordinates per axis in one int64 key (a 0.3 m head at 1 mm: 300 cells)


def median_edge(verts, tris, sample=20000):
    """The median length of the triangles' first edges, from every k-th triangle (k = len // sample: from
    `sample` to twice as many triangles, or all of them)."""
    if not len(tris):
        return 0.0
    t = tris[:: max(1, len(tris) // sample)]
    return float(np.median(np.linalg.norm(verts[t[:, 1]] - verts[t[:, 0]], axis=1)))


def _spread(values, mask):
    """values given at mask's True places, as an array over all of mask (0 elsewhere)."""
    out = np.zeros(len(mask), values.dtype)
    out[mask] = values
    return out


def unique_inverse(key):
    """(how many distinct values, each value's rank among them) of an int64 array: np.unique(key,
    return_inverse=True)'s inverse, by a stable sort, which keeps the runs a scan's vertex order already
    has (a 1M-vertex scan's cell keys: 0.06 s against np.unique's quicksort 0.13 s)."""
    if not len(key):
        return 0, np.zeros(0, np.int64)
    order = np.argsort(key, kind="stable")
    ranked = key[order]
    new = np.empty(len(key), bool)
    new[0] = True
    np.not_equal(ranked[1:], ranked[:-1], out=new[1:])
    rank = np.cumsum(new) - 1
    inv = np.empty(len(key), np.int64)
    inv[order] = rank
    return int(rank[-1]) + 1, inv


SPLIT = 0.6         # more vertices than this x triangles: corners not shared (a welded surface has about 0.5)
WELD_TOL = 1e-5     # corners nearer than this x the mesh's size (its box's diagonal) are one point


def weld_if_split(verts, tris):
    """weld_close(verts, tris) when the mesh has over SPLIT vertices a triangle, else None. Exporters split
    vertices at texture seams and normal creases, or write every triangle with its own corners (a
    triangle soup); unwelded, each such edge is a hole's border to the fit, which keeps no pair there
    (a head with a third of its triangles split: correspondence 12.9 mm instead of 6.2)."""
    if len(verts) > SPLIT * len(tris):
        lo, hi = geometry.bounds(np.asarray(verts, dtype=np.float64))
        return weld_close(np.asarray(verts), np.asarray(tris), WELD_TOL * float(np.linalg.norm(hi - lo)))
    return None


def weld_close(verts, tris, tol):
    """(verts, tris) with the vertices within tol of each other (chains of them) merged into the first of
    each group, in the given order; triangles left with a repeated corner dropped."""
    from scipy import sparse
    from scipy.sparse import csgraph
    from scipy.spatial import cKDTree

    n = len(verts)
    pairs = cKDTree(verts).query_pairs(tol, output_type="ndarray") if n else np.zeros((0, 2), np.int64)
    graph = sparse.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    count, label = csgraph.connected_components(graph, directed=False)
    first = np.full(count, n)
    np.minimum.at(first, label, np.arange(n))
    # each vertex moved onto its group's first, the exact weld then merges each group into it, in order
    verts, welded = geometry.weld(verts[first[label]], tris)
    keep = (welded[:, 0] != welded[:, 1]) & (welded[:, 1] != welded[:, 2]) & (welded[:, 0] != welded[:, 2])
    return verts, welded[keep]


def cluster_if_finer(verts, tris, cell):
    """cluster(verts, tris, cell) when the mesh's median edge is under `cell` (0: never), else None."""
    if cell and len(tris) and median_edge(verts, tris) < cell:
        return cluster(verts, tris, cell)
    return None


def cluster(verts, tris, cell):
    """(verts (k,3), tris (j,3), border (e,2)) of the mesh clustered on a grid of `cell` (the verts'
    unit): every used vertex merged into the mean of its cell's, the triangles that keep three corners,
    each set of three clusters once (its first triangle, with that orientation); unused vertices
    dropped. The border is the mesh's own carried to the clusters: the edges an odd number of the
    kept triangles used before duplicates were dropped (a triangle that loses a corner adds its one
    edge twice, so the parity of every edge is the original border's). Counted after the duplicates
    are dropped, clustering would leave edges used once where a fan collapses, inside the surface."""
    verts = np.asarray(verts, dtype=np.float64)
    tris = np.asarray(tris, dtype=np.int64)
    used = np.zeros(len(verts), bool)
    used[tris.ravel()] = True
    every = used.all()                                    # (a scan's usual case: no masks to apply)
    inside = verts if every else verts[used]
    lo = geometry.bounds(inside)[0]
    key = np.zeros(len(inside), np.int64)
    for k in range(3):
        g = ((inside[:, k] - lo[k]) * (1.0 / cell)).astype(np.int64)
        if g.max(initial=0) >= 1 << BITS:
            # a piece far from the rest (a stray triangle a kilometre off): the cells' ranks along the
            # axis instead, in the same order, so the same clusters
            g = unique_inverse(g)[1]
            if g.max(initial=0) >= 1 << BITS:
                raise MeshError(f"the mesh spans over 2^{BITS} occupied cells of {cell} along one axis")
        key |= g << (2 - k) * BITS
    n, inv = unique_inverse(key)
    count = np.bincount(inv, minlength=n)
    merged = np.stack([np.bincount(inv, weights=inside[:, k], minlength=n) for k in range(3)], axis=1) / count[:, None]
    if not every:                                         # the cluster of every vertex (unused: never read)
        inv = _spread(inv, used)
    # the triangles' clusters as int32 while they are many (a 1M scan's 2M: 0.03 against 0.1 s)
    t = inv.astype(np.int32)[tris] if n < 1 << 31 else inv[tris]
    t = t[(t[:, 0] != t[:, 1]) & (t[:, 1] != t[:, 2]) & (t[:, 2] != t[:, 0])]
    border = threads.pool().submit(geometry.odd_edges, t)  # beside the duplicates' sort (numpy's sorts
    first = first_of_each(t, n)                           # release the GIL: 0.07 s of 0.4 on a 1M scan)
    return merged, t[first].astype(np.int64), border.result()


def first_of_each(t, n):
    """The indices (sorted) of the first triangle of each set of three corners in t (k,3), n vertices."""
    s = np.sort(t, axis=1).astype(np.int64)
    if n ** 3 < 1 << 62:
        _, first = np.unique((s[:, 0] * n + s[:, 1]) * n + s[:, 2], return_index=True)
    else:                                                 # too many vertices for one key: rows
        _, first = np.unique(s, axis=0, return_index=True)
    return np.sort(first)
