"""Fast generalized winding numbers of many points w.r.t. one triangle mesh, equal to the brute force.

The generalized winding number w(q) (Jacobson et al. 2013; inside.winding_numbers sums it over
every triangle) is the signed solid angle of a mesh at q over 4 pi: about 1 inside a closed
outward-oriented surface, 0 outside, in between near the holes of an open one. The brute-force
sum costs (points x triangles) arctangents, and anatomy.transfer asks it for thousands of points.

Here the mesh is first closed: every loop of its border (cut where the border passes a vertex
twice) gets a cap, the loop's polygon cut into triangles (split at its middle vertex,
recursively; no new vertices), turned so that mesh + caps is a closed surface. At a point q off that surface

    w_mesh(q) = W(q) - w_caps(q)

exactly, where W, the winding number of the closed surface, is an integer: the signed count of
its triangles that a ray from q crosses (+1 where it leaves, -1 where it enters). That count
costs a few tests per point: the rays run along a fixed, generic direction, and a grid over the
plane across it lists the triangles whose shadow covers each cell. The caps are summed exactly as
inside.winding_numbers sums the mesh; they have one triangle per border edge less two per loop:
54 on the template's skin against its 8,716 triangles, 536 on the skull against 4,512. On 3,000
points that is 15 ms against 1.2 s on the skin, about 10x less on the skull (its caps dominate).

The crossing test is robust: a point's side of an edge is computed from the edge's two vertices
in a fixed order (the lower index first), bit for bit the same in both triangles that share the
edge, so a ray through an edge is counted in exactly one of them. A point whose count rounding
could change (within rounding of a vertex's shadow, or of the surface: the turn into the ray's
frame itself rounds the coordinates) is summed by brute force. So the values are the brute force's up to rounding (1e-13 on the template's meshes):
an exact method, not an approximation (headless_tests/test_inside.py compares them).

A hierarchical fast winding number (Barill et al. 2018, a tree of triangle clusters with Taylor
expansions of the far ones) was tried first: about 3x faster than the brute force on these meshes
at an error of 2e-3 (second order, beta 2), against 10-80x here without error.
"""

import numpy as np

from .caps import border_edges, border_loops, cap_triangles
from .inside import solid_angles, winding_numbers

_EPS = np.finfo(np.float64).eps
# FastWinding(remember=True) keeps each cap triangle's term at the points of its last few queries
# (by their number): the next query with those points sums the kept terms again and computes only
# the points that moved and the caps whose corners moved
REMEMBER_SETS = 4                    # query sets kept, the largest (the transfer's visible skin) first
REMEMBER_MOST = 4_000_000            # terms kept per set at most (32 MB); a larger query is summed afresh


def _rotation():
    """A fixed rotation with no special axis: rays run along its third row (no edge, symmetry plane
    or grid of a mesh built in axis-aligned coordinates lies along it)."""
    axis = np.array([0.37, 0.61, 0.70])
    axis /= np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(0.97) * k + (1 - np.cos(0.97)) * k @ k


ROTATION = _rotation()


