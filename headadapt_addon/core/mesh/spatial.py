"""Nearest-surface queries and ray casts on a triangle mesh, exact: a numpy BVH, or Embree's or
Blender's BVH if asked.

The numpy backend (core/mesh/bvh.py) walks a bounding-volume hierarchy for all queries at once and
hands every face that can answer to core/mesh/triangles.py, which measures them (closest_on_triangles,
ray_triangles) and chooses (closest_choice, ray_choice), so its answers are those of a brute-force loop
over every triangle, with one rule at a tie:
- closest point: the least distance; at exactly that distance (a shared vertex, or a shared edge where
  the rounding agrees) the face whose normal is most nearly along the offset from the surface (largest
  |cos|: the face the point lies most squarely in front of or behind), then the lowest face index;
- ray: the least |t| (both ways: t and -t alike), then the lowest face index.
The bvh backend (Blender's mathutils BVHTree) answers as Blender does: the same points and hits up to
float32 rounding (~1e-7 of the mesh's size), and at a tie whichever face its search met first.
The embree backend (core/mesh/embree.py: Intel Embree through the embreex package, where installed)
casts rays in C and measures each hit again in float64, so its rays give the numpy tree's numbers but
for the face at a tie and float32's misses by an edge; its closest points are the numpy tree's.
All coordinates are the mesh's own frame and unit.
"""

import dataclasses

import numpy as np

from .. import threads
from .bvh import TriangleBVH
from .triangles import closest_on_triangles, ray_triangles  # noqa: F401 (spatial.closest_on_triangles, ...)

CHUNK = 1 << 16     # queries per walk of the numpy tree (bounds its memory: ~10 pairs per query and level)
SPLIT = 1024        # more queries than twice this are walked as two halves on two threads


