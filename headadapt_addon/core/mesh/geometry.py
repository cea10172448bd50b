"""Triangle-mesh geometry on numpy arrays: normals, areas, boundaries, orientation, folds, checks
(mean curvature: curvature.py).

All functions take verts (n,3) float and tris (k,3) int and work in the verts' own frame and unit.
"""

import numpy as np
from scipy import sparse

from ..exceptions import MeshError
from ..tol import TINY


def cross(a, b):
    """Row-wise cross products (k,3) of (k,3) arrays: np.cross's numbers, three times faster on large arrays."""
    ax, ay, az = a[:, 0], a[:, 1], a[:, 2]
    bx, by, bz = b[:, 0], b[:, 1], b[:, 2]
    return np.stack([ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx], axis=1)


def bounds(v):
    """(lo, hi) (3,) of points (n,3): their box's corners. Column by column: numpy's min(axis=0) of an
    (n,3) array reduces three values a row at a time (a 1M-vertex scan: 28 ms against 2 ms a column)."""
    v = np.asarray(v)
    return (np.array([v[:, k].min() for k in range(v.shape[1])]),
            np.array([v[:, k].max() for k in range(v.shape[1])]))


def face_cross(v, t):
    """Cross product (k,3) of every triangle's two edges from its first corner: along its normal
    (right-hand rule), twice its area long. Computed once, it gives face_normals and vertex_normals
    the same numbers they would compute (a 2M-triangle scan needs both, and its winding check)."""
    a = v[t[:, 0]]                          # gathered once (a 2M-triangle scan: 48 MB)
    return cross(v[t[:, 1]] - a, v[t[:, 2]] - a)


def weld(verts, tris):
    """(verts, tris) with the vertices at exactly the same coordinates merged, keeping the first of each
    in the given order."""
    verts = np.ascontiguousarray(verts)
    key = verts.view(np.dtype((np.void, verts.dtype.itemsize * 3))).ravel()
    _, first, inverse = np.unique(key, return_index=True, return_inverse=True)
    order = np.argsort(first)
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return verts[first[order]], rank[inverse.ravel()][tris]


def face_areas(v, t):
    """Area of every triangle (k,), in the verts' unit squared."""
    return 0.5 * np.linalg.norm(face_cross(v, t), axis=1)


def face_normals(v, t, fc=None):
    """Unit normal (k,3) of every triangle (right-hand rule); zero for degenerate triangles. fc: the
    triangles' face_cross if the caller has it."""
    n = face_cross(v, t) if fc is None else fc
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return np.divide(n, length, out=np.zeros_like(n), where=length > 0)


def vertex_sums(t, fc, n):
    """Each vertex's sum (n,3) of its triangles' face_cross, added in triangle order: the area-weighted
    normal before its length is taken."""
    idx = t.ravel()
    # (float even with no triangles: bincount of nothing counts in integers)
    return np.stack([np.bincount(idx, weights=np.repeat(fc[:, c], 3), minlength=n) for c in range(3)],
                    axis=1).astype(np.float64, copy=False)


def vertex_normals(v, t, sums=None):
    """Area-weighted unit vertex normals (n,3); zero for vertices in no triangle. sums: the vertex_sums
    if the caller has them."""
    vn = vertex_sums(t, face_cross(v, t), len(v)) if sums is None else sums
    length = np.linalg.norm(vn, axis=1, keepdims=True)
    return np.divide(vn, length, out=np.zeros_like(vn), where=length > 0)


def _edge_keys(t):
    """(the sorted int64 key of every triangle's edges 01, 12, 20, n): key = lo * n + hi of its vertices."""
    t = np.asarray(t, dtype=np.int64)
    a, b = t.T.ravel(), t[:, [1, 2, 0]].T.ravel()
    n = int(t.max()) + 1
    key = np.minimum(a, b) * n + np.maximum(a, b)
    key.sort(kind="stable")         # the same values; timsort keeps the runs a mesh's order has (0.8x)
    return key, n


