"""Nearest-surface queries and ray casts on a triangle mesh, exact, with scipy kd-trees.

Triangles are grouped by size; each group has a kd-tree of centroids and the largest centroid-to-
corner radius R of its triangles. A triangle whose centroid is D from a point has no point nearer
than D - R, which bounds every search so the answers are exact, not approximate.
All coordinates are the mesh's own frame and unit.
"""

import dataclasses

import numpy as np
from scipy.spatial import cKDTree


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


def ray_triangles(o, d, a, b, c, eps=1e-12):
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


class MeshQuery:
    """Exact closest-point and ray queries on one triangle mesh (built once, reused)."""

    def __init__(self, verts, tris):
        self.verts = np.asarray(verts, dtype=np.float64)
        self.tris = np.asarray(tris, dtype=np.int64)
        corners = self.verts[self.tris]
        self.centroids = corners.mean(axis=1)
        radius = np.linalg.norm(corners - self.centroids[:, None], axis=2).max(axis=1)
        # size groups: each at most 3x the smallest radius of the group
        base = max(np.median(radius), 1e-12)
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
        n = len(points)
        # a corner of the mesh bounds the distance from above; then every triangle that could be
        # nearer has its centroid within that bound + its group's radius: test exactly those
        bound, _ = self.vertex_tree.query(points)
        best_d = np.full(n, np.inf)
        best_f = np.zeros(n, np.int64)
        best_q = np.zeros((n, 3))
        for idx, tree, R in self.groups:
            lists = tree.query_ball_point(points, r=bound + R + 1e-12, return_sorted=False)
            lens = np.fromiter((len(x) for x in lists), dtype=np.int64, count=n)
            if lens.sum() == 0:
                continue
            pid = np.repeat(np.arange(n), lens)
            faces = idx[np.fromiter((f for x in lists for f in x), dtype=np.int64, count=int(lens.sum()))]
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
            pairs = tree.query_ball_point(samples, r=0.5 * step + R + 1e-12 * max(R, 1.0), return_sorted=False)
            lens = np.fromiter((len(p) for p in pairs), dtype=np.int64, count=len(pairs))
            if lens.sum() == 0:
                continue
            cand_ray = np.repeat(ray_id, lens)
            cand_face = idx[np.fromiter((f for p in pairs for f in p), dtype=np.int64, count=int(lens.sum()))]
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