def _in_parts(walk, n):
    """walk(a, b) over the queries a..b-1 in parts of at most CHUNK, results in order. Two or more
    parts go to two threads: the walks are numpy on large arrays, which releases the GIL, so on two
    cores a skin's 4k rays onto a scan take about 0.6 of their time (answers the same: each query
    is walked alone)."""
    size = min(CHUNK, max(SPLIT, -(-n // 2)))
    bounds = [(a, min(a + size, n)) for a in range(0, n, size)] or [(0, 0)]
    if len(bounds) == 1:
        return [walk(*bounds[0])]
    return list(threads.pool().map(lambda ab: walk(*ab), bounds))


@dataclasses.dataclass
class RayHits:
    """Nearest hits of rays: hit mask, signed distance t along the unit direction, face, point, barycentrics."""
    hit: np.ndarray
    t: np.ndarray
    face: np.ndarray
    point: np.ndarray
    bary: np.ndarray


def bvh_class():
    """mathutils' BVHTree when running inside Blender or beside the bpy module, else None."""
    try:
        import bpy  # noqa: F401  (the bpy module makes mathutils importable)
        from mathutils.bvhtree import BVHTree
    except ImportError:
        return None
    return BVHTree


def barycentric(points, a, b, c):
    """Barycentric coordinates (n,3) of points in triangles (a,b,c) (points assumed in the plane)."""
    v0, v1, v2 = b - a, c - a, points - a
    d00, d01, d11 = (np.einsum("ij,ij->i", x, y) for x, y in ((v0, v0), (v0, v1), (v1, v1)))
    d20, d21 = np.einsum("ij,ij->i", v2, v0), np.einsum("ij,ij->i", v2, v1)
    den = np.where(np.abs(d00 * d11 - d01 * d01) > 0, d00 * d11 - d01 * d01, 1.0)
    v = (d11 * d20 - d01 * d21) / den
    w = (d00 * d21 - d01 * d20) / den
    return np.c_[1 - v - w, v, w]


class MeshQuery:
    """Closest-point and ray queries on one triangle mesh (built once, reused).

    backend "numpy" (the default) is the numpy BVH of core/mesh/bvh.py; "bvh" uses Blender's C BVH tree
    (mathutils, inside Blender or beside the bpy module) with a loop over queries; "embree" casts rays
    with Intel Embree (the embreex package; about 4x faster than the numpy tree on a skin's rays onto a
    scan) and finds closest points with the numpy tree. The caller chooses: nothing here imports Blender
    or embreex unless asked to. All give the same answers up to float32 rounding and the face at a tie
    (see the module; tested).
    """

    def __init__(self, verts, tris, backend="numpy"):
        self.verts = np.asarray(verts, dtype=np.float64)
        self.tris = np.asarray(tris, dtype=np.int64)
        if backend not in ("numpy", "bvh", "embree"):
            raise ValueError(f"unknown spatial backend {backend!r} (numpy, bvh or embree)")
        self.backend = backend
        if backend == "bvh":
            bvh = bvh_class()
            if bvh is None:
                raise ImportError("the bvh backend needs mathutils (Blender or the bpy module)")
            self.bvh = bvh.FromPolygons(self.verts.tolist(), self.tris.tolist(), all_triangles=True)
            return
        self.tree = TriangleBVH(self.verts, self.tris)
        if backend == "embree":
            from .embree import EmbreeRays
            self.rays = EmbreeRays(self.verts, self.tris, self.tree)

    def _tri(self, faces):
        c = self.verts[self.tris[faces]]
        return c[:, 0], c[:, 1], c[:, 2]

    def closest_points(self, points):
        """(closest (n,3), face (n,), dist (n,)) on the mesh for query points (n,3)."""
        points = np.atleast_2d(np.asarray(points, dtype=np.float64))
        if self.backend == "bvh":
            return self._bvh_closest(points)
        parts = _in_parts(lambda a, b: self.tree.closest(points[a:b]), len(points))
        return tuple(np.concatenate(x) for x in zip(*parts))

    def ray_cast(self, origins, directions, max_dist, both_ways=True):
        """Nearest hits within max_dist (scalar or (n,)) along unit directions (both ways if asked)."""
        o = np.atleast_2d(np.asarray(origins, dtype=np.float64))
        d = np.atleast_2d(np.asarray(directions, dtype=np.float64))
        d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)
        n = len(o)
        reach = np.broadcast_to(np.asarray(max_dist, dtype=np.float64), (n,)).copy()
        lo = -reach if both_ways else np.zeros(n)
        if self.backend == "bvh":
            t, face, bary = self._bvh_rays(o, d, lo, reach, both_ways)
        elif self.backend == "embree":
            t, face, bary = self.rays.nearest(o, d, lo, reach)
        else:
            parts = _in_parts(lambda a, b: self.tree.ray_nearest(o[a:b], d[a:b], lo[a:b], reach[a:b]), n)
            t, face, bary = (np.concatenate(x) for x in zip(*parts))
        hit = np.isfinite(t)
        point = np.where(hit[:, None], o + np.nan_to_num(t)[:, None] * d, np.nan)
        return RayHits(hit, t, face, point, bary)

    # --- Blender BVH backend -------------------------------------------------------------------
    # Blender's answers as it gives them (float32 inside; at a tie, whichever face its search meets
    # first), so that every figure made with it stays as it was.
    def _bvh_closest(self, points):
        found = [self.bvh.find_nearest(p) for p in points.tolist()]
        loc = np.array([f[0] if f[0] is not None else (np.nan,) * 3 for f in found], dtype=np.float64)
        face = np.array([f[2] if f[2] is not None else 0 for f in found], dtype=np.int64)
        return loc, face, np.linalg.norm(loc - points, axis=1)

    def _bvh_rays(self, o, d, lo, reach, both_ways):
        n = len(o)
        t = np.full(n, np.inf)
        face = np.zeros(n, np.int64)
        cast = self.bvh.ray_cast
        for sign in ((1.0, -1.0) if both_ways else (1.0,)):
            hits = [cast(a, b, r) for a, b, r in zip(o.tolist(), (sign * d).tolist(), reach.tolist())]
            dist = np.array([h[3] if h[3] is not None else np.inf for h in hits])
            idx = np.array([h[2] if h[2] is not None else 0 for h in hits], dtype=np.int64)
            better = dist < np.abs(t)
            t[better], face[better] = sign * dist[better], idx[better]
        hit = np.isfinite(t)
        t = np.where(hit, t, np.nan)
        point = np.where(hit[:, None], o + np.nan_to_num(t)[:, None] * d, np.nan)
        a, b, c = self._tri(face)
        bary = np.where(hit[:, None], barycentric(np.nan_to_num(point), a, b, c), 0.0)
        return t, face, bary
