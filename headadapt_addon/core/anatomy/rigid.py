"""Parts carried rigidly by their FDPs (paper eq 25-28): eyes, teeth, tongue; the eyes seated in
their orbits where the scan says they stand out."""

from __future__ import annotations

import dataclasses

import numpy as np

from ..adapt.calibration import Similarity
from ..mesh.spatial import MeshQuery

# rigid parts and the FDPs that carry them (eq 25-28): x axis (a - b), y axis (c - d), reference set
RIGID_FDPS = {
    "eye_l": (("3.7", "3.11"), ("3.13", "3.9"), ("3.7", "3.9", "3.11", "3.13")),
    "eye_r": (("3.8", "3.12"), ("3.14", "3.10"), ("3.8", "3.10", "3.12", "3.14")),
    "teeth_upper": (("8.3", "8.4"), ("9.15", "8.1"), ("8.3", "8.4", "9.15", "8.1")),
    "teeth_lower": (("8.3", "8.4"), ("8.2", "2.10"), ("8.3", "8.4", "8.2", "2.10")),
    "tongue": (("8.3", "8.4"), ("8.2", "2.10"), ("8.3", "8.4", "8.2", "2.10")),
}


def _frame(p, x_pair, y_pair):
    x = p[x_pair[0]] - p[x_pair[1]]
    y = p[y_pair[0]] - p[y_pair[1]]
    x = x / np.linalg.norm(x)
    y = y - (y @ x) * x
    y /= np.linalg.norm(y)
    return np.stack([x, y, np.cross(x, y)])


def rigid_from_fdps(part_verts, template_fdps, adapted_fdps, x_pair, y_pair, ref, centre=None, scale=None):
    """The paper's eq 25-28 similarity for a rigid part (uniform scale, rotation, translation).

    Scale: the geometric mean of the two axis-length ratios (eq 25 multiplies them, which would
    scale by an area ratio), unless `scale` is given; rotation: the frame (x, y orthogonalised) of the
    adapted FDPs times the inverse of the template's; the part's centre keeps its offset from the
    FDPs' mean (eq 26-27), unless `centre` (where the adaptation map takes the part's centre) is given.
    """
    s, t = template_fdps, adapted_fdps
    if scale is None:
        ratio = (np.linalg.norm(t[x_pair[0]] - t[x_pair[1]]) * np.linalg.norm(t[y_pair[0]] - t[y_pair[1]])
                 / (np.linalg.norm(s[x_pair[0]] - s[x_pair[1]]) * np.linalg.norm(s[y_pair[0]] - s[y_pair[1]])))
        scale = float(np.sqrt(ratio))
    rot = _frame(t, x_pair, y_pair).T @ _frame(s, x_pair, y_pair)
    c_s = np.asarray(part_verts).mean(axis=0)
    r_s = np.mean([s[k] for k in ref], axis=0)
    r_t = np.mean([t[k] for k in ref], axis=0)
    c_t = r_t - scale * rot @ (r_s - c_s) if centre is None else np.asarray(centre)   # eq 27
    return Similarity(scale, rot, c_t - scale * rot @ c_s)      # eq 28: T(x) = s R (x - c_s) + c_t


# The eyes keep the template's size in the calibrated head (the calibration's scale, one for both):
# eq 25 scales each eye by its own lids' opening and width, which say how open the eye is, not how
# big the eyeball is (adult eyeballs differ little); on 20 scan-like heads (seeds 300-319) eq 25
# made the two eyes differ by up to 2.2 mm in radius and lay a mean 1.44 mm from the generator's
# radius, the head's scale 1.15 mm
EYE_SCALE = 1.0
EYE_REACH = 0.010             # an eye's surface is looked for this far beyond the eye, m
EYE_TOLERANCE = 0.0008        # an eye standing out of the scan by more than this goes back, m
LID_GAP = 0.001               # an eye pushed back stops this far behind the scanned lid, m
LID_SKIN = 0.0005             # adapted skin this far beyond a ray's scan hit still makes it a lid's, m
SEEN_RAYS = 3                 # an eye seen along this many front rays between the lids is met where it is seen
ORBIT_FULL, ORBIT_FADE = 0.003, 0.020   # the orbit moves with its eye out to these distances beyond it, m


def surface_point(verts, tris, ref):
    """Point (3,) of a {"face", "bary"} reference on a mesh (verts (n,3), tris (k,3))."""
    return np.asarray(ref["bary"]) @ verts[tris[ref["face"]]]


