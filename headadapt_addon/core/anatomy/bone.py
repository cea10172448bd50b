"""The skull under the adapted skin: each bone point kept at least a clearance under its own skin
point, the pockets' points led out through the lining, the visible skin cleared out of the skull."""

from __future__ import annotations

import numpy as np

from ..mesh import winding

POCKET_REACH = 0.015          # bone points this close to the pockets' skin may end in one, m


def _pocket_tris(tpl, hidden):
    """Skin triangles (k,3) of the pockets (mouth bag, eye sockets): all corners hidden."""
    return tpl.skin.tris[hidden[tpl.skin.tris].all(axis=1)]


def _within(points, verts, tris, reach):
    """Mask (k,): the points nearer than `reach` to the mesh (verts, tris), by the exact closest point
    on each triangle (spatial.closest_on_triangles, as MeshQuery(backend="numpy") finds it), tried
    only on the triangles that could be that near: those whose bounding ball (about the centroid)
    grown by `reach` holds the point. A point with a corner nearer than `reach` needs no test."""
    from scipy.spatial import cKDTree

    from ..mesh.spatial import closest_on_triangles

    points = np.asarray(points, dtype=np.float64)
    near = cKDTree(verts[np.unique(tris)]).query(points)[0] < reach * (1 - 1e-9)
    todo = np.flatnonzero(~near)
    if not len(todo) or not len(tris):
        return near
    corners = verts[tris]
    centroid = corners.mean(axis=1)
    ball = np.linalg.norm(corners - centroid[:, None], axis=2).max(axis=1)
    lists = cKDTree(points[todo]).query_ball_point(centroid, ball + reach * (1 + 1e-9), return_sorted=False)
    count = np.fromiter((len(x) for x in lists), dtype=np.int64, count=len(lists))
    face = np.repeat(np.arange(len(tris)), count)
    pid = todo[np.fromiter((i for x in lists for i in x), dtype=np.int64, count=int(count.sum()))]
    q, _ = closest_on_triangles(points[pid], corners[face, 0], corners[face, 1], corners[face, 2])
    near[pid[np.linalg.norm(q - points[pid], axis=1) < reach]] = True
    return near


_ANCHORS = {}        # template-only closest points of keep_inside: {digest of the inputs: (face, bary, depth)}


def _skin_anchors(skin_verts, faces, bone_template, backend="numpy"):
    """(face, barycentric, distance) of the closest point of each template bone point on the
    template's visible skin (verts, faces): depends on the template alone, so computed once per
    template, bone and spatial backend in a process (keyed by the arrays' bytes) and then shared by
    every transfer."""
    import hashlib

    from ..mesh.spatial import MeshQuery, barycentric

    digest = hashlib.sha256(backend.encode())
    for a in (skin_verts, faces, bone_template):
        a = np.ascontiguousarray(a)
        digest.update(f"{a.dtype.str}{a.shape}".encode())
        digest.update(a.tobytes())
    key = digest.hexdigest()
    if key not in _ANCHORS:
        near, face, depth = MeshQuery(skin_verts, faces, backend).closest_points(bone_template)
        v0 = skin_verts[faces[face]]
        found = (face, barycentric(near, v0[:, 0], v0[:, 1], v0[:, 2]), depth)
        for a in found:
            a.setflags(write=False)
        if len(_ANCHORS) >= 8:
            _ANCHORS.clear()
        _ANCHORS[key] = found
    return _ANCHORS[key]


