"""Nearest-surface queries and ray casts on a triangle mesh, exact: scipy kd-trees, or Blender's BVH if asked.

Triangles are grouped by size; each group has a kd-tree of centroids and the largest centroid-to-
corner radius R of its triangles. A triangle whose centroid is D from a point has no point nearer
than D - R, which bounds every search so the answers are exact, not approximate.
All coordinates are the mesh's own frame and unit.
"""

import dataclasses

import numpy as np
from scipy.spatial import cKDTree

from ..tol import EXACT, TINY


def closest_on_triangles(p, a, b, c):
    """Closest points (n,3) on triangles (a,b,c) to points p, and their barycentric coords (n,3)."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = np.einsum("ij,ij->i", ab, ap), np.einsum("ij,ij->i", ac, ap)
    bp = p - b
    d3, d4 = np.einsum("ij,ij->i", ab, bp), np.einsum("ij,ij->i", ac, bp)
    cp = p - c
    d5, d6 = np.einsum("ij,ij->i", ab, cp), np.einsum("ij,ij->i", ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    n = len(p)
    bary = np.zeros((n, 3))
    done = np.zeros(n, bool)

    def put(mask, u, v, w):
        m = mask & ~done
        bary[m, 0], bary[m, 1], bary[m, 2] = u[m] if np.ndim(u) else u, v[m] if np.ndim(v) else v, w[m] if np.ndim(w) else w
        done[m] = True

    one, zero = np.ones(n), np.zeros(n)
    put((d1 <= 0) & (d2 <= 0), one, zero, zero)                        # vertex a
    put((d3 >= 0) & (d4 <= d3), zero, one, zero)                       # vertex b
    put((d6 >= 0) & (d5 <= d6), zero, zero, one)                       # vertex c
    with np.errstate(divide="ignore", invalid="ignore"):
        s = d1 / (d1 - d3)
        put((vc <= 0) & (d1 >= 0) & (d3 <= 0), 1 - s, s, zero)           # edge ab
        s = d2 / (d2 - d6)
        put((vb <= 0) & (d2 >= 0) & (d6 <= 0), 1 - s, zero, s)           # edge ac
        s = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        put((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), zero, 1 - s, s)  # edge bc
        denom = va + vb + vc
        v_, w_ = vb / denom, vc / denom
        put(np.ones(n, bool), 1 - v_ - w_, v_, w_)                       # inside
    bary = np.nan_to_num(bary, nan=1.0 / 3.0)
    q = bary[:, :1] * a + bary[:, 1:2] * b + bary[:, 2:] * c
    return q, bary


def ray_triangles(o, d, a, b, c, eps=TINY):
    """Moller-Trumbore: (hit (n,), t (n,), u (n,), v (n,)) of rays o + t d against triangles (a,b,c), any t."""
    e1, e2 = b - a, c - a
    pvec = np.cross(d, e2)
    det = np.einsum("ij,ij->i", e1, pvec)
    ok = np.abs(det) > eps * np.maximum(np.linalg.norm(e1, axis=1) * np.linalg.norm(e2, axis=1), 1e-300)
    inv = np.divide(1.0, det, out=np.zeros_like(det), where=ok)
    tvec = o - a
    u = np.einsum("ij,ij->i", tvec, pvec) * inv
    qvec = np.cross(tvec, e1)
    v = np.einsum("ij,ij->i", d, qvec) * inv
    t = np.einsum("ij,ij->i", e2, qvec) * inv
    tol = 1e-9
    hit = ok & (u >= -tol) & (v >= -tol) & (u + v <= 1 + tol)
    return hit, t, u, v


@dataclasses.dataclass
class RayHits:
    """Nearest hits of rays: hit mask, signed distance t along the unit direction, face, point, barycentrics."""
    hit: np.ndarray
    t: np.ndarray
    face: np.ndarray
    point: np.ndarray
    bary: np.ndarray


def _candidates(tree, points, radius, k=16):
    """(query index, tree index) of every tree point within radius (per query) of each point.

    A fixed-k query answers most points at numpy speed; the few with more than k neighbours in
    their radius are completed by a ball query, so the result is exact.
    """
    radius = np.broadcast_to(radius, (len(points),))
    k = min(k, tree.n)
    dist, nn = tree.query(points, k=k, distance_upper_bound=float(radius.max()))
    dist, nn = dist.reshape(len(points), k), nn.reshape(len(points), k)
    inside = dist <= radius[:, None]
    qi, col = np.nonzero(inside)
    pairs_q, pairs_t = [qi], [nn[qi, col]]
    full = np.flatnonzero(inside[:, -1]) if k < tree.n else np.zeros(0, int)
    if len(full):
        lists = tree.query_ball_point(points[full], r=radius[full], return_sorted=False)
        lens = np.fromiter((len(x) for x in lists), dtype=np.int64, count=len(full))
        extra_q = np.repeat(full, lens)
        extra_t = np.fromiter((f for x in lists for f in x), dtype=np.int64, count=int(lens.sum()))
        # replace the truncated answers of those points
        keep = ~np.isin(qi, full)
        pairs_q, pairs_t = [qi[keep], extra_q], [nn[qi, col][keep], extra_t]
    return np.concatenate(pairs_q), np.concatenate(pairs_t)


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

    backend "numpy" (the default) is the exact kd-tree method of this module; "bvh" uses Blender's C
    BVH tree (mathutils, inside Blender or beside the bpy module) with a loop over queries. The
    caller chooses: nothing here imports Blender unless asked to. Both give the same answers (tested).
    """

    def __init__(self, verts, tris, backend="numpy"):
        self.verts = np.asarray(verts, dtype=np.float64)
        self.tris = np.asarray(tris, dtype=np.int64)
        if backend not in ("numpy", "bvh"):
            raise ValueError(f"unknown spatial backend {backend!r} (numpy or bvh)")
        self.backend = backend
        if backend == "bvh":
            bvh = bvh_class()
            if bvh is None:
                raise ImportError("the bvh backend needs mathutils (Blender or the bpy module)")
            self.bvh = bvh.FromPolygons(self.verts.tolist(), self.tris.tolist(), all_triangles=True)
            return
        corners = self.verts[self.tris]
        self.centroids = corners.mean(axis=1)
        radius = np.linalg.norm(corners - self.centroids[:, None], axis=2).max(axis=1)
        # size groups: each at most 3x the smallest radius of the group
        base = max(np.median(radius), TINY)
        level = np.floor(np.log(np.maximum(radius, base) / base) / np.log(3.0)).astype(int)
        self.vertex_tree = cKDTree(self.verts[np.unique(self.tris)])
        self.groups = []
        for g in np.unique(level):
            idx = np.flatnonzero(level == g)
            self.groups.append((idx, cKDTree(self.centroids[idx]), float(radius[idx].max())))

    def _tri(self, faces):
        c = self.verts[self.tris[faces]]
        return c[:, 0], c[:, 1], c[:, 2]

    def closest_points(self, points):
        """(closest (n,3), face (n,), dist (n,)) on the mesh for query points (n,3)."""
        points = np.atleast_2d(np.asarray(points, dtype=np.float64))
        if self.backend == "bvh":
            return self._bvh_closest(points)
        n = len(points)
        # a corner of the mesh bounds the distance from above; then every triangle that could be
        # nearer has its centroid within that bound + its group's radius: test exactly those
        bound, _ = self.vertex_tree.query(points)
        best_d = np.full(n, np.inf)
        best_f = np.zeros(n, np.int64)
        best_q = np.zeros((n, 3))
        for idx, tree, R in self.groups:
            pid, local = _candidates(tree, points, bound + R + EXACT * max(R, 1e-300))
            if len(pid) == 0:
                continue
            faces = idx[local]
            a, b, c = self._tri(faces)
            q, _ = closest_on_triangles(points[pid], a, b, c)
            d = np.linalg.norm(q - points[pid], axis=1)
            order = np.lexsort((d, pid))
            first = order[np.r_[True, pid[order][1:] != pid[order][:-1]]]
            p_, d_ = pid[first], d[first]
            better = d_ < best_d[p_]
            sel = p_[better]
            best_d[sel], best_f[sel], best_q[sel] = d_[better], faces[first][better], q[first][better]
        return best_q, best_f, best_d

    def ray_cast(self, origins, directions, max_dist, both_ways=True):
        """Nearest hits within max_dist (scalar or (n,)) along unit directions (both ways if asked)."""
        o = np.atleast_2d(np.asarray(origins, dtype=np.float64))
        d = np.atleast_2d(np.asarray(directions, dtype=np.float64))
        d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)
        n = len(o)
        reach = np.broadcast_to(np.asarray(max_dist, dtype=np.float64), (n,)).copy()
        if self.backend == "bvh":
            return self._bvh_rays(o, d, reach, both_ways)
        best_t = np.full(n, np.inf)
        best_f = np.zeros(n, np.int64)
        best_uv = np.zeros((n, 2))
        lo = -reach if both_ways else np.zeros(n)
        for idx, tree, R in self.groups:
            step = 2.0 * R
            # samples along each segment so that every point of it is within R of a sample
            count = np.maximum(np.ceil((reach - lo) / step).astype(int), 0) + 1
            ray_id = np.repeat(np.arange(n), count)
            first = np.repeat(np.cumsum(count) - count, count)
            s = lo[ray_id] + (np.arange(len(ray_id)) - first) * np.minimum(
                step, (reach - lo)[ray_id] / np.maximum(count[ray_id] - 1, 1))
            samples = o[ray_id] + s[:, None] * d[ray_id]
            # a triangle meets the ray within `step/2` of a sample only if its centroid is within step/2 + R
            sid, local = _candidates(tree, samples, np.full(len(samples), 0.5 * step + R + EXACT * max(R, 1e-300)))
            if len(sid) == 0:
                continue
            cand_ray, cand_face = ray_id[sid], idx[local]
            key = np.unique(cand_ray * len(self.tris) + cand_face)
            cand_ray, cand_face = key // len(self.tris), key % len(self.tris)
            a, b, c = self._tri(cand_face)
            hit, t, u, v = ray_triangles(o[cand_ray], d[cand_ray], a, b, c)
            hit &= (t <= reach[cand_ray]) & (t >= lo[cand_ray])
            if not hit.any():
                continue
            cr, cf, ct, cu, cv = cand_ray[hit], cand_face[hit], t[hit], u[hit], v[hit]
            order = np.lexsort((np.abs(ct), cr))
            cr, cf, ct, cu, cv = cr[order], cf[order], ct[order], cu[order], cv[order]
            firsts = np.r_[True, cr[1:] != cr[:-1]]
            cr, cf, ct, cu, cv = cr[firsts], cf[firsts], ct[firsts], cu[firsts], cv[firsts]
            better = np.abs(ct) < np.abs(best_t[cr])
            r = cr[better]
            best_t[r], best_f[r] = ct[better], cf[better]
            best_uv[r] = np.c_[cu[better], cv[better]]
        hit = np.isfinite(best_t)
        bary = np.c_[1 - best_uv.sum(axis=1), best_uv]
        bary[~hit] = 0
        t = np.where(hit, best_t, np.nan)
        point = np.where(hit[:, None], o + np.nan_to_num(t)[:, None] * d, np.nan)
        return RayHits(hit, t, best_f, point, bary)

    # --- Blender BVH backend -------------------------------------------------------------------
    def _bvh_closest(self, points):
        found = [self.bvh.find_nearest(p) for p in points.tolist()]
        loc = np.array([f[0] if f[0] is not None else (np.nan,) * 3 for f in found], dtype=np.float64)
        face = np.array([f[2] if f[2] is not None else 0 for f in found], dtype=np.int64)
        return loc, face, np.linalg.norm(loc - points, axis=1)

    def _bvh_rays(self, o, d, reach, both_ways):
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
        return RayHits(hit, t, face, point, bary)
