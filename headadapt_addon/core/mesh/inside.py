"""Inside/outside queries by the generalized winding number (Jacobson et al. 2013)."""

import numpy as np


def winding_numbers(points, verts, tris, chunk=32):
    """Generalized winding number of each point (k,3) w.r.t. the triangle mesh (verts, tris).

    About 1 inside a closed, outward-oriented surface, 0 outside, in between near holes; any
    consistent unit. Vectorized over triangles per coordinate (small chunks of points stay in
    cache: about ten times faster than stacked (k,t,3) arrays)."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    corners = np.asarray(verts, dtype=np.float64)[np.asarray(tris)]           # (t,3,3)
    out = np.empty(len(points))
    for start, angles in _angle_chunks(points, corners, chunk):
        out[start:start + len(angles)] = angles.sum(axis=1) / (2 * np.pi)
    return out


def solid_angles(points, corners, chunk=32):
    """(k,t) terms of points (k,3) and triangles (corners (t,3,3)), those winding_numbers sums: each
    row's sum over 2 pi is the point's winding number, to the bit (the same arithmetic, row by row)."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    out = np.empty((len(points), len(corners)))
    for start, angles in _angle_chunks(points, np.asarray(corners, dtype=np.float64), chunk):
        out[start:start + len(angles)] = angles
    return out


def _angle_chunks(points, corners, chunk):
    """(start, (m,t) arctangents) for each chunk of `chunk` points: Van Oosterom and Strackee's
    solid angle of each triangle at each point, over 2 (the arctangent of the half angle)."""
    a, b, c = (np.ascontiguousarray(corners[:, i].T) for i in range(3))     # (3,t) each
    for start in range(0, len(points), chunk):
        p = points[start:start + chunk, :, None]                              # (m,3,1)
        (ax, ay, az), (bx, by, bz), (cx, cy, cz) = (
            [corner[i][None] - p[:, i] for i in range(3)] for corner in (a, b, c))
        la, lb, lc = (np.sqrt(x * x + y * y + z * z) for x, y, z in ((ax, ay, az), (bx, by, bz), (cx, cy, cz)))
        num = ax * (by * cz - bz * cy) + ay * (bz * cx - bx * cz) + az * (bx * cy - by * cx)
        den = (la * lb * lc + (ax * bx + ay * by + az * bz) * lc
               + (bx * cx + by * cy + bz * cz) * la + (cx * ax + cy * ay + cz * az) * lb)
        yield start, np.arctan2(num, den)
