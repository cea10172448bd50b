"""Anatomy transfer (paper sec 6.2): skull, mandible, muscles, sphincters, eyes, teeth, tongue, FAPUs.

Everything in the template frame (metres); AdaptResult.to_scan takes points to the scan's frame.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from . import geometry, mpeg4
from .calibration import Similarity
from .winding import FastWinding

# rigid parts and the FDPs that carry them (eq 25-28): x axis (a - b), y axis (c - d), reference set
RIGID_FDPS = {
    "eye_l": (("3.7", "3.11"), ("3.13", "3.9"), ("3.7", "3.9", "3.11", "3.13")),
    "eye_r": (("3.8", "3.12"), ("3.14", "3.10"), ("3.8", "3.10", "3.12", "3.14")),
    "teeth_upper": (("8.3", "8.4"), ("9.15", "8.1"), ("8.3", "8.4", "9.15", "8.1")),
    "teeth_lower": (("8.3", "8.4"), ("8.2", "2.10"), ("8.3", "8.4", "8.2", "2.10")),
    "tongue": (("8.3", "8.4"), ("8.2", "2.10"), ("8.3", "8.4", "8.2", "2.10")),
}


@dataclasses.dataclass
class Anatomy:
    """The transferred anatomy: part vertices, muscle ends, sphincters, FDPs, FAPUs, jaw pivot (m)."""
    parts: dict
    muscles: list
    sphincters: list
    fdps: dict
    fapus: dict
    jaw_pivot: np.ndarray
    rigid: dict


def _frame(p, x_pair, y_pair):
    x = p[x_pair[0]] - p[x_pair[1]]
    y = p[y_pair[0]] - p[y_pair[1]]
    x = x / np.linalg.norm(x)
    y = y - (y @ x) * x
    y /= np.linalg.norm(y)
    return np.stack([x, y, np.cross(x, y)])


def rigid_from_fdps(part_verts, template_fdps, adapted_fdps, x_pair, y_pair, ref, centre=None):
    """The paper's eq 25-28 similarity for a rigid part (uniform scale, rotation, translation).

    Scale: the geometric mean of the two axis-length ratios (eq 25 multiplies them, which would
    scale by an area ratio); rotation: the frame (x, y orthogonalised) of the adapted FDPs times the
    inverse of the template's; the part's centre keeps its offset from the FDPs' mean (eq 26-27),
    unless `centre` (where the adaptation map takes the part's centre) is given.
    """
    s, t = template_fdps, adapted_fdps
    ratio = (np.linalg.norm(t[x_pair[0]] - t[x_pair[1]]) * np.linalg.norm(t[y_pair[0]] - t[y_pair[1]])
             / (np.linalg.norm(s[x_pair[0]] - s[x_pair[1]]) * np.linalg.norm(s[y_pair[0]] - s[y_pair[1]])))
    scale = float(np.sqrt(ratio))
    rot = _frame(t, x_pair, y_pair).T @ _frame(s, x_pair, y_pair)
    c_s = np.asarray(part_verts).mean(axis=0)
    r_s = np.mean([s[k] for k in ref], axis=0)
    r_t = np.mean([t[k] for k in ref], axis=0)
    c_t = r_t - scale * rot @ (r_s - c_s) if centre is None else np.asarray(centre)   # eq 27
    return Similarity(scale, rot, c_t - scale * rot @ c_s)      # eq 28: T(x) = s R (x - c_s) + c_t


HIDDEN_REGIONS = ("mouth_interior", "eye_socket_l", "eye_socket_r")
POCKET_REACH = 0.015          # bone points this close to the pockets' skin may end in one, m
EYE_REACH = 0.010             # an eye's surface is looked for this far beyond the eye, m
EYE_TOLERANCE = 0.0008        # an eye standing out of the scan by more than this goes back, m
LID_GAP = 0.001               # an eye pushed back stops this far behind the scanned lid, m
ORBIT_FULL, ORBIT_FADE = 0.003, 0.020   # the orbit moves with its eye out to these distances beyond it, m


def _hidden(tpl):
    """(n_skin,) mask of the skin that is never seen: the mouth bag, the lids folded behind the eyes."""
    return np.isin(tpl.region, [tpl.region_names.index(r) for r in HIDDEN_REGIONS])


def _pocket_tris(tpl, hidden):
    """Skin triangles (k,3) of the pockets (mouth bag, eye sockets): all corners hidden."""
    return tpl.skin.tris[hidden[tpl.skin.tris].all(axis=1)]


def _within(points, verts, tris, reach):
    """Mask (k,): the points nearer than `reach` to the mesh (verts, tris), by the exact closest point
    on each triangle (spatial.closest_on_triangles, as MeshQuery(backend="numpy") finds it), tried
    only on the triangles that could be that near: those whose bounding ball (about the centroid)
    grown by `reach` holds the point. A point with a corner nearer than `reach` needs no test."""
    from scipy.spatial import cKDTree

    from .spatial import closest_on_triangles

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


def _skin_anchors(skin_verts, faces, bone_template):
    """(face, barycentric, distance) of the closest point of each template bone point on the
    template's visible skin (verts, faces): depends on the template alone, so computed once per
    template and bone in a process (keyed by the arrays' bytes) and then shared by every transfer."""
    import hashlib

    from .spatial import MeshQuery, barycentric

    digest = hashlib.sha256()
    for a in (skin_verts, faces, bone_template):
        a = np.ascontiguousarray(a)
        digest.update(f"{a.dtype.str}{a.shape}".encode())
        digest.update(a.tobytes())
    key = digest.hexdigest()
    if key not in _ANCHORS:
        near, face, depth = MeshQuery(skin_verts, faces).closest_points(bone_template)
        v0 = skin_verts[faces[face]]
        found = (face, barycentric(near, v0[:, 0], v0[:, 1], v0[:, 2]), depth)
        for a in found:
            a.setflags(write=False)
        if len(_ANCHORS) >= 8:
            _ANCHORS.clear()
        _ANCHORS[key] = found
    return _ANCHORS[key]


def keep_inside(tpl, bone_template, bone_mapped, skin_adapted, clearance=0.0015, skin_inside=None):  # noqa: C901
    """Mapped bone points (n,3), moved where needed to at least `clearance` under the adapted skin.

    Each bone point keeps, from the template, its nearest point on the visible skin (face +
    barycentric, not the lids folded behind the eyes nor the mouth bag); where the adapted skin
    there is less than `clearance` above the mapped point (the scan is thinner than the template's
    tissue), the point moves to `clearance` under it along the skin's normal. Any point by a
    pocket of the skin (eye socket, mouth bag) that ends in it goes out through the pocket's lining
    (the mandible's centre, the old way out, lies in the mouth). Template frame, m. skin_inside:
    the adapted skin's FastWinding, if the caller has one (transfer builds it once).
    """
    from .geometry import face_normals
    from .spatial import MeshQuery

    hidden = _hidden(tpl)
    faces = tpl.skin.tris[~hidden[tpl.skin.tris].any(axis=1)]
    face, bary, depth0 = _skin_anchors(tpl.skin.verts, faces, bone_template)
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
            skin_inside = FastWinding(skin_adapted, tpl.skin.tris)
        w = skin_inside(out[near_pocket])
        still = near_pocket[w < 0.5]
        if len(still):                 # out through the pocket's lining, `clearance` into the tissue
            pocket_t = _pocket_tris(tpl, hidden)
            lining, face, _ = MeshQuery(skin_adapted, pocket_t).closest_points(out[still])
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
    `radius` of it steps `step` deeper (fading with distance), each bone vertex along the inward
    normal of the skin vertex the template offset it from. A step that would take a bone point
    into a pocket of the skin (the eye socket behind the lids) slides along the pocket's lining
    instead, or is not taken, so the bone stays inside the skin. skin_inside, bone_inside: the
    skin's and the skull's FastWinding if the caller has them (the skull's is refit as it moves).
    """
    from scipy.spatial import cKDTree

    from .geometry import face_normals, vertex_normals
    from .spatial import MeshQuery

    n_cr = len(cranium)
    bone = np.vstack([cranium, mandible]).astype(np.float64)
    tris = tpl.skull_tris
    hidden = _hidden(tpl)
    visible = np.flatnonzero(~hidden)
    normals = vertex_normals(skin, tpl.skin.tris)
    # each bone vertex deepens along the skin normal of the skin vertex it was offset from
    inward = -normals[np.r_[tpl.bone_skin_index["cranium"], tpl.bone_skin_index["mandible"]]]
    near = visible[_within(skin[visible], bone, tris, 0.002)]
    if skin_inside is None:
        skin_inside = FastWinding(skin, tpl.skin.tris)
    if bone_inside is None:
        bone_inside = FastWinding(bone, tris, slack=step)
    check = near
    by_pocket = cKDTree(skin[hidden]).query(bone, distance_upper_bound=POCKET_REACH)[0] < np.inf
    pocket_t = _pocket_tris(tpl, hidden)
    pocket_q = MeshQuery(skin, pocket_t, backend="numpy")
    pocket_n = face_normals(skin, pocket_t)
    frozen = np.zeros(len(bone), bool)
    for _ in range(rounds):
        w = bone_inside.refit(bone)(skin[check])
        bad = check[w > limit]
        if not len(bad):
            if len(check) == len(near):
                break
            check = near                          # a last look at every point near the bone
            continue
        pairs = cKDTree(skin[bad]).sparse_distance_matrix(cKDTree(bone), radius, output_type="coo_matrix")
        push = np.zeros_like(bone)
        np.add.at(push, pairs.col, (step * (1.0 - pairs.data / radius))[:, None] * inward[pairs.col])
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


def _unrelax_under_skin(tpl, parts, pressed, radius=0.008, skin_inside=None, bone_inside=None):
    """Where visible skin still lies inside the relaxed skull (a lid at the orbit's opening), the
    bone within `radius` of it takes back its pressed, unrelaxed place and is cleared again."""
    n_cr = len(parts["cranium"])
    bone = np.vstack([parts["cranium"], parts["mandible"]])
    visible = np.flatnonzero(~_hidden(tpl))
    if bone_inside is None:
        bone_inside = FastWinding(bone, tpl.skull_tris, slack=0.001)
    bad = visible[bone_inside.refit(bone)(parts["skin"][visible]) > 0.5]
    if not len(bad):
        return parts["cranium"], parts["mandible"]
    from scipy.spatial import cKDTree

    back = cKDTree(parts["skin"][bad]).query(bone, distance_upper_bound=radius)[0] < np.inf
    bone[back] = np.vstack([pressed["cranium"], pressed["mandible"]])[back]
    return clear_visible_skin(tpl, parts["skin"], bone[:n_cr], bone[n_cr:],
                              skin_inside=skin_inside, bone_inside=bone_inside)


def surface_point(verts, tris, ref):
    """Point (3,) of a {"face", "bary"} reference on a mesh (verts (n,3), tris (k,3))."""
    return np.asarray(ref["bary"]) @ verts[tris[ref["face"]]]


def eye_protrusion(scan_query, eye, centre, gaze):
    """How far (m) the front of an eye (vertices (n,3), centre, unit gaze) stands out of the scanned
    surface: along rays from the centre through the middle of the eye's front (within ~25 degrees of
    the gaze, where an open eye shows its cornea and a closed one its lids), the median reach of the
    eye beyond the scan's first hit; 0 where the scan has nothing in front of the eye (a hole).
    Not the maximum: at the lid margins an eye off by a millimetre sideways reaches through them."""
    radial = eye - centre
    r = np.linalg.norm(radial, axis=1)
    front = radial @ gaze > 0.9 * r
    if not front.any():
        return 0.0
    hits = scan_query.ray_cast(np.repeat(centre[None], front.sum(), axis=0), radial[front],
                               r[front] + EYE_REACH, both_ways=False)
    if not hits.hit.any():
        return 0.0
    return max(float(np.median(r[front][hits.hit] - hits.t[hits.hit])), 0.0)


def seat_orbits(tpl, scan, parts, rigid, mapped):
    """Eyes that stand out of the scan by over EYE_TOLERANCE (closed or deep-set lids lie behind
    where the map put the eye) go back along their gaze until LID_GAP behind it, and the orbit goes
    with them: the eye socket's lining and the bone around the eye (`mapped`: {bone: (n,3)} through
    the map) move by the same push, fading out with distance. parts[eye] and rigid[eye] are updated;
    returns (skin with the sockets moved, bone offsets {bone: (n,3)}), template frame, m."""
    skin = parts["skin"].copy()
    offsets = {b: np.zeros_like(p) for b, p in mapped.items()}
    if scan is None:
        return skin, offsets
    socket = np.isin(tpl.region, [tpl.region_names.index(r) for r in ("eye_socket_l", "eye_socket_r")])
    for eye in ("eye_l", "eye_r"):
        sim = rigid[eye]
        centre = parts[eye].mean(axis=0)
        radius = float(np.linalg.norm(parts[eye] - centre, axis=1).mean())
        g0 = np.asarray(tpl.meta["eyes"][eye]["gaze"])
        gaze = sim.rotation @ (g0 / np.linalg.norm(g0))
        push = eye_protrusion(scan.query, parts[eye], centre, gaze)
        if push <= EYE_TOLERANCE:       # within what the FDP-carried eye is off anyway (open eyes)
            continue
        shift = -(push + LID_GAP) * gaze

        def fade(points):
            d = np.linalg.norm(points - centre, axis=1) - radius
            t = np.clip((d - ORBIT_FULL) / (ORBIT_FADE - ORBIT_FULL), 0.0, 1.0)
            return (1.0 - t * t * (3.0 - 2.0 * t))[:, None] * shift

        parts[eye] = parts[eye] + shift
        rigid[eye] = dataclasses.replace(sim, translation=sim.translation + shift)
        skin[socket] += fade(skin[socket])
        for b in offsets:
            offsets[b] += fade(mapped[b])
    return skin, offsets


def transfer(tpl, result):
    """Carry the template's anatomy onto the adapted head of an AdaptResult (template frame, m)."""
    parts = {"skin": result.verts}
    tris = {name: part.tris for name, part in tpl.parts.items()}
    tpl_fdps = tpl.fdp_points()
    fdps = {}
    for name, ref in tpl.meta["fdps"].items():
        if ref["part"] == "skin":
            fdps[name] = surface_point(parts["skin"], tris["skin"], ref)
    rigid = {}
    for name, (x_pair, y_pair, ref) in RIGID_FDPS.items():
        # centre through the map (it carries the socket around the part), scale and turn by eq 25
        centre = result.map_points(tpl.parts[name].verts.mean(axis=0)[None])[0]
        sim = rigid_from_fdps(tpl.parts[name].verts, tpl_fdps, fdps, x_pair, y_pair, ref, centre)
        rigid[name] = sim
        parts[name] = sim.apply(tpl.parts[name].verts)
    # the skull through the final map (all last-level FPs)
    mapped = {name: result.map_points(tpl.parts[name].verts) for name in ("cranium", "mandible")}
    parts["skin"], offsets = seat_orbits(tpl, result.scan, parts, rigid, mapped)
    # the inside tests of the rest: the adapted skin's built once, the skull's refit as it moves
    skin_inside = FastWinding(parts["skin"], tris["skin"])
    pressed = {}
    for name in mapped:
        pressed[name] = keep_inside(tpl, tpl.parts[name].verts, mapped[name] + offsets[name], parts["skin"],
                                    skin_inside=skin_inside)
        # each point goes under its own skin point: neighbours pressed different ways fold the
        # bone (orbit floors, cheeks); relax the folds, giving back as much of the press as can be
        relaxed = geometry.unfold(tpl.parts[name].verts, pressed[name], tris[name])[0]
        lifted = skin_inside(relaxed) < 0.5    # out of the skin again
        relaxed[lifted] = pressed[name][lifted]
        parts[name] = relaxed
    # the skull's: clear_visible_skin moves it a step (1 mm) at a time; its grid keeps for a step
    bone_inside = FastWinding(np.vstack([parts["cranium"], parts["mandible"]]), tpl.skull_tris, slack=0.001)
    parts["cranium"], parts["mandible"] = clear_visible_skin(tpl, parts["skin"], parts["cranium"], parts["mandible"],
                                                             skin_inside=skin_inside, bone_inside=bone_inside)
    parts["cranium"], parts["mandible"] = _unrelax_under_skin(tpl, parts, pressed, skin_inside=skin_inside,
                                                              bone_inside=bone_inside)
    for name, ref in tpl.meta["fdps"].items():
        if ref["part"] != "skin":
            fdps[name] = surface_point(parts[ref["part"]], tris[ref["part"]], ref)

    muscles = []
    for m in tpl.meta["muscles"]:
        muscles.append({"name": m["name"], "regions": m["regions"],
                        "attachment": surface_point(parts[m["attachment"]["part"]], tris[m["attachment"]["part"]],
                                                    m["attachment"]),
                        "insertion": surface_point(parts[m["insertion"]["part"]], tris[m["insertion"]["part"]],
                                                   m["insertion"])})
    sphincters = []
    for sph in tpl.meta["sphincters"]:
        centre = result.map_points(np.asarray(sph["centre"])[None])[0]
        axes = []
        for axis, (a, b) in zip(sph["axes"], sph["scale_pairs"]):
            ratio = np.linalg.norm(fdps[a] - fdps[b]) / np.linalg.norm(tpl_fdps[a] - tpl_fdps[b])
            axes.append(np.asarray(axis) * ratio)
        sphincters.append({"name": sph["name"], "centre": centre, "axes": axes, "regions": sph["regions"]})
    pivot = result.map_points(np.asarray(tpl.meta["jaw"]["pivot"])[None])[0]
    return Anatomy(parts=parts, muscles=muscles, sphincters=sphincters, fdps=fdps,
                   fapus=mpeg4.measure_fapus(fdps), jaw_pivot=pivot, rigid=rigid)
