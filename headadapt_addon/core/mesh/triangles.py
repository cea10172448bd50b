"""Exact tests of points and rays against triangles, and the rule that picks one answer among several.

These are the arithmetic every spatial answer comes from (both backends of spatial.MeshQuery, the
template's build): a query's candidates, found however, are measured here, and pick() chooses.
"""

import numpy as np

from ..tol import TINY
from .geometry import cross

RAY_TOL = 1e-9      # barycentric slack of a ray hit: a ray through a shared edge hits both faces, never neither


def closest_on_segments(p, a, b, c):
    """Closest points (k,3) and barycentrics (k,3) on triangles taken as their three edges: the exact
    answer for a degenerate (flat) triangle, which is the union of its edges."""
    best_d = np.full(len(p), np.inf)
    q, bary = np.zeros((len(p), 3)), np.zeros((len(p), 3))
    for i, (x, y) in enumerate(((a, b), (b, c), (c, a))):
        e = y - x
        ee = np.einsum("ij,ij->i", e, e)
        s = np.clip(np.einsum("ij,ij->i", p - x, e) / np.where(ee > 0, ee, 1.0), 0.0, 1.0)
        s = np.where(ee > 0, s, 0.0)
        qi = x + s[:, None] * e
        d = np.linalg.norm(p - qi, axis=1)
        better = d < best_d
        best_d[better], q[better] = d[better], qi[better]
        bi = np.zeros((len(p), 3))
        bi[:, i], bi[:, (i + 1) % 3] = 1 - s, s
        bary[better] = bi[better]
    return q, bary


def finite(x):
    """np.nan_to_num(x) (NaN to 0, an infinity to the largest float), x itself where all is finite: the
    same numbers, without nan_to_num's cost on the small arrays of the skin's contact looks."""
    return x if np.isfinite(x).all() else np.nan_to_num(x)


def flat_triangles(e1, e2):
    """Triangles (edges from a corner, (k,3) each) too flat for the region test: their normal vanishes
    against their edges (within TINY), a zero-length edge included."""
    n = cross(e1, e2)
    return np.einsum("ij,ij->i", n, n) <= TINY * TINY * np.einsum("ij,ij->i", e1, e1) * np.einsum("ij,ij->i", e2, e2)


def closest_on_triangles(p, a, b, c):
    """Closest points (n,3) on triangles (a,b,c) to points p, and their barycentric coords (n,3)
    (Ericson's Voronoi regions; a degenerate triangle: the nearest point of its three edges)."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = np.einsum("ij,ij->i", ab, ap), np.einsum("ij,ij->i", ac, ap)
    bp = p - b
    d3, d4 = np.einsum("ij,ij->i", ab, bp), np.einsum("ij,ij->i", ac, bp)
    cp = p - c
    d5, d6 = np.einsum("ij,ij->i", ab, cp), np.einsum("ij,ij->i", ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    # the first region that holds the point (Ericson's order), its barycentrics from that region's formula
    region = np.select([(d1 <= 0) & (d2 <= 0), (d3 >= 0) & (d4 <= d3), (d6 >= 0) & (d5 <= d6),
                        (vc <= 0) & (d1 >= 0) & (d3 <= 0), (vb <= 0) & (d2 >= 0) & (d6 <= 0),
                        (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0)], [0, 1, 2, 3, 4, 5], 6)
    bary = np.zeros((len(p), 3))
    bary[region == 0, 0] = 1.0                                            # vertex a
    bary[region == 1, 1] = 1.0                                            # vertex b
    bary[region == 2, 2] = 1.0                                            # vertex c
    with np.errstate(divide="ignore", invalid="ignore"):
        for r, (i, j), num, den in ((3, (0, 1), d1, d1 - d3), (4, (0, 2), d2, d2 - d6),          # edges ab, ac
                                    (5, (1, 2), d4 - d3, (d4 - d3) + (d5 - d6))):               # edge bc
            at = region == r
            s = num[at] / den[at]
            bary[at, i], bary[at, j] = 1 - s, s
        at = region == 6                                                  # inside
        denom = va[at] + vb[at] + vc[at]
        v_, w_ = vb[at] / denom, vc[at] / denom
        bary[at, 0], bary[at, 1], bary[at, 2] = 1 - v_ - w_, v_, w_
    bary = finite(bary)
    flat = np.flatnonzero(flat_triangles(ab, ac))           # degenerate: the closest of its three edges
    if len(flat):
        _, bary[flat] = closest_on_segments(p[flat], a[flat], b[flat], c[flat])
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
    hit = ok & (u >= -RAY_TOL) & (v >= -RAY_TOL) & (u + v <= 1 + RAY_TOL)
    return hit, t, u, v


def pick(owner, first, second=None, face=None):
    """Per run of `owner` (sorted): the index of the run's answer: the least `first` (compared exactly),
    then the least `second`, then the lowest `face`. Returns (the runs' owners, the chosen indices)."""
    if not len(owner):
        return owner[:0], np.zeros(0, np.int64)
    keys = [k for k in (face, second) if k is not None] + [first, owner]
    order = np.lexsort(keys)
    starts = np.flatnonzero(np.concatenate([[True], owner[order][1:] != owner[order][:-1]]))
    return owner[order][starts], order[starts]


def closest_choice(points, owner, face, verts, tris):
    """The closest point of each owner among its candidate faces (owner sorted): (owners, closest point,
    face, distance). The least distance as closest_on_triangles computes it; among faces at exactly that
    distance (a shared vertex, or a shared edge where the rounding agrees) the face whose normal is most
    nearly along the offset from the surface (the point lies most squarely in front of or behind it:
    largest |cos|), then the lowest face index."""
    corners = verts[tris[face]]
    q, _ = closest_on_triangles(points[owner], corners[:, 0], corners[:, 1], corners[:, 2])
    off = points[owner] - q
    dist = np.linalg.norm(off, axis=1)
    n = cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    cos = np.abs(np.einsum("ij,ij->i", n, off)) / np.maximum(np.linalg.norm(n, axis=1) * dist, 1e-300)
    who, chosen = pick(owner, dist, -cos, face)
    return who, q[chosen], face[chosen], dist[chosen]


def ray_choice(o, d, lo, hi, owner, face, verts, tris):
    """The nearest hit of each ray among its candidate faces (owner sorted): (rays, t, face, bary) of the
    rays that hit with lo <= t <= hi. The least |t| as ray_triangles computes it, then the lowest face."""
    corners = verts[tris[face]]
    hit, t, u, v = ray_triangles(o[owner], d[owner], corners[:, 0], corners[:, 1], corners[:, 2])
    hit &= (t >= lo[owner]) & (t <= hi[owner])
    owner, face, t, u, v = owner[hit], face[hit], t[hit], u[hit], v[hit]
    who, chosen = pick(owner, np.abs(t), None, face)
    return who, t[chosen], face[chosen], np.c_[1 - (u[chosen] + v[chosen]), u[chosen], v[chosen]]