def _front_reach(scan_query, eye, centre, gaze, skin_query=None):
    """(reach (k,), through (k,) bool) along rays from an eye's centre through the middle of its front
    (within ~25 degrees of the gaze): how far the eye reaches beyond the scan's first hit (m), for the
    rays that hit the scan; `through`: the ray meets no adapted skin (skin_query) before, at or just
    beyond (LID_SKIN) the scan's hit, so what it meets is the scanned eye seen through the lids'
    opening, not a lid (a lid's adapted skin lies on the scanned one)."""
    radial = eye - centre
    r = np.linalg.norm(radial, axis=1)
    front = radial @ gaze > 0.9 * r
    if not front.any():
        return np.zeros(0), np.zeros(0, bool)
    origins = np.repeat(centre[None], front.sum(), axis=0)
    hits = scan_query.ray_cast(origins, radial[front], r[front] + EYE_REACH, both_ways=False)
    reach = (r[front] - hits.t)[hits.hit]
    if skin_query is None:
        return reach, np.zeros(len(reach), bool)
    skin = skin_query.ray_cast(origins[hits.hit], radial[front][hits.hit], hits.t[hits.hit] + LID_SKIN,
                               both_ways=False)
    return reach, ~skin.hit


def eye_protrusion(scan_query, eye, centre, gaze):
    """How far (m) the front of an eye (vertices (n,3), centre, unit gaze) stands out of the scanned
    surface: along rays from the centre through the middle of the eye's front (within ~25 degrees of
    the gaze, where an open eye shows its cornea and a closed one its lids), the median reach of the
    eye beyond the scan's first hit; 0 where the scan has nothing in front of the eye (a hole).
    Not the maximum: at the lid margins an eye off by a millimetre sideways reaches through them."""
    return _out_by(_front_reach(scan_query, eye, centre, gaze)[0])


def _out_by(reach):
    """The median of an eye's reaches beyond the scan (_front_reach), not below 0; 0 for none."""
    return max(float(np.median(reach)), 0.0) if len(reach) else 0.0


def seat_orbits(tpl, scan, parts, rigid, mapped):
    """Each eye's depth along its gaze from the scan, and the orbit moved with it: an eye that stands
    out of what the scan shows through the adapted lids' opening (an open eye, scanned) goes back until
    its front meets it; one the adapted lids cover (deep-set, or the map put it out through them) goes
    back, if it stands out by over EYE_TOLERANCE, until LID_GAP behind them. An eye is never brought
    forward. The template's lids stay open on a scan with closed eyes, so there the scanned lid
    between them counts as the eye: the eye goes back until it meets the lid, not LID_GAP behind it.
    The eye socket's lining and the bone around the eye (`mapped`: {bone: (n,3)} through the map) move
    by the same shift, fading out with distance. parts[eye] and rigid[eye] are updated; returns (skin
    with the sockets moved, bone offsets {bone: (n,3)}), template frame, m."""
    skin = parts["skin"].copy()
    offsets = {b: np.zeros_like(p) for b, p in mapped.items()}
    if scan is None:
        return skin, offsets
    skin_query = MeshQuery(parts["skin"], tpl.skin.tris)
    socket = tpl.region_mask("eye_socket_l", "eye_socket_r")
    for eye in ("eye_l", "eye_r"):
        sim = rigid[eye]
        centre = parts[eye].mean(axis=0)
        radius = float(np.linalg.norm(parts[eye] - centre, axis=1).mean())
        g0 = np.asarray(tpl.meta["eyes"][eye]["gaze"])
        gaze = sim.rotation @ (g0 / np.linalg.norm(g0))
        reach, through = _front_reach(scan.query, parts[eye], centre, gaze, skin_query)
        if through.sum() >= SEEN_RAYS:          # the scanned eye, seen between the lids: meet it
            push = float(np.median(reach[through]))
            if push <= 0.0:
                continue
            shift = -push * gaze
        else:
            push = _out_by(reach)
            if push <= EYE_TOLERANCE:       # within what the FDP-carried eye is off anyway
                continue
            shift = -(push + LID_GAP) * gaze

        def fade(points, centre=centre, radius=radius, shift=shift):
            d = np.linalg.norm(points - centre, axis=1) - radius
            t = np.clip((d - ORBIT_FULL) / (ORBIT_FADE - ORBIT_FULL), 0.0, 1.0)
            return (1.0 - t * t * (3.0 - 2.0 * t))[:, None] * shift

        parts[eye] = parts[eye] + shift
        rigid[eye] = dataclasses.replace(sim, translation=sim.translation + shift)
        skin[socket] += fade(skin[socket])
        for b in offsets:
            offsets[b] += fade(mapped[b])
    return skin, offsets
