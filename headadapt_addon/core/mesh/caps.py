"""A triangle mesh's holes closed: its border's directed edges, the simple loops they make, and a cap of
triangles over each loop (no new vertices), turned so that the mesh and its caps are a closed surface
(core/mesh/winding.py counts ray crossings of that closed surface)."""

import numpy as np


def border_edges(tris):
    """Directed border edges (k,2) of a triangle mesh: each undirected edge as often as its uses a->b
    outnumber those b->a (never on a closed surface), turned the way the mesh runs along its border."""
    tris = np.asarray(tris, dtype=np.int64).reshape(-1, 3)
    if not len(tris):
        return np.zeros((0, 2), np.int64)
    d = np.r_[tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]]
    lo, hi = d.min(axis=1), d.max(axis=1)
    base = int(tris.max()) + 1
    key, inv = np.unique(lo * base + hi, return_inverse=True)
    net = np.bincount(inv, np.where(d[:, 0] == lo, 1.0, -1.0), minlength=len(key)).round().astype(np.int64)
    e = np.flatnonzero(net)
    a, b = key[e] // base, key[e] % base
    edges = np.where((net[e] > 0)[:, None], np.c_[a, b], np.c_[b, a])
    return np.repeat(edges, np.abs(net[e]), axis=0)


def border_loops(edges):
    """Simple closed loops (lists of vertex ids, in the mesh's direction) that use every directed
    border edge (k,2) once: where the border passes a vertex twice, it is cut into two loops there."""
    edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    outgoing = {}
    for e in np.argsort(edges[:, 0], kind="stable")[::-1]:
        outgoing.setdefault(int(edges[e, 0]), []).append(int(e))
    used = np.zeros(len(edges), bool)
    loops = []
    for first in range(len(edges)):
        if used[first]:
            continue
        loop, at, e = [], {}, first
        while True:
            used[e] = True
            a, b = int(edges[e, 0]), int(edges[e, 1])
            at[a] = len(loop)
            loop.append(a)
            if b in at:                     # back at a vertex of this walk: that part is a loop
                cut = at[b]
                loops.append(loop[cut:])
                for v in loop[cut:]:
                    del at[v]
                del loop[cut:]
            nxt = outgoing.get(b, [])
            while nxt and used[nxt[-1]]:
                nxt.pop()
            if not nxt:
                break
            e = nxt.pop()
        if loop:
            loops.append(loop)
    return loops


def cap_triangles(loops):
    """Triangles (k,3) closing each loop: its polygon split at the middle vertex, recursively, turned
    against the loop so that the mesh and its caps together are a closed surface."""
    out = []
    for loop in loops:
        stack = [(0, len(loop) - 1)]
        while stack:
            i, j = stack.pop()
            if j - i < 2:
                continue
            m = (i + j) // 2
            out.append((loop[j], loop[m], loop[i]))
            stack += [(i, m), (m, j)]
    return np.array(out, dtype=np.int64).reshape(-1, 3)
