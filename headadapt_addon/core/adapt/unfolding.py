"""Step 4 for any level: the triangles a level folded are repaired before the level is judged, as the
skin will be delivered. Two repairs, and the one that leaves the skin nearer the scan is kept:
relaxation (geometry.unfold: the displacement smoothed around the folds) and going back to the level
below around them (blend_back: that skin folded nowhere, and the level's own offset ramps back in over a
few rings of vertices)."""

from __future__ import annotations

import time

import numpy as np

from ..mesh import geometry
from ..tol import MM, TINY

LIDS = ("eyelid_l", "eyelid_r", "eye_socket_l", "eye_socket_r")     # the skin round the eyes


def ring_distance(seed: np.ndarray, adjacency, most: int) -> tuple[np.ndarray, np.ndarray]:
    """((n,) the number of edges from each vertex to the nearest vertex of the mask `seed` (0 on it),
    counted up to `most`, farther vertices most + 1; (n,) which piece of the seed that nearest vertex
    is in (its connected component; -1 beyond most)). adjacency: the skin's neighbour_mean (its pattern
    is the edges)."""
    from scipy.sparse import csgraph

    n = len(seed)
    dist, piece = np.full(n, most + 1), np.full(n, -1)
    on = np.flatnonzero(seed)
    dist[on] = 0
    piece[on] = csgraph.connected_components(adjacency[on][:, on], directed=False)[1]
    front = on
    for k in range(1, most + 1):
        # the front's neighbours not reached yet take the ring and a front neighbour's piece
        rows = adjacency[front]
        nbrs = rows.indices
        owner = np.repeat(front, np.diff(rows.indptr))
        fresh = dist[nbrs] > k
        if not fresh.any():
            break
        dist[nbrs[fresh]], piece[nbrs[fresh]] = k, piece[owner[fresh]]
        front = np.unique(nbrs[fresh])
    return dist, piece


def blend_back(below: np.ndarray, cur: np.ndarray, fit, widths, keep: np.ndarray | None = None
               ) -> tuple[np.ndarray | None, int]:
    """(skin, vertices changed) with the folds of `cur` (n,3) repaired by the skin of the level below
    (`below`, folded nowhere): below on the folded triangles' corners, the level's offset coming back
    linearly over a width of rings around them, each piece of folds (connected corners) with the
    narrowest width of `widths` that folds nothing near it; (None, 0) if the widest leaves a fold.
    keep: (n,) bools, vertices whose folds are not repaired here (their pieces are left as in `cur`,
    folded, for the caller to relax)."""
    keep = np.zeros(len(cur), bool) if keep is None else keep
    folds = fit.folds(cur)
    corners = fit.tris[folds]
    seed = np.zeros(len(cur), bool)
    seed[corners.ravel()] = True
    dist, piece = ring_distance(seed, fit.adjacency, max(widths))
    # the pieces with a kept vertex stay as they are: the level's own skin there, folds and all
    kept = np.isin(piece, piece[corners[keep[corners].any(axis=1)].ravel()])
    left = folds[kept[corners].any(axis=1)]
    dist[kept], piece[kept] = max(widths) + 1, -1
    if not (piece >= 0).any():
        return None, 0
    step = np.zeros(piece.max() + 1, int)                   # each piece's width, as an index into widths
    widths = np.asarray(widths, dtype=float)
    for _ in range(len(widths)):
        width = np.where(piece >= 0, widths[step[piece]], 1.0)
        y = below + np.clip(dist / width, 0.0, 1.0)[:, None] * (cur - below)
        hit = np.unique(piece[fit.tris[np.setdiff1d(fit.folds(y), left)].ravel()])
        if not len(hit):
            return y, int(np.sum(dist < width))
        if (hit < 0).any() or (step[hit] == len(widths) - 1).any():
            return None, 0
        step[hit] += 1
    return None, 0