class FastWinding:
    """Winding numbers of points w.r.t. a triangle mesh (verts (n,3), tris (k,3)), equal to
    inside.winding_numbers up to rounding. Built once per mesh; refit(verts) for moved vertices
    (the same triangles: a deforming mesh keeps its caps, and its grid while no vertex has moved
    farther than `slack` since the grid was built; a larger slack means fewer rebuilds and more
    triangles tried per point). remember: keep the caps' terms at the last queries' points, for a
    caller that asks again at the same points while the mesh moves in places (the anatomy transfer
    asks at every visible skin vertex seven times). Any unit."""

    def __init__(self, verts, tris, slack=0.0, remember=False):
        self.tris = np.asarray(tris, dtype=np.int64).reshape(-1, 3)
        verts = np.asarray(verts, dtype=np.float64)
        self.n_verts = len(verts)
        self.cap = cap_triangles(border_loops(border_edges(self.tris)))
        closed = np.vstack([self.tris, self.cap])
        # each triangle of the closed surface by its corners in index order, and whether that order
        # turns the triangle's way (+1) or against it (-1)
        self.sorted = np.sort(closed, axis=1)
        a, b, c = closed.T
        even = ((a < b) & (b < c)) | ((b < c) & (c < a)) | ((c < a) & (a < b))
        self.parity = np.where(even, 1, -1).astype(np.int8)
        self.n_closed = len(closed)
        self.slack = slack
        self.remember = remember
        self._kept = {}                  # {number of points: (points, cap corners, (k, caps) terms)}
        self._grid_verts = None
        self.refit(verts)

    def refit(self, verts):
        """The same mesh with its vertices at `verts` (n,3) (the grid follows at the next query)."""
        verts = np.asarray(verts, dtype=np.float64)
        if verts.shape != (self.n_verts, 3):
            raise ValueError(f"refit with vertices of shape {verts.shape}, the mesh has {self.n_verts}")
        self.verts = verts
        self._ready = False
        return self

    def _prepare(self):
        """Rotated corners of every triangle; the grid again if a vertex left its slack."""
        if self._ready:
            return
        rotated = self.verts @ ROTATION.T
        self.corners = rotated[self.sorted].reshape(-1, 9)            # (m,9): x0 y0 z0 x1 ...
        self._reach = float(np.abs(self.corners).max(initial=0.0))    # the largest coordinate
        if self._grid_verts is None or np.einsum("ij,ij->i", rotated - self._grid_verts,
                                                 rotated - self._grid_verts).max(initial=0.0) > self._slack ** 2:
            self._build_grid(rotated)
        self._ready = True

    def _build_grid(self, rotated):
        self._grid_verts = rotated
        c = self.corners.reshape(-1, 3, 3)[:, :, :2]                   # (m,3,2): the shadows
        lo, hi = c.min(axis=1), c.max(axis=1)
        if not self.n_closed:
            lo, hi = np.zeros((0, 2)), np.zeros((0, 2))
        extent = float((hi.max(axis=0, initial=0.0) - lo.min(axis=0, initial=0.0)).max())
        span = (hi - lo)[: len(self.tris)].max(axis=1)
        cell = max(float(np.median(span)) if len(span) else extent, extent / 2048.0, 1e-300)
        self._slack = float(self.slack)
        # each shadow's box grown by the slack: it holds the shadow until a vertex moves farther
        lo, hi = lo - self._slack, hi + self._slack
        self.box = np.hstack([lo, hi])
        origin = lo.min(axis=0) if len(lo) else np.zeros(2)
        while True:
            i0 = np.floor((lo - origin) / cell).astype(np.int64)
            i1 = np.floor((hi - origin) / cell).astype(np.int64)
            shape = i1.max(axis=0) + 1 if len(lo) else np.ones(2, np.int64)
            width = i1 - i0 + 1
            counts = width[:, 0] * width[:, 1]
            # large triangles (caps over wide holes) in many cells: coarser cells, a shorter list
            if counts.sum() <= 32 * self.n_closed + 4096:
                break
            cell *= 1.5
        tri = np.repeat(np.arange(self.n_closed), counts)
        local = np.arange(len(tri)) - np.repeat(np.cumsum(counts) - counts, counts)
        key = (i0[tri, 0] + local % width[tri, 0]) * shape[1] + i0[tri, 1] + local // width[tri, 0]
        # a stable sort of the cell ids (a radix sort when they fit 16 bits: 10x quicker)
        order = np.argsort(key.astype(np.uint16) if shape[0] * shape[1] <= 65536 else key, kind="stable")
        self.cell, self.shape, self.origin = cell, (int(shape[0]), int(shape[1])), origin
        self.cell_tris = tri[order]
        self.start = np.searchsorted(key[order], np.arange(shape[0] * shape[1] + 1))

    def crossings(self, points, chunk=65536):
        """(W (k,) int, unsure (k,) bool): the winding number of mesh + caps at each point, the signed
        count of triangles a ray crosses; unsure where rounding could change the count."""
        points = np.atleast_2d(np.asarray(points, dtype=np.float64))
        if len(points) > chunk:
            parts = [self.crossings(points[i:i + chunk], chunk) for i in range(0, len(points), chunk)]
            return np.concatenate([w for w, _ in parts]), np.concatenate([u for _, u in parts])
        self._prepare()
        q = points @ ROTATION.T
        n = len(q)
        unsure = ~np.isfinite(q).all(axis=1)
        cx = np.floor((q[:, 0] - self.origin[0]) / self.cell)
        cy = np.floor((q[:, 1] - self.origin[1]) / self.cell)
        idx = np.flatnonzero(~unsure & (cx >= 0) & (cy >= 0) & (cx < self.shape[0]) & (cy < self.shape[1]))
        cid = cx[idx].astype(np.int64) * self.shape[1] + cy[idx].astype(np.int64)
        first, count = self.start[cid], self.start[cid + 1] - self.start[cid]
        pid = np.repeat(idx, count)
        t = self.cell_tris[np.repeat(first - np.cumsum(count) + count, count) + np.arange(len(pid))]
        # the triangles whose grown shadow box holds the point; the edge tests decide
        b = self.box[t]
        px, py = q[pid, 0], q[pid, 1]
        keep = np.flatnonzero((b[:, 0] <= px) & (px <= b[:, 2]) & (b[:, 1] <= py) & (py <= b[:, 3]))
        pid, t, px, py = pid[keep], t[keep], px[keep], py[keep]
        c = self.corners[t]
        x0, y0, x1, y1, x2, y2 = (c[:, k] - p for k, p in ((0, px), (1, py), (3, px), (4, py), (6, px), (7, py)))
        # the point's side of the edges 0->1, 1->2, 0->2 (corners in index order): > 0 on the left
        a01, b01 = x0 * y1, y0 * x1
        a12, b12 = x1 * y2, y1 * x2
        a02, b02 = x0 * y2, y0 * x2
        s01, s12, s02 = a01 - b01, a12 - b12, a02 - b02
        e01 = 4 * _EPS * (np.abs(a01) + np.abs(b01))
        e12 = 4 * _EPS * (np.abs(a12) + np.abs(b12))
        e02 = 4 * _EPS * (np.abs(a02) + np.abs(b02))
        # the turn itself moves each coordinate by up to `shift` (the same for every triangle: the
        # count stays consistent, but a point closer than that to the surface may change sides)
        shift = 8 * _EPS * max(self._reach, float(np.abs(q).max(initial=0.0)))
        ax0, ay0, ax1, ay1, ax2, ay2 = (np.abs(x) for x in (x0, y0, x1, y1, x2, y2))
        m01, m12, m02 = e01 + shift * (ax0 + ay0 + ax1 + ay1), e12 + shift * (ax1 + ay1 + ax2 + ay2), \
            e02 + shift * (ax0 + ay0 + ax2 + ay2)
        # inside the shadow: the same side of 0->1, 1->2 and 2->0 (a tie counts as the left of the
        # edge taken low index first, the same in both triangles that share the edge)
        f01, f12, f20 = s01 >= 0, s12 >= 0, s02 < 0
        inside = (f01 == f12) & (f12 == f20)
        # a triangle whose shadow is one point (its corners on one line along the ray: a bone triangle
        # the transfer collapsed) has every side exactly 0 and no area: it crosses no ray and holds no
        # vertex of note (a point on it is the edge test's, below); counted near, it sent every point
        # within the slack of it (2 mm for the bone) to the brute force, 14% of a bake's
        point = (x0 == x1) & (x1 == x2) & (y0 == y1) & (y1 == y2)
        near_vertex = (((np.abs(s01) <= e01).astype(np.int8) + (np.abs(s12) <= e12) + (np.abs(s02) <= e02)) >= 2) & ~point
        # where the ray meets the triangle, above the point or below (weights: the opposite edges' sides)
        z0, z1, z2 = c[:, 2] - q[pid, 2], c[:, 5] - q[pid, 2], c[:, 8] - q[pid, 2]
        num = s12 * z0 - s02 * z1 + s01 * z2
        bound = (4 * _EPS * (np.abs(s12 * z0) + np.abs(s02 * z1) + np.abs(s01 * z2))
                 + m12 * np.abs(z0) + m02 * np.abs(z1) + m01 * np.abs(z2)
                 + 2 * shift * (np.abs(s12) + np.abs(s02) + np.abs(s01)))
        ccw = np.where(f01, 1, -1)              # the shadow of corners 0, 1, 2 turns counter-clockwise
        cross = inside & (num * ccw > 0)
        # +1 where the triangle faces along the ray (the ray leaves), -1 where against
        W = np.bincount(pid[cross], (ccw * self.parity[t])[cross], minlength=n).round().astype(np.int64)
        unsure[pid[near_vertex | (inside & (np.abs(num) <= bound))]] = True
        # a point on an edge where the surface folds over along the ray (no triangle's shadow holds
        # it, or both do): the edge passes within rounding of the point's shadow and spans its height
        edge = np.flatnonzero((np.abs(s01) <= m01) | (np.abs(s12) <= m12) | (np.abs(s02) <= m02))
        if len(edge):
            rel = [(x0[edge], y0[edge], z0[edge]), (x1[edge], y1[edge], z1[edge]), (x2[edge], y2[edge], z2[edge])]
            on = np.zeros(len(edge), bool)
            for (i, j), sv, mv in (((0, 1), s01, m01), ((1, 2), s12, m12), ((0, 2), s02, m02)):
                spans = np.abs(sv[edge]) <= mv[edge]
                for a, b in zip(rel[i], rel[j]):
                    spans &= (np.minimum(a, b) <= shift) & (np.maximum(a, b) >= -shift)
                on |= spans
            unsure[pid[edge[on]]] = True
        return W, unsure

    def __call__(self, points):
        """Winding numbers (k,) of points (k,3) w.r.t. the mesh."""
        points = np.atleast_2d(np.asarray(points, dtype=np.float64))
        if not len(points):
            return np.zeros(0)
        W, unsure = self.crossings(points)
        out = W - self._caps(points) if len(self.cap) else W.astype(np.float64)
        redo = np.flatnonzero(unsure)
        if len(redo):
            out[redo] = winding_numbers(points[redo], self.verts, self.tris)
        return out

    def _caps(self, points):
        """The caps' winding numbers (k,) at points (k,3), as inside.winding_numbers sums them (to the
        bit: the same terms, each row summed alike), from the kept terms where remembering."""
        if not self.remember or len(points) * len(self.cap) > REMEMBER_MOST:
            return winding_numbers(points, self.verts, self.cap)
        corners = self.verts[self.cap]
        kept = self._kept.pop(len(points), None)
        if kept is None:
            terms = solid_angles(points, corners)
        else:
            seen, was, terms = kept
            moved = (points != seen).any(axis=1)
            if moved.any():
                terms[moved] = solid_angles(points[moved], corners)
            cols, same = np.flatnonzero((corners != was).any(axis=(1, 2))), np.flatnonzero(~moved)
            if len(cols) and len(same):
                terms[np.ix_(same, cols)] = solid_angles(points[same], corners[cols], chunk=max(32, 16384 // len(cols)))
        while len(self._kept) >= REMEMBER_SETS:          # the smallest set goes: the quickest to sum anew
            self._kept.pop(min(self._kept))
        self._kept[len(points)] = (points.copy(), corners, terms)
        return terms.sum(axis=1) / (2 * np.pi)