def keep_inside(tpl, bone_template, bone_mapped, skin_adapted, clearance=0.0015, skin_inside=None,
                backend="numpy"):
    """Mapped bone points (n,3), moved where needed to at least `clearance` under the adapted skin.

    Each bone point keeps, from the template, its nearest point on the visible skin (face +
    barycentric, not the lids folded behind the eyes nor the mouth bag); where the adapted skin
    there is less than `clearance` above the mapped point (the scan is thinner than the template's
    tissue), the point moves to `clearance` under it along the skin's normal. Any point by a
    pocket of the skin (eye socket, mouth bag) that ends in it goes out through the pocket's lining
    (the mandible's centre, the old way out, lies in the mouth). Template frame, m. skin_inside:
    the adapted skin's FastWinding, if the caller has one (transfer builds it once).
    """
    from ..mesh.geometry import face_normals
    from ..mesh.spatial import MeshQuery

    hidden = tpl.hidden
    faces = tpl.skin.tris[~hidden[tpl.skin.tris].any(axis=1)]
    face, bary, depth0 = _skin_anchors(tpl.skin.verts, faces, bone_template, backend)
    clearance = np.minimum(clearance, 0.8 * depth0)      # never deeper than the template itself had it
    skin_pt = np.einsum("ij,ijk->ik", bary, skin_adapted[faces[face]])
    normal = face_normals(skin_adapted, faces[face])
    out = np.asarray(bone_mapped, dtype=np.float64).copy()
    depth = np.einsum("ij,ij->i", skin_pt - out, normal)
    bad = depth < clearance
    out[bad] = skin_pt[bad] - clearance[bad, None] * normal[bad]
    # next to the pockets (eye sockets, mouth) the skin folds back: check those few points exactly
    # (winding number) and walk any that ended in a pocket toward the bone's centre until inside
    from scipy.spatial import cKDTree

    near_pocket = np.flatnonzero(cKDTree(skin_adapted[hidden]).query(out, distance_upper_bound=POCKET_REACH)[0] < np.inf)
    if len(near_pocket):
        if skin_inside is None:
            skin_inside = winding.FastWinding(skin_adapted, tpl.skin.tris)
        w = skin_inside(out[near_pocket])
        still = near_pocket[w < 0.5]
        if len(still):                 # out through the pocket's lining, `clearance` into the tissue
            pocket_t = _pocket_tris(tpl, hidden)
            lining, face, _ = MeshQuery(skin_adapted, pocket_t, backend).closest_points(out[still])
            inward = -clearance[still, None] * face_normals(skin_adapted, pocket_t)[face]
            # behind a thin lip the tissue may be thinner than the clearance: a shorter step then
            for share in (1.0, 0.5, 0.25):
                out[still] = lining + share * inward
                outside = skin_inside(out[still]) < 0.5
                still, lining, inward = still[outside], lining[outside], inward[outside]
                if not len(still):
                    break
        if len(still):                 # else toward the bone's centre
            centre = np.asarray(bone_mapped).mean(axis=0)
            lo, hi = np.zeros(len(still)), np.ones(len(still))
            for _ in range(16):
                mid = 0.5 * (lo + hi)
                ok = skin_inside(out[still] + mid[:, None] * (centre - out[still])) > 0.5
                hi, lo = np.where(ok, mid, hi), np.where(ok, lo, mid)
            step = centre - out[still]
            out[still] += hi[:, None] * step + clearance[still, None] * step / np.linalg.norm(step, axis=1, keepdims=True)
    return out


def clear_visible_skin(tpl, skin, cranium, mandible, limit=0.48, radius=0.008, step=0.001, rounds=20,
                       skin_inside=None, bone_inside=None):
    """Cranium and mandible (template frame, m) pressed inward until no visible skin vertex is inside.

    keep_inside puts every bone point under the skin; this is the converse, for skin points that a
    thin scan brings down onto a bone rim (lids over the orbit's edge, brows): while a visible skin
    vertex near the bone has a winding number over `limit` w.r.t. the bone, the bone within
    `radius` of it steps deeper, each bone vertex along the inward normal of the skin vertex the
    template offset it from, by the largest step any such vertex asks of it (`step`, fading with
    distance; not their sum, which pressed a rim under a row of lid vertices several millimetres a
    round). A step that would take a bone point into a pocket of the skin (the eye socket behind the
    lids) slides along the pocket's lining instead, or is not taken (the point is frozen), so the
    bone stays inside the skin; a skin vertex whose nearest bone face has every corner frozen is left
    to lift_visible_skin (pressing the bone round it never cleared it). skin_inside, bone_inside: the
    skin's and the skull's FastWinding if the caller has them (the skull's is refit as it moves).
    """
    from scipy.spatial import cKDTree

    from ..mesh.geometry import face_normals, vertex_normals
    from ..mesh.spatial import MeshQuery

    n_cr = len(cranium)
    bone = np.vstack([cranium, mandible]).astype(np.float64)
    tris = tpl.skull_tris
    hidden = tpl.hidden
    visible = np.flatnonzero(~hidden)
    normals = vertex_normals(skin, tpl.skin.tris)
    # each bone vertex deepens along the skin normal of the skin vertex it was offset from
    inward = -normals[np.r_[tpl.bone_skin_index["cranium"], tpl.bone_skin_index["mandible"]]]
    near = visible[_within(skin[visible], bone, tris, 0.002)]
    if skin_inside is None:
        skin_inside = winding.FastWinding(skin, tpl.skin.tris)
    if bone_inside is None:
        bone_inside = winding.FastWinding(bone, tris, slack=step)
    check = near
    by_pocket = cKDTree(skin[hidden]).query(bone, distance_upper_bound=POCKET_REACH)[0] < np.inf
    pocket_t = _pocket_tris(tpl, hidden)
    pocket_q = MeshQuery(skin, pocket_t, backend="numpy")
    pocket_n = face_normals(skin, pocket_t)
    frozen = np.zeros(len(bone), bool)
    for _ in range(rounds):
        w = bone_inside.refit(bone)(skin[check])
        bad = check[w > limit]
        if len(bad) and frozen.any():          # held by bone that may not move: left to the lift
            _, face, _ = MeshQuery(bone, tris, backend="numpy").closest_points(skin[bad])
            bad = bad[~frozen[tris[face]].all(axis=1)]
        if not len(bad):
            if len(check) == len(near):
                break
            check = near                          # a last look at every point near the bone
            continue
        pairs = cKDTree(skin[bad]).sparse_distance_matrix(cKDTree(bone), radius, output_type="coo_matrix")
        size = np.zeros(len(bone))            # the largest step any point asks of each bone vertex
        np.maximum.at(size, pairs.col, step * (1.0 - pairs.data / radius))
        push = size[:, None] * inward
        push[frozen] = 0.0
        moved = bone + push
        # a bone point by a pocket (the orbit behind the lids) stops before it leaves the skin
        watch = np.flatnonzero(by_pocket & push.any(axis=1))
        if len(watch):
            out = watch[skin_inside(moved[watch]) < 0.5]
            if len(out):       # slide along the pocket's lining instead of into the pocket
                face = pocket_q.closest_points(moved[out])[1]
                n_out = pocket_n[face]
                p = push[out]
                p -= np.maximum(np.einsum("ij,ij->i", p, n_out), 0.0)[:, None] * n_out
                moved[out] = bone[out] + p
                still = out[skin_inside(moved[out]) < 0.5]
                moved[still], frozen[still] = bone[still], True
        bone = moved
        check = near[cKDTree(skin[bad]).query(skin[near], distance_upper_bound=radius)[0] < np.inf]
    return bone[:n_cr], bone[n_cr:]


