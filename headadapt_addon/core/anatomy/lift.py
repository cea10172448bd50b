"""The transfer's last guarantee: a visible skin vertex still inside the bone after the bone was
cleared comes out, through the bone's nearest face where its own normal is not the way."""

from __future__ import annotations

import numpy as np

from ..mesh import winding


def _bump(tpl, skin, at, to, rings=3):
    """skin with the vertices `at` moved to `to` and their neighbours along, the move fading over
    `rings` rings (Jacobi steps of the neighbours' mean with `at` held)."""
    from ..mesh.geometry import neighbour_mean

    mean = neighbour_mean(tpl.skin.tris, len(skin))
    d = np.zeros_like(skin)
    d[at] = to - skin[at]
    near = np.zeros(len(skin), bool)
    near[at] = True
    for _ in range(rings):
        near |= (mean @ near.astype(float)) > 0
    for _ in range(4 * rings):
        d[near] = (mean @ d)[near]
        d[at] = to - skin[at]
    return skin + d


def _exit(inside, points, way, most):
    """How far along `way` (k,3) each point first lies outside the bone (bisection within `most`)."""
    lo, hi = np.zeros(len(points)), np.full(len(points), most)
    for _ in range(12):
        mid = 0.5 * (lo + hi)
        out = inside(points + mid[:, None] * way) <= 0.5
        hi, lo = np.where(out, mid, hi), np.where(out, lo, mid)
    return hi


def _lift_near(tpl, skin, bad, inside, query, most, clearance):
    """The visible skin vertices `bad` inside the bone moved out where that is short (within `most`):
    along their own outward normal, else back along it, else through the bone's nearest face. Returns (skin (n,3), the
    vertices moved, the rest, their nearest outside points (k,3) through the bone's faces, and how
    far those are (k,))."""
    from ..mesh.geometry import face_normals, vertex_normals

    normals = vertex_normals(skin, tpl.skin.tris)[bad]
    skin = skin.copy()
    # out along the outward normal; else back along it, where the bone's edge is that near (a lid over
    # the orbit's opening, inside by the winding number of the skull's open rim: the CT's closed left lid
    # lay 0.11 mm in, and out through neither the normal nor the rim's nearest face)
    way, step, out_at_most = normals.copy(), np.full(len(bad), np.inf), np.zeros(len(bad), bool)
    for sign in (1.0, -1.0):
        at = ~out_at_most & (inside(skin[bad] + sign * most * normals) <= 0.5)
        if sign < 0:
            at &= inside(skin[bad] - 0.5 * most * normals) <= 0.5      # not through bone and out again
        hi = _exit(inside, skin[bad][at], sign * normals[at], most)
        way[at], step[at], out_at_most[at] = sign * normals[at], hi, True
    move, rest = bad[out_at_most], bad[~out_at_most]
    skin[move] += (np.minimum(step[out_at_most] + clearance, most))[:, None] * way[out_at_most]
    if not len(rest):
        return skin, move, rest, np.zeros((0, 3)), np.zeros(0)
    near, face, dist = query.closest_points(skin[rest])          # out through the bone's nearest face
    to = near + (clearance + 1e-6) * face_normals(query.verts, query.tris)[face]
    dist = np.where(inside(to) <= 0.5, dist, np.inf)
    ok = dist <= most
    skin[rest[ok]] = to[ok]
    return skin, np.concatenate([move, rest[ok]]), rest[~ok], to[~ok], dist[~ok]


def lift_visible_skin(tpl, skin, cranium, mandible, most=0.0005, clearance=0.0001, bone_inside=None,
                      farthest=0.002):
    """The last guarantee of the transfer: a visible skin vertex still inside the bone after the bone
    was cleared (clear_visible_skin freezes bone by a pocket: a lid at the orbit's opening) steps out
    along its own outward normal (or back along it), at most `most` (0.5 mm: a sliver of bone rim, not
    a fit gone wrong), to `clearance` outside; where that way is longer (bone folded round the point: a statue's lid on
    the orbit's rim), through the bone's nearest face if that is within `most`, else within `farthest`
    (2 mm) with the skin round it taken along, if no skin triangle turns over for it and fewer visible
    vertices stay inside (the neighbours it drags back in lifted again first): Nefertiti's carved left
    lid, on the orbit's rim, ended 0.06 mm inside on one machine and 0.6 to 1.6 mm on another (the
    arithmetic's rounding differs between processors and numpy versions, and the bone's clearing
    before this step amplifies it). Returns (skin (n,3), the vertices moved, those still inside)."""
    from ..mesh.geometry import folded
    from ..mesh.spatial import MeshQuery

    bone = np.vstack([cranium, mandible])
    inside = (winding.FastWinding(bone, tpl.skull_tris) if bone_inside is None else bone_inside).refit(bone)
    visible = np.flatnonzero(~tpl.hidden)

    def inside_of(x):                         # the visible vertices of skin x inside the bone
        return visible[inside(x[visible]) > 0.5]

    bad = inside_of(skin)
    if not len(bad):
        return skin, bad, bad
    query = MeshQuery(bone, tpl.skull_tris, backend="numpy")
    lifted, move, rest, to, dist = _lift_near(tpl, skin, bad, inside, query, most, clearance)
    left = inside_of(lifted)
    # farther, up to `farthest`: the skin round them taken along (a bump fading over a few rings, so the
    # lid's small triangles do not turn over), the neighbours it pushed in lifted again, kept if nothing
    # folds that did not before and fewer visible vertices stay inside
    far = dist <= farthest
    if far.any():
        trial = _bump(tpl, lifted, rest[far], to[far])
        again = inside_of(trial)
        if len(again):
            trial = _lift_near(tpl, trial, again, inside, query, most, clearance)[0]
            again = inside_of(trial)
        new = np.setdiff1d(folded(tpl.skin.verts, trial, tpl.skin.tris), folded(tpl.skin.verts, lifted, tpl.skin.tris))
        if not len(new) and len(again) < len(left):
            move = np.union1d(move, np.flatnonzero(np.any(trial != lifted, axis=1)))
            lifted, left = trial, again
    return lifted, move, left