def seen_rms_mm(fit, skin: np.ndarray) -> float:
    """The distance RMS of a skin from the scan as the levels are judged (pipeline.Judge: E_d's
    weights over the vertices matched on the scan's tangent planes), mm."""
    de = fit.distance_error(skin)
    return float(np.sqrt(np.sum(de.w * de.dist ** 2) / max(np.sum(de.w), TINY))) * MM


class Unfolding:
    """Step 4 for any level: skin (n,3) -> (the skin with its folded triangles repaired,
    {"folded_triangles", "vertices_relaxed", "folded_left", "repair"}); keeps the seconds spent (`last`
    call, and in all). The repair is the relaxation (geometry.unfold) or, from level 1 on, the level
    below around the folds (blend_back; folds on the lids relaxed after), whichever leaves the skin
    nearer the scan ("repair": "relaxed" or "level below"; vertices_relaxed counts the vertices the
    repair moved). A level that folds is judged as it will be delivered: on Fran's closed eyes level
    4 folded 19 lid triangles (level 3: 8), relaxed over 1290 vertices, and its seen face ended 0.80
    mm RMS from the scan against level 3's 0.53. Relaxed, a few folds of an ear or a lip spread over
    hundreds of vertices and the level lost its fit there; taken back to the level below over a few
    rings, the fit stays (seen-face surface on tuning heads 0-11: -0.014 and -0.022 mm with 8 and 11
    clicks, better on 11 of 24 cases and worse on none; heads 12-49: -0.008 and -0.009, better on 34
    of 76 and worse on 5 by at most 0.024; correspondence within 0.004; the CT 0.317 -> 0.303 mm, the
    other real scans the same)."""

    def __init__(self, fit):
        self.fit, self.seconds, self.last = fit, 0.0, 0.0
        self.below = None                   # the last skin delivered: the level below the next one
        # the lids: their folds are relaxed, not taken back to the level below, whose lids closed a
        # scanned open eye's opening (the eye then seated 0.8 mm too deep) and left a CT's closed lid
        # 0.6 mm inside its orbit's rim
        self.lids = fit.tpl.region_mask(*LIDS)

    def __call__(self, cur):
        t0 = time.perf_counter()
        fit = self.fit
        n_folded = len(fit.folds(cur))                     # the template's FoldCheck, made once
        moved, left, how = 0, 0, None
        if n_folded:
            raw = cur
            cur, relaxed, left = geometry.unfold(fit.V, raw, fit.tris, mean=fit.adjacency, folds=fit.folds)
            moved, how = int(relaxed.sum()), "relaxed"
            if self.below is not None:
                back, changed = blend_back(self.below, raw, fit, fit.options.blend_back_rings, self.lids)
                if back is not None and len(fit.folds(back)):      # the lids' folds, relaxed as before
                    back, relaxed, still = geometry.unfold(fit.V, back, fit.tris, mean=fit.adjacency,
                                                           folds=fit.folds)
                    back, changed = (None, 0) if still else (back, changed + int(relaxed.sum()))
                if back is None and left:         # the relaxation fails: the lids go back too
                    back, changed = blend_back(self.below, raw, fit, fit.options.blend_back_rings)
                # judged as the level is (the RMS over the matched vertices): comparing only the vertices
                # either repair moved, a vertex off the scan counted at the threshold, chose the
                # relaxation more often and gained a third as much (tuning heads 12-49: -0.005 mm).
                # A relaxation that leaves a fold loses to a repair that leaves none: on a head whose
                # level 3 folded 8 triangles of a lid, the relaxation left one, moved 906 vertices and took
                # the level 1.18 mm RMS from the scan; the level below around them, lid and all: 0.47
                # (stop 59)
                if back is not None and (left or seen_rms_mm(fit, back) < seen_rms_mm(fit, cur)):
                    cur, moved, left, how = back, changed, 0, "level below"
        self.below = cur
        self.last = time.perf_counter() - t0
        self.seconds += self.last
        return cur, {"folded_triangles": n_folded, "vertices_relaxed": moved, "folded_left": left, "repair": how}
