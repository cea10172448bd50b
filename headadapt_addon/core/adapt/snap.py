"""The last step after the levels (HeadAdapt, not the paper): the skin laid onto the scan where the scan
shows it. The levels are smooth maps of the template; the finest one's centres lie 2 mm apart and
its smoothness term and robust weights leave the skin a few tenths of a millimetre off the scan
(lips, the nose's wings, cheeks). Each seen vertex is paired along its normal with the scan, as the
fine levels pair it, and the skin takes the displacement that reaches those points with the least
stretch (a membrane over the skin's edges); the vertices with no pair (holes, the lip seam, the skin
where the scan has no room for the template's detail) follow their neighbours, and round a triangle
the snap would fold the skin stays where the levels left it, as do the lids' margins (snap_keep:
the blink is simulated on them). It moves the skin only, by at most snap_reach (each move is a
weighted mean of the pairs' own): bone, eyes and muscles follow the levels (AdaptResult.map_points)."""

from __future__ import annotations

import numpy as np
from scipy import sparse

from ..mesh import geometry
from ..tol import MM
from .fit import Fit
from .levels import factor_spd
from .pairs import normal_hits


def snap_to_scan(fit: Fit, verts: np.ndarray) -> tuple[np.ndarray, dict]:
    """(the skin verts (n,3) laid onto the scan, {"paired": vertices paired with the scan, "pinned":
    vertices held round what it would fold, "rounds": solves again, "moved_rms_mm": how far the skin
    moved}); template frame. `verts` must fold nowhere (the fit after pipeline.Unfolding). Round any
    triangle the snap would fold, two rings of vertices are pinned to `verts` and the snap solved
    again, the pins widening by two rings each round (AdaptOptions.snap_fold_rounds); if a fold still
    resists, the skin is returned unsnapped."""
    o = fit.options
    n = len(verts)
    normals = geometry.vertex_normals(verts, fit.tris)
    use = np.flatnonzero((fit.pair_w > 0) & ~fit.near_seam)
    point, normal, _, missed = normal_hits(fit.scan, verts[use], normals[use], o.snap_reach)
    ok = ~missed & (np.einsum("ij,ij->i", normals[use], normal) > 0.5)
    w = np.zeros(n)
    w[use[ok]] = 1.0
    target = np.zeros_like(verts)
    target[use[ok]] = point[ok] - verts[use[ok]]
    # the lids round the eyes stay where the levels left them (AdaptOptions.snap_keep): the blink is
    # simulated on them, and laid onto a scan's lids it left more of the eyeball showing
    keep = fit.grown(fit.tpl.region_mask(*o.snap_keep), o.snap_keep_rings)
    w[keep], target[keep] = 1.0, 0.0
    # the skin's graph Laplacian (a membrane: a vertex with no pair takes its neighbours' mean)
    graph = (fit.ring != 0).astype(float)
    bend = sparse.diags(np.asarray(graph.sum(axis=1)).ravel()) - graph
    system = (sparse.diags(w + 1e-9) + o.snap_smooth * bend).tocsc()
    factor = factor_spd(system)
    moved, pinned, rounds = verts + factor.solve(w[:, None] * target), np.zeros(n, bool), 0
    while len(folds := fit.folds(moved)) and rounds < o.snap_fold_rounds:
        # round a fold the skin stays where the levels left it (folded nowhere): its pairs become pins
        # there, over two rings, widening while a fold resists
        rounds += 1
        pinned[fit.tris[folds].ravel()] = True
        pinned = fit.grown(pinned, 2)
        if (new := pinned & (w == 0)).any():       # new weights on the diagonal
            system = system + sparse.diags(new.astype(float), format="csc")
            factor = factor_spd(system)
        w[pinned], target[pinned] = 1.0, 0.0
        moved = verts + factor.solve(w[:, None] * target)
    if len(folds):              # not to be had: no snap at all
        moved = verts
    step = np.linalg.norm(moved - verts, axis=1)
    return moved, {"paired": int(np.sum(ok)), "pinned": int(pinned.sum()), "rounds": rounds,
                   "moved_rms_mm": float(np.sqrt(np.mean(step ** 2))) * MM, "snapped": moved is not verts}
