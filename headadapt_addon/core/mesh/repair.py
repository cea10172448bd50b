"""A scan's triangles as exporters write them, put right before the fit: corners split at seams welded
(simplify.weld_if_split), triangles written twice dropped, windings made consistent within a piece
(geometry.orient_outward then turns each piece to face out).

Written twice: a "double-sided" export writes every triangle again, often reversed. Every edge is then
used four times, so no edge is a hole's border (the fit's seen-skin RMS counted the holes' rims: 0.78
mm reported against a true 0.27), and a reversed copy cancels its triangle's normal.
Mixed windings: a converter that writes some triangles reversed within one surface leaves each vertex's
normal the sum of opposite faces; the piece's vote then turns all or none of them (a head with half its
triangles reversed: surface 0.41 mm against 0.29).
"""

from __future__ import annotations

import numpy as np

from . import simplify

TWICE = 2.2        # more triangles than this x vertices: some written twice (a welded surface has about 2)


def drop_repeated_faces(tris, n):
    """(tris, how many dropped): each set of three corners once, its first triangle in the given
    order (with its winding). Only looked for when the mesh has over TWICE triangles a vertex."""
    if len(tris) <= TWICE * n:
        return tris, 0
    tris = np.asarray(tris, dtype=np.int64)
    first = simplify.first_of_each(tris, n)
    return tris[first], len(tris) - len(first)


def consistent_winding(tris, n):
    """(tris, how many turned): the triangles wound one way within each piece they form through their
    shared edges (an edge two triangles use must run opposite ways in them). Each triangle is two nodes
    of a graph, as it is and turned; two triangles sharing an edge join the same ways round (if they
    agree) or crossed; each piece is then two mirror components, and its triangles take the ways
    round of the component with the lower label, the one holding the piece's first triangle as it is
    written. A piece that cannot be wound one way (a Moebius strip, or a knot of edges three triangles
    use) keeps the windings it has. Which way out is geometry.orient_outward's."""
    from scipy import sparse
    from scipy.sparse import csgraph

    t = np.asarray(tris, dtype=np.int64)
    k = len(t)
    if not k:
        return tris, 0
    a, b = t.ravel(), t[:, [1, 2, 0]].ravel()
    key = np.minimum(a, b) * n + np.maximum(a, b)
    order = np.argsort(key, kind="stable")
    ranked = key[order]
    start = np.flatnonzero(np.r_[True, ranked[1:] != ranked[:-1]])
    twice = start[np.diff(np.r_[start, len(ranked)]) == 2]             # edges exactly two triangles use
    e1, e2 = order[twice], order[twice + 1]
    f, g = e1 // 3, e2 // 3
    disagree = (a < b)[e1] == (a < b)[e2]                               # the edge run the same way in both
    if not disagree.any():                  # (a scan's usual case: the sort alone, 5 of 30 ms on 60k triangles)
        return tris, 0
    cross = disagree.astype(np.int64) * k
    rows, cols = np.r_[f, f + k], np.r_[g + cross, g + k - cross]
    graph = sparse.coo_matrix((np.ones(len(rows), np.int8), (rows, cols)), shape=(2 * k, 2 * k)).tocsr()
    label = csgraph.connected_components(graph, directed=False)[1]
    turn = label[:k] > label[k:]
    if not turn.any():
        return tris, 0
    out = t.copy()
    out[turn] = out[turn][:, ::-1]
    return out, int(turn.sum())


def put_right(verts, tris, info):
    """(verts, tris, info): split corners welded (simplify.weld_if_split), triangles written twice
    dropped; what was done added to the calibration's info dict ("scan_welded", "scan_triangles_repeated").
    The windings are made consistent after a dense scan's clustering would be decided (the caller)."""
    welded = simplify.weld_if_split(verts, tris)
    if welded is not None:
        info = {**info, "scan_welded": {"vertices": len(verts), "kept": len(welded[0])}}
        verts, tris = welded
    tris, repeated = drop_repeated_faces(tris, len(verts))
    return verts, tris, ({**info, "scan_triangles_repeated": repeated} if repeated else info)