def boundary_edges(t):
    """Edges (e,2) used by exactly one triangle (sorted vertex pairs, in order). One int64 key per
    edge, sorted; a key unlike both its neighbours is used once (a 2M-triangle scan: no row sorts
    nor np.unique's counts, 3x faster)."""
    if not len(t):
        return np.zeros((0, 2), np.int64)
    key, n = _edge_keys(t)
    differ = key[1:] != key[:-1]
    single = key[np.r_[True, differ] & np.r_[differ, True]]
    return np.c_[single // n, single % n]


def odd_edges(t):
    """Edges (e,2) that an odd number of the triangles use (sorted vertex pairs, in order): on a
    manifold mesh, boundary_edges; carried through a vertex clustering, the original's border
    (mesh/simplify.py)."""
    if not len(t):
        return np.zeros((0, 2), np.int64)
    key, n = _edge_keys(t)
    start = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
    odd = key[start[np.diff(np.r_[start, len(key)]) % 2 == 1]]
    return np.c_[odd // n, odd % n]


def boundary_vertices(t, n):
    """Boolean mask (n,) of the vertices on a boundary edge."""
    mask = np.zeros(n, bool)
    mask[boundary_edges(t).ravel()] = True
    return mask


def boundary_faces(t):
    """Boolean mask (k,) of the triangles touching a boundary vertex (hole or outer border)."""
    if len(t) == 0:
        return np.zeros(0, bool)
    return any_corner(boundary_vertices(t, int(t.max()) + 1), t)


def any_corner(mask, t):
    """Boolean mask (k,) of the triangles with a corner in the vertex mask, corner by corner (numpy's
    any(axis=1) of the (k,3) gather: 20x slower on a scan's 2M triangles)."""
    return mask[t[:, 0]] | mask[t[:, 1]] | mask[t[:, 2]]


def all_corners(mask, t):
    """Boolean mask (k,) of the triangles with every corner in the vertex mask (as any_corner)."""
    return mask[t[:, 0]] & mask[t[:, 1]] & mask[t[:, 2]]


def orient_outward(v, t, centre, sums=None):
    """(tris, flipped): the triangles (k,3) with each connected piece wound so that its normals
    face away from `centre` (a point inside the head, same frame) on area-weighted balance, and
    how many pieces were turned. Scanners and converters often write inward-facing windings.
    sums: the triangles' vertex_sums if the caller has them."""
    from scipy.sparse import csgraph

    t = np.asarray(t)
    n, k = len(v), len(t)
    # the pieces: components of the graph of vertices and triangles, each triangle joined to its
    # corners; its rows (the triangles') are written as CSR as they stand, nothing to sort (a
    # 2M-triangle scan: 4x faster than the vertex graph through a coo matrix)
    graph = sparse.csr_matrix((np.ones(3 * k), t.ravel(), np.r_[np.zeros(n, np.int64), 3 * np.arange(k + 1)]),
                              shape=(n + k, n + k))
    n_comp, label = csgraph.connected_components(graph, directed=False)
    sums = vertex_sums(t, face_cross(v, t), n) if sums is None else sums
    # a piece's balance, sum over its triangles of cross . (centroid - centre), is corner by corner
    # a third of sum over its vertices of (vertex - centre) . sums: no triangle corners to gather
    vote = np.bincount(label[:n], weights=np.einsum("ij,ij->i", v - centre, sums), minlength=n_comp)
    flip = vote[label[n:]] < 0
    out = t.copy()
    out[flip] = out[flip][:, ::-1]
    return out, int((vote < 0).sum())


def neighbour_mean(t, n):
    """(n,n) sparse row-normalised vertex adjacency of a triangle mesh: A @ x is each vertex's
    neighbours' mean (an isolated vertex gets 0)."""
    e = np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]])
    e = np.unique(np.sort(e, axis=1), axis=0)
    adj = sparse.coo_matrix((np.ones(2 * len(e)), (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])),
                            shape=(n, n)).tocsr()
    return sparse.diags(1.0 / np.maximum(np.asarray(adj.sum(axis=1)).ravel(), 1)) @ adj


def folded(rest, x, t, sliver=0.01):
    """Indices of triangles whose normal at x turned against their normal at rest; slivers of rest
    (least height under `sliver` of the longest edge) have no orientation and are left out."""
    return FoldCheck(rest, t, sliver)(x)


class FoldCheck:
    """folded() against one rest mesh (rest (n,3), t (k,3)), its rest normals computed once: call it
    with positions x (n,3) for the indices of the triangles folded there."""

    def __init__(self, rest, t, sliver=0.01):
        self.t = t
        self.n0 = face_cross(rest, t)
        longest = np.linalg.norm(rest[t] - rest[np.roll(t, 1, axis=1)], axis=2).max(axis=1)
        self.ok = np.linalg.norm(self.n0, axis=1) > sliver * np.maximum(longest, TINY) ** 2

    def __call__(self, x):
        t = self.t
        n1 = face_cross(x, t)
        return np.flatnonzero((np.einsum("ij,ij->i", self.n0, n1) <= 0) & self.ok)

    def among(self, x, idx):
        """(len(idx),) bools: whether triangles idx are folded at x, each tested as __call__ tests it."""
        n1 = face_cross(x, self.t[idx])
        return (np.einsum("ij,ij->i", self.n0[idx], n1) <= 0) & self.ok[idx]


