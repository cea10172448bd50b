"""The skin's closest points on its bone, kept from one contact look to the next.

An equilibrium looks at the skin near the bone again and again (each push, then the retraction's
check), and about a quarter of those looks find every point where the last one left it: nothing was
pushed there. A point's closest point on a bone depends on that point alone, so the last look's
answer for the same vertex at the same place is the answer, to the bit; a look at a few dozen points
costs the tree's walk all the same (about 1 ms each, half the bake)."""

from __future__ import annotations

import numpy as np


class KeptClosest:
    """A MeshQuery's closest points for the places of numbered vertices (0..n-1): each vertex's last
    answer kept, and given again when it is asked at the very same place."""

    def __init__(self, query, n):
        self.query = query
        self.pts = np.full((n, 3), np.nan)                    # where each vertex was last asked (NaN: never)
        self.answer = (np.zeros((n, 3)), np.zeros(n, np.int64), np.zeros(n))

    def __call__(self, pts, idx):
        """(closest (k,3), face (k,), distance (k,)) of points pts (k,3), the places of vertices idx (k,)."""
        new = np.flatnonzero((self.pts[idx] != pts).any(axis=1))
        if len(new):
            for kept, fresh in zip(self.answer, self.query.closest_points(pts[new])):
                kept[idx[new]] = fresh
            self.pts[idx[new]] = pts[new]
        return tuple(kept[idx] for kept in self.answer)


def closest_on_bone(model, pts, local, idx):
    """((closest, face, distance) on the cranium of skin points pts (k,3), the same on the mandible of
    their places `local` (k,3) in the jaw's frame) for skin vertices idx (k,); idx None: asked afresh."""
    (q_cr, *_), (q_md, *_), *_ = model.bone
    if idx is None:
        return q_cr.closest_points(pts), q_md.closest_points(local)
    kept = model.__dict__.get("_kept_closest")
    if kept is None:
        kept = model.__dict__["_kept_closest"] = (KeptClosest(q_cr, model.n), KeptClosest(q_md, model.n))
    return kept[0](pts, idx), kept[1](local, idx)