def unrelax_under_skin(tpl, parts, pressed, radius=0.008, skin_inside=None, bone_inside=None):
    """Where visible skin still lies inside the relaxed skull (a lid at the orbit's opening), the
    bone within `radius` of it takes back its pressed, unrelaxed place and is cleared again."""
    n_cr = len(parts["cranium"])
    bone = np.vstack([parts["cranium"], parts["mandible"]])
    visible = np.flatnonzero(~tpl.hidden)
    if bone_inside is None:
        bone_inside = winding.FastWinding(bone, tpl.skull_tris, slack=0.001)
    bad = visible[bone_inside.refit(bone)(parts["skin"][visible]) > 0.5]
    if not len(bad):
        return parts["cranium"], parts["mandible"]
    from scipy.spatial import cKDTree

    back = cKDTree(parts["skin"][bad]).query(bone, distance_upper_bound=radius)[0] < np.inf
    bone[back] = np.vstack([pressed["cranium"], pressed["mandible"]])[back]
    return clear_visible_skin(tpl, parts["skin"], bone[:n_cr], bone[n_cr:],
                              skin_inside=skin_inside, bone_inside=bone_inside)


def relax_cleared(tpl, parts, skin_inside, bone_inside, radius=0.008):
    """(cranium, mandible) with the folds that clearing the visible skin left (clear_visible_skin
    pushes the bone by a rim point 1 mm a step, fading over `radius`: neighbours pushed unequally
    turn triangles over) relaxed by geometry.unfold, where that keeps the bone inside the skin
    and every visible skin vertex outside the bone; bone near a skin vertex the relaxation would
    put inside keeps its cleared place (the nearest first: radius/4, /2, then radius; else all of it),
    so no visible vertex is inside the bone that was not before."""
    from scipy.spatial import cKDTree

    from ..mesh.geometry import folded, unfold

    bone = {name: parts[name].copy() for name in ("cranium", "mandible")}
    relaxed_any = False
    for name in bone:
        rest, tris = tpl.parts[name].verts, tpl.parts[name].tris
        if not len(folded(rest, bone[name], tris)):
            continue
        relaxed, moved, _ = unfold(rest, bone[name], tris)
        out = moved & (skin_inside(relaxed) < 0.5)          # relaxed out of the skin: keep the cleared place
        relaxed[out] = bone[name][out]
        bone[name] = relaxed
        relaxed_any = True
    if not relaxed_any:                                    # nothing folded: nothing to check
        return parts["cranium"], parts["mandible"]
    both = np.vstack([bone["cranium"], bone["mandible"]])
    cleared = np.vstack([parts["cranium"], parts["mandible"]])
    visible = np.flatnonzero(~tpl.hidden)

    def inside(b):
        return visible[bone_inside.refit(b)(parts["skin"][visible]) > 0.5]

    before = inside(cleared)                               # left to lift_visible_skin as they were

    def new_inside(b):
        found = inside(b)
        return found[~np.isin(found, before)]

    for reach in (0.25 * radius, 0.5 * radius, radius):     # the narrowest give-back that clears the skin
        bad = new_inside(both)
        if not len(bad):
            break
        back = cKDTree(parts["skin"][bad]).query(both, distance_upper_bound=reach)[0] < np.inf
        both[back] = cleared[back]
    else:
        if len(new_inside(both)):                          # none of it, then
            both = cleared.copy()
    n_cr = len(parts["cranium"])
    return both[:n_cr], both[n_cr:]