def unfold(rest, x, t, rounds=40, steps=10, mean=None, folds=None):
    """(x', moved mask, folded left): x (n,3) with its displacement from rest relaxed around the
    triangles still folded (Jacobi steps toward the neighbours' mean displacement, on their corners
    and a ring around them that widens every 4 rounds a fold resists) until nothing is folded or
    `rounds` run out; where folds are still left, the displacement over a widening ring around them
    is solved harmonic exactly (_harmonic); then each relaxed patch goes back toward x as far as it
    can without a fold. Same frame and unit as x; the rest of x is untouched. mean, folds: the mesh's
    neighbour_mean and its FoldCheck at rest if the caller keeps them (the adaptation does: made once
    per template, they were a third of a level's unfold)."""
    x = np.array(x, dtype=np.float64)
    x0 = x.copy()
    mean = neighbour_mean(t, len(x)) if mean is None else mean
    folds = FoldCheck(rest, t) if folds is None else folds
    moved = np.zeros(len(x), bool)
    for k in range(rounds):
        bad = folds(x)
        if not len(bad):
            break
        ring = np.zeros(len(x), bool)
        ring[t[bad].ravel()] = True
        for _ in range(1 + k // 4):
            ring |= (mean @ ring.astype(float)) > 0
        moved |= ring
        for _ in range(steps):
            x[ring] = rest[ring] + (mean @ (x - rest))[ring]
    if len(folds(x)):
        # the Jacobi steps did not settle (a fold pinned by a tight ring): the displacement over a ring
        # around the folds solved harmonic exactly, the ring widened until nothing is folded (a
        # harmonic map of a disc onto a convex patch does not fold, Rado-Kneser-Choquet)
        x, moved = _harmonic(folds, rest, x, t, mean, moved)
    if moved.any() and not len(folds(x)):
        x = _give_back(folds, x, x0, t, mean, moved)
    return x, moved, len(folds(x))


def _harmonic(folds, rest, x0, t, mean, moved, widen=(2, 4, 8, 16)):
    """(x, moved): x0 with the displacement from rest replaced, over the folds of x0 and `widen`
    rings around them, by the harmonic interpolation of its values on the ring's border; the
    narrowest ring that folds nothing (else the widest tried)."""
    from scipy.sparse.linalg import spsolve

    seed = np.zeros(len(x0), bool)
    seed[t[folds(x0)].ravel()] = True
    ring, grown, y = seed.copy(), 0, x0
    for n in widen:
        for _ in range(n - grown):
            ring |= (mean @ ring.astype(float)) > 0
        grown = n
        inside = np.flatnonzero(ring)
        d = x0 - rest
        system = (sparse.identity(len(inside), format="csc") - mean[inside][:, inside]).tocsc()
        border = mean[inside][:, ~ring] @ d[~ring]
        y = x0.copy()
        y[inside] = rest[inside] + np.asarray(spsolve(system, border)).reshape(-1, 3)
        if not len(folds(y)):
            break
    return y, moved | ring


def _give_back(folds, x, x0, t, mean, moved, steps=8):
    """Each relaxed patch (a connected piece of `moved`) goes back toward its unrelaxed place x0
    by the largest share (bisection) that folds nothing: the repair costs the fit no more than it
    must."""
    from scipy.sparse import csgraph

    sel = np.flatnonzero(moved)
    _, comp = csgraph.connected_components(mean[sel][:, sel], directed=False)
    label = np.full(len(x), -1)
    label[sel] = comp
    lo, hi = np.zeros(comp.max() + 1), np.ones(comp.max() + 1)
    for _ in range(steps):
        mid = 0.5 * (lo + hi)
        y = x.copy()
        y[sel] += mid[comp][:, None] * (x0[sel] - x[sel])
        bad = np.zeros(len(lo), bool)
        corners = label[t[folds(y)]].ravel()
        bad[corners[corners >= 0]] = True
        lo, hi = np.where(bad, lo, mid), np.where(bad, mid, hi)
    y = x.copy()
    y[sel] += lo[comp][:, None] * (x0[sel] - x[sel])
    return y


def check_mesh(v, t, name="scan"):
    """Raise MeshError naming the mesh if it cannot be adapted to (empty, not triangles, bad indices, NaN)."""
    v, t = np.asarray(v), np.asarray(t)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0:
        raise MeshError(f"the {name} has no vertices (expected an (n,3) array, got shape {v.shape})")
    if t.ndim != 2 or t.shape[1] != 3:
        raise MeshError(f"the {name} is not a triangle mesh (faces of shape {t.shape}; triangulate it first)")
    if len(t) == 0:
        raise MeshError(f"the {name} has no faces (a point cloud is not a surface)")
    if t.min() < 0 or t.max() >= len(v):
        raise MeshError(f"the {name} has faces that refer to vertices that do not exist")
    if not np.isfinite(v).all():
        bad = int(np.flatnonzero(~np.isfinite(v).all(axis=1))[0])
        raise MeshError(f"the {name} has NaN or infinite coordinates (vertex {bad} and maybe more)")
    if not (face_areas(v, t[:1000]) > 0).any() and not (face_areas(v, t) > 0).any():   # most: the first 1000
        raise MeshError(f"every face of the {name} is degenerate (zero area)")
