"""Inside/outside queries by the generalized winding number (Jacobson et al. 2013)."""

import numpy as np


def winding_numbers(points, verts, tris, chunk=256):
    """Generalized winding number of each point (k,3) w.r.t. the triangle mesh (verts, tris).

    About 1 inside a closed, outward-oriented surface, 0 outside, in between near holes; any
    consistent unit. Vectorized over triangles, chunked over points to bound memory."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    corners = np.asarray(verts, dtype=np.float64)[np.asarray(tris)]
    out = np.empty(len(points))
    for start in range(0, len(points), chunk):
        rel = corners[None] - points[start:start + chunk, None, None, :]
        a, b, c = rel[:, :, 0], rel[:, :, 1], rel[:, :, 2]
        la, lb, lc = (np.linalg.norm(x, axis=2) for x in (a, b, c))
        num = np.einsum("ijk,ijk->ij", a, np.cross(b, c))
        den = (la * lb * lc + np.einsum("ijk,ijk->ij", a, b) * lc
               + np.einsum("ijk,ijk->ij", b, c) * la + np.einsum("ijk,ijk->ij", c, a) * lb)
        out[start:start + chunk] = np.arctan2(num, den).sum(axis=1) / (2 * np.pi)
    return out
