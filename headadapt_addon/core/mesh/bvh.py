"""A bounding-volume hierarchy of a triangle mesh in plain numpy, walked by many queries at once.

The tree is implicit and complete: 2^depth leaves of at most `leaf_size` triangles each, made by one
sort of the triangles' centroids along a Morton curve (a linear BVH: each node holds a run of that
order, cut in the middle; 4x faster to build on a 2M-triangle scan than median splits, its queries
as fast); node j of level l covers leaves j 2^(depth-l) .. (j+1) 2^(depth-l) - 1: a node is its level
and its number, its box the union of its children's. Every triangle's
box is widened by `pad` (EXACT x the mesh's size) and by the slack of the ray test (RAY_TOL of its
barycentrics), so neither rounding nor that slack ever drops a triangle that can answer.

A query walks the tree level by level for all queries at once (breadth first): the (query, node)
pairs still alive are split into their two children and kept where the child's box can hold an
answer (a ray's segment crosses it; a box nearer a point than a distance the point surely has).
The triangles of the leaves reached are then tested exactly (Python loops per level, never per
query or triangle). Answers are exact, with triangles.py's rule at a tie.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ..tol import EXACT, TINY
from .triangles import RAY_TOL, closest_choice, closest_on_segments, finite, ray_choice


def _spread_bits(x):
    """The 21 low bits of each uint64 moved to every third bit (a Morton code's one axis)."""
    x = x & np.uint64(0x1FFFFF)
    for shift, mask in ((32, 0x1F00000000FFFF), (16, 0x1F0000FF0000FF), (8, 0x100F00F00F00F00F),
                        (4, 0x10C30C30C30C30C3), (2, 0x1249249249249249)):
        x = (x | (x << np.uint64(shift))) & np.uint64(mask)
    return x


def _morton_order(cent):
    """Slots -> triangles: the centroids (three coordinate arrays) sorted along a Morton (Z-order)
    curve on a cubic 2^21 grid over their box, so that each run of slots is a compact cluster."""
    lo = np.array([c.min() if len(c) else 0.0 for c in cent])                       # (no triangles: no order)
    span = max(max((c.max() - lo[k] for k, c in enumerate(cent) if len(c)), default=0.0), 1e-300)
    code = np.zeros(len(cent[0]), np.uint64)
    for k, c in enumerate(cent):
        code |= _spread_bits(((c - lo[k]) * ((2 ** 21 - 1) / span)).astype(np.uint64)) << np.uint64(k)
    return np.argsort(code, kind="stable")


class TriangleBVH:
    """The tree of one triangle mesh (see the module): nearest ray hits and closest points, exact."""

    def __init__(self, verts, tris, leaf_size=4):
        leaf_size = max(int(leaf_size), 2)                              # so that no leaf is empty
        self.verts = verts = np.asarray(verts, dtype=np.float64)
        self.tris = tris = np.asarray(tris, dtype=np.int64)
        self.m = m = len(tris)
        # corners as coordinate arrays: xyz[k][j] is coordinate k of corner j of every triangle
        xyz = [[np.ascontiguousarray(verts[tris[:, j], k]) for j in range(3)] for k in range(3)]
        lo = np.array([min(c[0].min(), c[1].min(), c[2].min()) if m else 0.0 for c in xyz])
        hi = np.array([max(c[0].max(), c[1].max(), c[2].max()) if m else 0.0 for c in xyz])
        self.scale = float(np.linalg.norm(hi - lo)) or 1.0
        self.pad = EXACT * self.scale
        self.depth = int(np.ceil(np.log2(max(m / leaf_size, 1.0))))
        leaves = 1 << self.depth
        self.leaf_start = (np.arange(leaves + 1) * m) // leaves         # leaf k: slots leaf_start[k]..[k+1]-1
        order = _morton_order([(c[0] + c[1] + c[2]) / 3.0 for c in xyz])
        self.face = order                                               # tree slot -> face of the mesh
        xyz = [[x[order] for x in c] for c in xyz]                      # in slot order from here on
        boxes = [None] * (self.depth + 1)                               # per level (root first): (lo (3,k), hi (3,k))
        if m:
            # a triangle's box, widened by pad and by the most a ray hit may lie off it (RAY_TOL of its
            # barycentrics, so a box never drops a hit the exact test accepts)
            slack = self.pad + 2 * RAY_TOL * np.sqrt(np.maximum(np.maximum(
                sum((c[1] - c[0]) ** 2 for c in xyz), sum((c[2] - c[1]) ** 2 for c in xyz)),
                sum((c[0] - c[2]) ** 2 for c in xyz)))
            starts = self.leaf_start[:-1]
            boxes[-1] = tuple(np.stack([f.reduceat(f(f(c[0], c[1]), c[2]) + sign * slack, starts) for c in xyz])
                              for f, sign in ((np.minimum, -1.0), (np.maximum, 1.0)))
        else:
            boxes[-1] = (np.full((3, 1), np.inf), np.full((3, 1), -np.inf))
        for level in range(self.depth - 1, -1, -1):
            blo, bhi = boxes[level + 1]
            boxes[level] = (np.minimum(blo[:, 0::2], blo[:, 1::2]), np.maximum(bhi[:, 0::2], bhi[:, 1::2]))
        self.boxes = [tuple(np.ascontiguousarray(x[k]) for x in b for k in range(3)) for b in boxes]
        # per slot: a corner, the two edges from it, their cross product, the Moller-Trumbore threshold
        self.a = a = tuple(c[0] for c in xyz)
        self.e1 = e1 = tuple(c[1] - ak for c, ak in zip(xyz, a))
        self.e2 = e2 = tuple(c[2] - ak for c, ak in zip(xyz, a))
        self.n = (e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2], e1[0] * e2[1] - e1[1] * e2[0])
        self.e11 = e1[0] * e1[0] + e1[1] * e1[1] + e1[2] * e1[2]
        self.e22 = e2[0] * e2[0] + e2[1] * e2[1] + e2[2] * e2[2]
        self.det_min = TINY * np.maximum(np.sqrt(self.e11 * self.e22), 1e-300)
        n2 = self.n[0] * self.n[0] + self.n[1] * self.n[1] + self.n[2] * self.n[2]
        self.flat = n2 <= TINY * TINY * self.e11 * self.e22           # as flat_triangles: taken as 3 segments
        self._near = self._vtree = None                                 # closest-point data (_spheres, vertex_tree)

    def _spheres(self, slot):
        """Bounding spheres (centre: 3 arrays, radius) of slots: made for those asked if under a quarter
        of the mesh (a 1M-vertex scan's clicks, its skin's distances), else for all once and kept."""
        if self._near is None and len(slot) < self.m // 4:
            return self._make_spheres(slot)
        if self._near is None:
            self._near = self._make_spheres(slice(None))
        return tuple(x[slot] for x in self._near[0]), self._near[1][slot]

    def _make_spheres(self, slot):
        e1, e2 = [x[slot] for x in self.e1], [x[slot] for x in self.e2]
        third = [(b + c) / 3.0 for b, c in zip(e1, e2)]       # centroid g - a; b - g = e1 - third, ...
        centre = tuple(ak[slot] + t for ak, t in zip(self.a, third))
        r2 = [sum(t ** 2 for t in third)] + [sum((x - t) ** 2 for x, t in zip(e, third)) for e in (e1, e2)]
        return centre, np.sqrt(np.maximum(np.maximum(r2[0], r2[1]), r2[2])) + self.pad

    def vertex_tree(self):
        """A kd-tree of the vertices in use (the nearest one's distance bounds a point's), of all `verts` if
        all are (ScanSide shares it). Unbalanced, loose: 2x faster to build, 10x to query far inside."""
        if self._vtree is None:
            used = np.bincount(self.tris.ravel(), minlength=len(self.verts)) > 0
            self._vtree = cKDTree(self.verts[used] if not used.all() else self.verts, balanced_tree=False,
                                  compact_nodes=False)
        return self._vtree

    # --- walking the tree -------------------------------------------------------------------------
    def _walk(self, count, keep_fn, stride=2):
        """(owner, leaf) pairs reached from the root, owners 0..count-1 in increasing order, keeping at
        each level the pairs keep_fn(owner, level, node) says can hold an answer. `stride` levels a step
        (a node's grandchildren at once): a box holds its descendants' (the tests are monotone in its
        bounds), so the leaves kept are the level-by-level walk's, at 0.85 of its time on a head's rays."""
        owner, node = np.arange(count), np.zeros(count, np.int64)
        keep, level = keep_fn(owner, 0, node), 0
        for deeper in [min(k, self.depth) for k in range(stride, self.depth + stride, stride)]:
            fan = 1 << (deeper - level)
            owner, node = np.repeat(owner[keep], fan), (fan * node[keep][:, None] + np.arange(fan)).ravel()
            keep, level = keep_fn(owner, deeper, node), deeper
        return owner[keep], node[keep]

    def _slots(self, owner, leaf):
        """(owner, slot) of every triangle in the given leaves (owner order kept)."""
        start = self.leaf_start[leaf]
        count = self.leaf_start[leaf + 1] - start
        owner = np.repeat(owner, count)
        first = np.repeat(np.cumsum(count) - count, count)
        return owner, np.arange(len(owner)) - first + np.repeat(start, count)

    def ray_candidates(self, o, d, t0, t1):
        """(ray, slot), rays in order, of the triangles whose leaf box the segment o + t d, t0 <= t <= t1,
        meets (d need not be unit; a ray with t0 > t1 meets nothing)."""
        # a zero component: a huge finite slope, never nan (a ray exactly on a box's face plane is
        # then kept on one side only; no hit lies there, every box being wider than its triangles)
        inv = 1.0 / np.where(d == 0.0, 1e-300, d)
        ox, oy, oz = (np.ascontiguousarray(o[:, k]) for k in range(3))
        ix, iy, iz = (np.ascontiguousarray(inv[:, k]) for k in range(3))

        def keep(ray, level, node):
            lx, ly, lz, hx, hy, hz = self.boxes[level]
            enter, leave = t0[ray], t1[ray]
            for lo_, hi_, oc, ic in ((lx, hx, ox, ix), (ly, hy, oy, iy), (lz, hz, oz, iz)):
                oc, ic = oc[ray], ic[ray]
                ta, tb = (lo_[node] - oc) * ic, (hi_[node] - oc) * ic
                enter = np.maximum(enter, np.minimum(ta, tb))
                leave = np.minimum(leave, np.maximum(ta, tb))
            return enter <= leave

        return self._slots(*self._walk(len(o), keep))

    def _box_gap2(self, p, owner, level, node):
        """Squared distance from points p[owner] to the boxes of nodes of a level (0 inside)."""
        lx, ly, lz, hx, hy, hz = self.boxes[level]
        d2 = np.zeros(len(owner))
        for k, (lo_, hi_) in enumerate(((lx, hx), (ly, hy), (lz, hz))):
            pc = p[k][owner]
            gap = np.maximum(np.maximum(lo_[node] - pc, pc - hi_[node]), 0.0)
            d2 += gap * gap
        return d2

    # --- exact tests --------------------------------------------------------------------------
    def ray_test(self, o, d, ray, slot):
        """A prefilter of the exact ray test (triangles.ray_triangles) with the triangles' edges and
        normal computed once: hit (k,) and t (k,) of rays (o, d)[ray] against slots, any t, with twice
        its slack and half its parallel threshold, so that it never misses a hit the exact test has."""
        ax, ay, az = (x[slot] for x in self.a)
        nx, ny, nz = (x[slot] for x in self.n)
        dx, dy, dz = (d[ray, k] for k in range(3))
        tx, ty, tz = o[ray, 0] - ax, o[ray, 1] - ay, o[ray, 2] - az          # o - a
        det = -(dx * nx + dy * ny + dz * nz)                                   # e1 . (d x e2)
        ok = np.abs(det) > 0.5 * self.det_min[slot]
        inv = np.divide(1.0, det, out=np.zeros_like(det), where=ok)
        wx, wy, wz = ty * dz - tz * dy, tz * dx - tx * dz, tx * dy - ty * dx  # (o - a) x d
        e1x, e1y, e1z = (x[slot] for x in self.e1)
        e2x, e2y, e2z = (x[slot] for x in self.e2)
        u = (e2x * wx + e2y * wy + e2z * wz) * inv
        v = -(e1x * wx + e1y * wy + e1z * wz) * inv
        t = (tx * nx + ty * ny + tz * nz) * inv
        hit = ok & (u >= -2 * RAY_TOL) & (v >= -2 * RAY_TOL) & (u + v <= 1 + 2 * RAY_TOL)
        return hit, t

    def point_test(self, p, owner, slot):
        """Distances from points p[owner] to slots (Ericson's regions, as triangles.closest_on_triangles,
        with the edges and their dot products computed once; equal to it but for rounding)."""
        ax, ay, az = (x[slot] for x in self.a)
        bx, by, bz = (x[slot] for x in self.e1)
        cx, cy, cz = (x[slot] for x in self.e2)
        px, py, pz = p[0][owner] - ax, p[1][owner] - ay, p[2][owner] - az     # p - a
        d1 = bx * px + by * py + bz * pz                                       # ab . ap
        d2 = cx * px + cy * py + cz * pz                                       # ac . ap
        e11, e12, e22 = self.e11[slot], bx * cx + by * cy + bz * cz, self.e22[slot]
        d3, d4, d5, d6 = d1 - e11, d2 - e12, d1 - e12, d2 - e22               # ab.bp, ac.bp, ab.cp, ac.cp
        va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
        with np.errstate(divide="ignore", invalid="ignore"):
            denom = va + vb + vc
            v, w = vb / denom, vc / denom                                     # inside
            # the regions from last to first priority, so the first that holds is the one left
            s = (d4 - d3) / ((d4 - d3) + (d5 - d6))
            m = (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0)                  # edge bc
            v, w = np.where(m, 1 - s, v), np.where(m, s, w)
            s = d2 / (d2 - d6)
            m = (vb <= 0) & (d2 >= 0) & (d6 <= 0)                             # edge ac
            v, w = np.where(m, 0.0, v), np.where(m, s, w)
            s = d1 / (d1 - d3)
            m = (vc <= 0) & (d1 >= 0) & (d3 <= 0)                             # edge ab
            v, w = np.where(m, s, v), np.where(m, 0.0, w)
        m = (d6 >= 0) & (d5 <= d6)                                            # vertex c
        v, w = np.where(m, 0.0, v), np.where(m, 1.0, w)
        m = (d3 >= 0) & (d4 <= d3)                                            # vertex b
        v, w = np.where(m, 1.0, v), np.where(m, 0.0, w)
        m = (d1 <= 0) & (d2 <= 0)                                             # vertex a
        v, w = np.where(m, 0.0, v), np.where(m, 0.0, w)
        v, w = finite(v), finite(w)                                           # flat: redone below
        rx, ry, rz = v * bx + w * cx, v * by + w * cy, v * bz + w * cz        # closest point - a
        dist = np.sqrt((px - rx) ** 2 + (py - ry) ** 2 + (pz - rz) ** 2)
        flat = np.flatnonzero(self.flat[slot])
        if len(flat):
            a, e1, e2 = (np.column_stack([x[flat] for x in xyz]) for xyz in ((ax, ay, az), (bx, by, bz), (cx, cy, cz)))
            pp = np.column_stack([k[owner[flat]] for k in p])
            dist[flat] = np.linalg.norm(closest_on_segments(pp, a, a + e1, a + e2)[0] - pp, axis=1)
        return dist

    def sphere_gap(self, p, owner, slot):
        """A lower bound of the distance from points p[owner] to slots: to their bounding spheres."""
        (cx, cy, cz), radius = self._spheres(slot)
        return np.sqrt((p[0][owner] - cx) ** 2 + (p[1][owner] - cy) ** 2 + (p[2][owner] - cz) ** 2) - radius

    # --- queries ----------------------------------------------------------------------------------
    def ray_nearest(self, o, d, lo, hi, shells=(4.0,)):
        """Nearest hit by |t| of each ray o + t d (d unit) with lo <= t <= hi: (t (nan: none), face, bary),
        as triangles.ray_choice picks it among every face the exact test hits.

        Searched in shells: first |t| <= shells[0] x the mesh's median edge, then the rays that hit
        nothing there go on to the next shell and finally to their whole segment; a hit inside a shell
        is the nearest, since every hit nearer was a candidate."""
        n = len(o)
        t_out, f_out, bary_out = np.full(n, np.nan), np.zeros(n, np.int64), np.zeros((n, 3))
        if not self.m or not n:
            return t_out, f_out, bary_out
        todo = np.arange(n)
        for radius in [k * self.median_edge() for k in shells] + [np.inf]:
            if not len(todo):
                break
            oo, dd = o[todo], d[todo]
            a, b = np.maximum(lo[todo], -radius), np.minimum(hi[todo], radius)
            ray, slot = self.ray_candidates(oo, dd, a, b)
            hit, t = self.ray_test(oo, dd, ray, slot)
            hit &= (t >= a[ray] - self.pad) & (t <= b[ray] + self.pad)
            rays, t, face, bary = ray_choice(oo, dd, a, b, ray[hit], self.face[slot[hit]], self.verts, self.tris)
            done = todo[rays]
            t_out[done], f_out[done], bary_out[done] = t, face, bary
            left = np.ones(len(todo), bool)
            left[rays] = False
            todo = todo[left]
        return t_out, f_out, bary_out

    def closest(self, points):
        """(closest point, face, distance) on the mesh of each point, as triangles.closest_choice picks it.

        The nearest vertex in use (vertex_tree) bounds each point's distance; the walk finds every leaf
        box within that bound, and of their triangles those whose bounding sphere is within it are
        measured; the ones within `pad` of the least go to closest_choice. (Any sound bound gives these
        candidates: this tree has half the points of the triangle centres', and ScanSide needs it.)"""
        n = len(points)
        out_q, out_f, out_d = np.full((n, 3), np.nan), np.zeros(n, np.int64), np.full(n, np.inf)
        if not self.m or not n:
            return out_q, out_f, out_d
        p = tuple(np.ascontiguousarray(points[:, k]) for k in range(3))
        bound = self.vertex_tree().query(points)[0] + self.pad
        b2 = bound * bound
        owner, leaf = self._walk(n, lambda q, level, nd: self._box_gap2(p, q, level, nd) <= b2[q])
        q2, s2 = self._slots(owner, leaf)
        near = self.sphere_gap(p, q2, s2) <= bound[q2]
        allq, slots = q2[near], s2[near]                                # owners in order
        dist = self.point_test(p, allq, slots)
        # every candidate within pad of its point's least distance, by point
        starts = np.flatnonzero(np.concatenate([[True], allq[1:] != allq[:-1]]))
        least = np.repeat(np.minimum.reduceat(dist, starts), np.diff(np.append(starts, len(allq))))
        keep = dist <= least + self.pad
        who, q, face, d = closest_choice(points, allq[keep], self.face[slots[keep]], self.verts, self.tris)
        out_q[who], out_f[who], out_d[who] = q, face, d
        return out_q, out_f, out_d

    def median_edge(self):
        if not hasattr(self, "_edge"):                                  # |e1|: the first edges' lengths
            self._edge = float(np.median(np.sqrt(self.e11))) if self.m else 0.0
        return self._edge
