"""What of an eyeball a person facing the head sees: rays from the front (along +y, the template frame's
backward; an adapted head is in that frame too) over the eyeball's outline, each seeing the eyeball
where it meets the eyeball before any skin. The lids' turn is measured from it at rest (controls), and
a closed eye is judged by it: an eyeball that pokes through a closed lid is seen as a slit is."""

from __future__ import annotations

import numpy as np

from ..mesh.spatial import MeshQuery

SIGHT_STEP = 0.25e-3          # the rays' grid over the eyeball's outline, m (about 7,000 rays an eye)
SIGHT_FROM = 0.1              # the rays start this far in front of the eyeball's centre, m


def eyeball_in_sight(skin, skin_tris, eye, eye_tris, step=SIGHT_STEP):
    """(the points of the eyeball seen from the front (k,3), the number of rays cast over its outline).
    skin_tris: the skin triangles that can hide it (the seen skin's); eye, eye_tris: the eyeball's mesh.
    A ray sees the eyeball where it meets it nearer than the skin, or meets no skin."""
    eye = np.asarray(eye, dtype=np.float64)
    centre = eye.mean(axis=0)
    radius = 0.98 * float(np.linalg.norm(eye - centre, axis=1).max())
    ticks = np.arange(-radius, radius, step)
    grid = np.stack(np.meshgrid(ticks, ticks), axis=-1).reshape(-1, 2)
    grid = grid[np.linalg.norm(grid, axis=1) < radius] + centre[[0, 2]]
    origins = np.c_[grid[:, 0], np.full(len(grid), centre[1] - SIGHT_FROM), grid[:, 1]]
    ahead = np.tile([0.0, 1.0, 0.0], (len(grid), 1))
    # only the skin triangles whose outline from the front can cover the eyeball's (the rays run along y)
    xz = skin[skin_tris][:, :, [0, 2]]
    near = ((xz.max(axis=1) >= centre[[0, 2]] - radius) & (xz.min(axis=1) <= centre[[0, 2]] + radius)).all(axis=1)
    t_eye = _first_hit(eye, eye_tris, origins, ahead)
    t_skin = _first_hit(skin, skin_tris[near], origins, ahead)
    seen = t_eye < t_skin
    return origins[seen] + t_eye[seen, None] * ahead[seen], len(grid)


def _first_hit(verts, tris, origins, ahead):
    """Each ray's distance to its first hit on the mesh (inf: none)."""
    if not len(tris):
        return np.full(len(origins), np.inf)
    hits = MeshQuery(verts, tris, backend="numpy").ray_cast(origins, ahead, 2 * SIGHT_FROM, both_ways=False)
    return np.where(hits.hit, hits.t, np.inf)
