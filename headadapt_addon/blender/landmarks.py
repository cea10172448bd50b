"""FDP landmarks stored on the scan object (custom property, survives save and reload) and picking.

Landmarks are kept in the object's local coordinates (the scan file's frame and unit), so moving the
object does not move them relative to the surface. Picking is a pure function of a world-space ray.
"""

import json

import numpy as np

from ..core import mpeg4

PROP = "headadapt_landmarks"
SUGGESTED_PROP = "headadapt_suggested"
FLAGGED_PROP = "headadapt_flagged"       # the clicks the last fit judged wrong, each with where it was
# the order the picker walks: the 8 clicks calibration and Suggest the Rest start from, then the rest
GUIDED_ORDER = mpeg4.CLICKS_8 + tuple(k for k in mpeg4.FDPS if k not in mpeg4.CLICKS_8)


def _stored(obj, prop):
    """The JSON object stored in obj's custom property prop ({} when none or unreadable)."""
    if obj is None or prop not in obj:
        return {}
    try:
        data = json.loads(obj[prop])
    except (TypeError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


def get_landmarks(obj, prop=PROP):
    """{FDP id: (3,) local coordinates} stored on obj (empty dict when none)."""
    data = _stored(obj, prop)
    return {k: np.asarray(v, dtype=np.float64) for k, v in sorted(data.items(), key=lambda kv: mpeg4.fdp_sort_key(kv[0]))}


def set_landmarks(obj, points, prop=PROP):
    """Store {FDP id: (3,) local coordinates} on obj, replacing what was there."""
    ordered = {k: [float(c) for c in points[k]] for k in sorted(points, key=mpeg4.fdp_sort_key)}
    obj[prop] = json.dumps(ordered)


def set_flagged(obj, flagged, points):
    """Store the clicks a fit judged wrong ({FDP id: reason}) with where each was when judged (points:
    the clicks it was judged from), replacing what was there; none: nothing stored."""
    kept = {k: {"why": why, "at": [float(c) for c in points[k]]} for k, why in flagged.items() if k in points}
    if kept:
        obj[FLAGGED_PROP] = json.dumps(kept)
    elif FLAGGED_PROP in obj:
        del obj[FLAGGED_PROP]


def get_flagged(obj, points=None):
    """{FDP id: reason} of the clicks the last fit judged wrong that are still where they were judged
    (a click moved or cleared since is judged no more). points: obj's landmarks, if read already."""
    data = _stored(obj, FLAGGED_PROP)
    pts = (get_landmarks(obj) if points is None else points) if data else {}
    return {k: v["why"] for k, v in data.items()
            if k in pts and np.array_equal(pts[k], np.asarray(v.get("at", ()), dtype=np.float64))}


def world_points(obj, points):
    """The same landmarks in world coordinates."""
    m = np.array(obj.matrix_world)
    return {k: m[:3, :3] @ p + m[:3, 3] for k, p in points.items()}


def pick_point(obj, origin, direction, depsgraph=None):
    """First hit of a world-space ray on obj: (hit, local location (3,), face index) -- no change to obj."""
    from mathutils import Vector

    inv = obj.matrix_world.inverted()
    o = inv @ Vector(origin)
    d = (inv.to_3x3() @ Vector(direction)).normalized()
    hit, loc, _normal, face = obj.ray_cast(o, d, depsgraph=depsgraph) if depsgraph else obj.ray_cast(o, d)
    return bool(hit), np.array(loc, dtype=np.float64), int(face)


def next_missing(points, order=None, after=None):
    """The next FDP id (standard order, starting after `after`) that has no point yet, or None."""
    order = list(order or mpeg4.FDPS)
    start = order.index(after) + 1 if after in order else 0
    for name in order[start:] + order[:start]:
        if name not in points:
            return name
    return None


def place(obj, points, name, origin, direction):
    """Place FDP `name` where a world ray hits obj; returns (new points dict, placed?)."""
    hit, loc, _ = pick_point(obj, origin, direction)
    if not hit:
        return points, False
    out = dict(points)
    out[name] = loc
    return out, True


def remove_near(obj, points, origin, direction, radius):
    """Remove the landmark nearest to where a world ray hits obj, if within radius (local units)."""
    hit, loc, _ = pick_point(obj, origin, direction)
    if not hit or not points:
        return points, None
    names = list(points)
    d = np.linalg.norm(np.array([points[k] for k in names]) - loc, axis=1)
    i = int(np.argmin(d))
    if d[i] > radius:
        return points, None
    out = dict(points)
    del out[names[i]]
    return out, names[i]


def mirror_suggestion(points, name):
    """Where the partner of FDP `name` would sit by mirroring its placed partner across the
    midline plane fitted to the placed midline FDPs (local coords), or None."""
    partner = mpeg4.FDPS[name].mirror
    if partner is None or partner not in points:
        return None
    mids = np.array([p for k, p in points.items() if mpeg4.FDPS[k].side == "M"])
    pairs = [(points[k], points[mpeg4.FDPS[k].mirror]) for k in points
             if mpeg4.FDPS[k].mirror in points and mpeg4.FDPS[k].side == "L"]
    if len(pairs) >= 1:
        normal = np.mean([a - b for a, b in pairs], axis=0)
        centre = np.mean([0.5 * (a + b) for a, b in pairs] + list(mids), axis=0)
    else:
        return None
    normal /= np.linalg.norm(normal)
    p = points[partner]
    return p - 2 * np.dot(p - centre, normal) * normal


def seen_from(obj, points_local, eye_world, tolerance=0.05):
    """{FDP id: bool} of landmarks (obj's local coordinates) that the eye (a world point) sees on obj:
    the ray from the eye hits the surface no nearer than the point itself (less tolerance x the
    object's size: a click in a crease, such as an eye corner, lies a few mm behind the lid or nose
    seen from the side), so labels of points round the back of the head are not drawn through it."""
    from mathutils import Vector

    inv = obj.matrix_world.inverted()
    eye = inv @ Vector(eye_world)
    size = max(Vector(obj.bound_box[6]) - Vector(obj.bound_box[0]))
    out = {}
    for k, p in points_local.items():
        to = Vector(p) - eye
        hit, loc, _n, _f = obj.ray_cast(eye, to.normalized(), distance=to.length + size)
        out[k] = (not hit) or (loc - eye).length >= to.length - tolerance * size
    return out


def thinned(points_2d, first=(), min_px=14.0):
    """The FDP ids whose labels are drawn, in drawing order: `first` (the active FDP), then the 8
    clicks, then the rest in the standard order, each left out when its screen point (x, y) lies
    within min_px of a label already kept (labels would overlap)."""
    order = [k for k in first if k in points_2d]
    order += [k for k in mpeg4.CLICKS_8 if k in points_2d and k not in order]
    order += [k for k in sorted(points_2d, key=mpeg4.fdp_sort_key) if k not in order]
    kept = []
    for k in order:
        xy = np.asarray(points_2d[k], dtype=float)
        if all(np.hypot(*(xy - np.asarray(points_2d[j], dtype=float))) >= min_px for j in kept):
            kept.append(k)
    return kept
