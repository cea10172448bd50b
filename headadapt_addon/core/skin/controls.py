"""The skin model's controls at activation 1: muscle forces (Waters-style linear muscles and
sphincters, and sheet muscles spread over a patch of skin), the cheeks' air pressure and the lips'
push, and the lids turning about the eyeball."""

from __future__ import annotations

import numpy as np

from ..tol import TINY
from . import sight

LID_REACH = 1.7                       # the lid's turn fades to 0 at this many margin radii from the eye axis
LOWER_LID_SHARE = 0.35                # the lower lid at 1 rises this share of the opening (as in a blink)
# Along the fissure the turn is the opening as a person facing the head sees it (sight.py, at rest: at
# each place along the lid axis, the angle about it from the top of the seen eyeball to its bottom),
# measured on each head. (A half-ellipse through the margins' middles left 22% of the eyeball seen,
# median of twelve heads' blinks, up to 37%: the upper margin, sunk onto the lower one's inner row to
# meet FDP 3.3, went inside the eyeball, which showed through the closed lid.)
LID_SIGHT_BIN = 1e-3                  # the seen opening's bins along the fissure, m
LID_OVERLAP = np.radians(6.0)         # the margins turned past each other by this, so no slit stays between
LID_OVERLAP_FULL = np.radians(30.0)   # ... where the opening is at least this; less where it is narrower
                                      # (at the canthi an overlap folded the triangles joining the lids)
LID_TAPER = 4e-3                      # the turn fades to 0 over this much of each end of the seen opening:
                                      # the canthi's triangles join the two lids, and a full turn there
                                      # folded them (2 mm: the relaxation of those folds reopened lids)
LID_PIN = 0.97                        # lid skin turned at least this share stays on its plate while folds
                                      # round it are relaxed (relaxed too, the lid opened again)
LID_RETRY, LID_RETRIES = 0.95, 3      # a closed lid whose held margin leaves a fold is turned again this
                                      # much less far, up to this many times, before its skin is relaxed
                                      # free (which reopened the upper lid alone to 36% of the eyeball seen)
LID_ZONE_RINGS = 6                    # folds within this many rings of a turned lid's skin are first smoothed
                                      # in place a few at a time (positions, not displacement: relaxing the
                                      # displacement pulled the closed lid back up, to 39% of the eyeball
                                      # seen on head 11); elsewhere (a smile's lip corners) as before
LID_FRONT = 0.6                       # the plate fades out over this many margin radii in front of the eye's centre
LID_KINEMATIC = 0.2                   # lid skin turned at least this share is put where its plate takes it
                                      # (the solve's springs shear the lid's thin rim and fold it)
LID_EASE_STEPS, LID_EASE = 12, 0.9     # the lid's placement eases into the skin around it (rings, share)
LID_STIFFNESS = 2.0                   # the whole plate on its turned place (a weak hold where the turn is
                                      # small drags the skin by the canthi along and folds it)
MUSCLE_CONE_DEG = 15.0               # Waters' angular fall-off: zero at this angle off the muscle axis
MUSCLE_BAND = 0.15                    # radial fall-off: zero this fraction of the length from the insertion
MUSCLE_MIN_REACH = 0.008              # short muscles still spread their pull this far (m)
PUFF_REGIONS = ("cheek_l", "mouth_interior")
PUFF_FORWARD = 3.0
FUNNEL_FORWARD = 1.0
PUFF_OFFSET, PUFF_RADIUS = 0.5, 0.9  # puff centre beside the lip corner and reach, in mouth widths
# Muscles spread over a sheet of skin, each a force field on the hypodermis of one side: (centre,
# reach in mouth widths, fall-off power, pull, regions). A centre or a pull point is an FDP, or
# (a, b, t) the point a + t (b - a); a pull is toward a point, or a fixed direction (x, y, z) for
# the left side. Placed after FACS's action units on the faceunits01 shapes they make:
SHEET_MUSCLES = {
    # AU6, the cheek raised: orbicularis oculi's orbital part lifts the cheek's fat pad under the
    # eye, the whole cheek from the lid down to the nose's wing, up and a little out
    "cheek_raiser": (("5.3", "5.1", 0.3), 0.8, 1.0, (0.15, 0.0, 1.0), ("cheek_l", "eyelid_l")),
    # AU9, the nose wrinkled: levator labii superioris alaeque nasi, from the maxilla's frontal
    # process beside the nose bridge to the nose's wing and the lip under it
    "levator_alaeque_nasi": (("9.1", "3.11", 0.1), 0.35, 2.0, ("3.11", "9.1", 0.4),
                             ("nose", "cheek_l", "upper_lip")),
    # AU4's inner part (with AU9): depressor supercilii and procerus pull the brow's inner end
    # down and in toward the nose bone
    "depressor_supercilii": ("4.1", 0.45, 1.0, "9.12", ("brow_l", "forehead", "nose", "eyelid_l")),
}

# Pull of each control at activation 1 (total force, stiffness units x m; angles in degrees,
# slides in m). Fitted so that activation 1 is about the amplitude of the matching ARKit face
# unit of faceunits01 on the template (headless_tests/bench/bench_expressions.py prints the fit).
STRENGTH = {
    "frontalis_inner": 0.35, "frontalis_outer": 0.45, "corrugator": 0.4,
    "levator_labii_superioris": 0.6, "zygomaticus_minor": 0.6, "zygomaticus_major": 1.0,
    "risorius": 0.6, "depressor_anguli_oris": 0.8, "depressor_labii_inferioris": 0.8,
    "mentalis": 3.0, "buccinator": 0.6, "nasalis": 0.4,
    "orbicularis_oris": 0.8, "orbicularis_oculi": 0.6,
    "cheek_puff": 0.8, "lip_push": 0.5, "lip_funnel": 0.6, "depressor_septi": 1.0,
    "cheek_raiser": 1.1, "levator_alaeque_nasi": 0.65, "depressor_supercilii": 0.45,
}


def strength_of(name):
    """Force scale of a control at activation 1 (muscle family name without _l/_r)."""
    base = name[:-2] if name.endswith(("_l", "_r")) else name
    base = base.replace("_upper", "").replace("_lower", "")
    return STRENGTH.get(base, 0.5)


def _mirror_dofs(tpl, idx_l, n):
    """The right side's dof indices (any layer) of left ones, through hm08.mirror."""
    layer, v = np.divmod(idx_l, n)
    return layer * n + tpl.skin_mirror[v]


def _mirror_control(tpl, idx_l, vec_l, n):
    """The right side's force of a left control: vertex through hm08.mirror, x flipped."""
    return _mirror_dofs(tpl, idx_l, n), vec_l * [-1.0, 1.0, 1.0]


def _along_skin(direction, normals):
    """Unit vectors (n,3): each direction with its part along the vertex normal taken out."""
    direction = direction - np.einsum("ij,ij->i", direction, normals)[:, None] * normals
    return direction / np.maximum(np.linalg.norm(direction, axis=1, keepdims=True), TINY)


def _normalised(idx, direction, weight, strength):
    keep = weight > 0
    return idx[keep], direction[keep] * (strength * weight[keep] / max(weight.sum(), TINY))[:, None]


def muscle_forces(tpl, rest, normals, n, muscles, sphincters):
    """Muscle forces on the hypodermis at activation 1: {name: (dof index, force (k,3))}."""
    hyp = rest[2 * n:]
    out = {}
    for mm in muscles:
        inside = tpl.region_mask(*mm["regions"])
        a_pt, i_pt = np.asarray(mm["attachment"]), np.asarray(mm["insertion"])
        below = np.argmin(np.linalg.norm(rest[:n] - i_pt, axis=1))
        i_pt = i_pt + hyp[below] - rest[below]                       # the insertion on the hypodermis
        axis = i_pt - a_pt
        length = np.linalg.norm(axis)
        rel = hyp - a_pt
        dist = np.linalg.norm(rel, axis=1)
        cosang = rel @ axis / np.maximum(dist * length, TINY)
        cone = np.cos(max(np.radians(MUSCLE_CONE_DEG), np.arctan2(MUSCLE_MIN_REACH, length)))
        angular = np.clip((cosang - cone) / (1 - cone), 0, 1)
        radial = np.clip(1 - np.abs(dist - length) / max(MUSCLE_BAND * length, MUSCLE_MIN_REACH), 0, 1)
        w = angular * radial * inside
        direction = _along_skin(-rel, normals)                       # toward the attachment, along the skin
        out[mm["name"]] = _normalised(np.arange(n) + 2 * n, direction, w, strength_of(mm["name"]))
    for sph in sphincters:
        inside = tpl.region_mask(*sph["regions"])
        centre = np.asarray(sph["centre"])
        a, b = (np.asarray(x) for x in sph["axes"])
        rel = hyp - centre
        u, v = rel @ a / (a @ a), rel @ b / (b @ b)
        rho = np.sqrt(u ** 2 + v ** 2)
        w = np.clip(1 - np.abs(rho - 0.8) / 0.6, 0, 1) * inside
        inward = -(u[:, None] * a + v[:, None] * b)
        inward /= np.maximum(np.linalg.norm(inward, axis=1, keepdims=True), TINY)
        out[sph["name"]] = _normalised(np.arange(n) + 2 * n, inward, w, strength_of(sph["name"]))
    return out


def pressure_controls(tpl, skin, normals, fdps, n):
    """Cheek puff (outward, around 5.1/5.2) and lip push (forward, around 8.1/8.2) on the hypodermis."""
    out = {}
    mw = np.linalg.norm(fdps["8.3"] - fdps["8.4"])
    hyp = np.arange(n) + 2 * n
    side_l = np.clip(0.5 + skin[:, 0] / 1e-3, 0, 1)          # 1 on the left, 1/2 on the midline
    cheek = tpl.region_mask(*PUFF_REGIONS)
    centre = fdps["8.3"] + np.array([PUFF_OFFSET * mw, 0.0, 0.0])      # beside the lip corner
    d = np.linalg.norm(skin - centre, axis=1)
    w = np.clip(1 - d / (PUFF_RADIUS * mw), 0, 1) ** 2 * cheek * side_l
    push = normals + PUFF_FORWARD * np.array([0.0, -1.0, 0.0])        # out, and forward as cheeks round
    push /= np.linalg.norm(push, axis=1, keepdims=True)
    idx_l, f_l = _normalised(hyp, push, w, strength_of("cheek_puff"))
    out["cheek_puff_l"] = idx_l, f_l
    out["cheek_puff_r"] = _mirror_control(tpl, idx_l, f_l, n)
    forward = np.tile([0.0, -1.0, 0.0], (n, 1))
    for name, fdp, region in (("lip_push_upper", "8.1", "upper_lip"), ("lip_push_lower", "8.2", "lower_lip")):
        near = tpl.region_mask(region, "mouth_interior")
        d = np.linalg.norm(skin - fdps[fdp], axis=1)
        w = np.clip(1 - d / (0.6 * mw), 0, 1) * near
        out[name] = _normalised(hyp, forward, w, strength_of(name))
    # funnel: the lips flare away from the mouth's centre line and forward (an O-shaped mouth)
    mouth = 0.5 * (fdps["2.2"] + fdps["2.3"])
    lips = tpl.region_mask("upper_lip", "lower_lip", "mouth_interior")
    flare = np.zeros((n, 3))
    flare[:, 2] = np.sign(skin[:, 2] - mouth[2])
    flare += FUNNEL_FORWARD * np.array([0.0, -1.0, 0.0])
    flare /= np.linalg.norm(flare, axis=1, keepdims=True)
    d = np.linalg.norm((skin - mouth)[:, [0, 2]], axis=1)
    w = np.clip(1 - d / (0.5 * mw), 0, 1) * lips
    out["lip_funnel"] = _normalised(hyp, flare, w, strength_of("lip_funnel"))
    # depressor septi: the nose's base (columella, subnasale) pulled down toward the upper lip
    d = np.linalg.norm(skin - fdps["9.15"], axis=1)
    w = np.clip(1 - d / (0.5 * mw), 0, 1) * tpl.region_mask("nose")
    out["depressor_septi"] = _normalised(hyp, np.tile([0.0, 0.0, -1.0], (n, 1)), w, strength_of("depressor_septi"))
    return out


def _point(fdps, spec):
    if isinstance(spec, str):
        return fdps[spec]
    a, b, t = spec
    return fdps[a] + t * (fdps[b] - fdps[a])


def sheet_muscles(tpl, skin, normals, fdps, n):
    """The SHEET_MUSCLES on the hypodermis at activation 1, left (from the left FDPs) and right
    (mirrored): {name_l / name_r: (dof index, force (k,3))}. A force is the pull along the skin,
    weighted (1 - distance / reach) ** power from the centre, inside the regions, on the left side
    (half on the midline)."""
    out = {}
    mw = np.linalg.norm(fdps["8.3"] - fdps["8.4"])
    side_l = np.clip(0.5 + skin[:, 0] / 1e-3, 0, 1)
    for name, (centre, reach, power, pull, regions) in SHEET_MUSCLES.items():
        d = np.linalg.norm(skin - _point(fdps, centre), axis=1)
        w = np.clip(1 - d / (reach * mw), 0, 1) ** power * tpl.region_mask(*regions) * side_l
        fixed = not isinstance(pull, str) and not isinstance(pull[0], str)
        direction = _along_skin(np.tile(pull, (n, 1)) if fixed else _point(fdps, pull) - skin, normals)
        idx_l, f_l = _normalised(np.arange(n) + 2 * n, direction, w, strength_of(name))
        out[name + "_l"] = idx_l, f_l
        out[name + "_r"] = _mirror_control(tpl, idx_l, f_l, n)
    return out


def lid_controls(tpl, skin, parts, fdps, n):
    """Lid plates: {control: (dofs, anchor stiffness, eye centre, angle scale rad, weight, axis)}; a dof
    turns by angle scale x activation x weight.

    A lid turns about the axis through the eyeball's centre parallel to the line of its corners; the
    turn fades from the margin (1) to the orbit's rim (0) and behind the eye's centre, and along the
    fissure it is the opening seen from the front at that place (and LID_OVERLAP more), so at 1 the
    upper margin covers the eyeball down to the lower one all along the fissure, without sinking into
    the eye. The right eye is built as the left of the mirrored head (an adapted head is not
    symmetric), then mirrored back.
    """
    mirror = tpl.skin_mirror
    flip = np.array([-1.0, 1.0, 1.0])
    right_fdps = {a: fdps[b] * flip for a, b in (("3.1", "3.2"), ("3.3", "3.4"), ("3.7", "3.12"), ("3.11", "3.8"))}
    out = {}
    for side in "lr":             # the right eye: the left's construction on the mirrored head
        eye = np.asarray(parts[f"eye_{side}"], dtype=np.float64)
        if side == "l":
            side_skin, side_eye, side_fdps = skin, eye, fdps
        else:
            side_skin, side_eye, side_fdps = skin[mirror] * flip, eye * flip, right_fdps
        centre = side_eye.mean(axis=0)
        plates = _lid_plates(tpl, side_skin, centre, side_fdps, (side_eye, tpl.parts[f"eye_{side}"].tris))
        for which, (v, w, angle, axis) in plates.items():
            idx = np.concatenate([v + layer * n for layer in range(3)])
            wk = np.tile(w, 3)
            if side == "r":       # back to the right side: an axis is a pseudovector
                idx, centre, axis = _mirror_dofs(tpl, idx, n), eye.mean(axis=0), axis * -flip
            out[f"{which}_lid_{side}"] = (idx, np.full(len(idx), LID_STIFFNESS), centre, angle, wk, axis)
    return out


def _lid_plates(tpl, skin, centre, fdps, eye):
    """The left eye's lid plates of skin (n,3), eye (its vertices, triangles): {upper/lower: (vertices,
    weight, angle scale, axis)}."""
    outer, inner = fdps["3.7"], fdps["3.11"]
    axis = (outer - inner) / np.linalg.norm(outer - inner)
    axis = np.array([axis[0], 0.0, axis[2]]) / np.linalg.norm([axis[0], axis[2]])   # no forward tilt
    lid = tpl.region_mask("eyelid_l", "eye_socket_l")
    rel = skin - centre
    along = rel @ axis
    radial = np.linalg.norm(rel - np.outer(along, axis), axis=1)    # distance from the axis
    r_margin = np.linalg.norm(fdps["3.1"] - centre)
    half = 0.5 * np.linalg.norm(outer - inner)
    r1, r3 = (fdps[k] - centre for k in ("3.1", "3.3"))
    r1, r3 = r1 - (r1 @ axis) * axis, r3 - (r3 @ axis) * axis
    down = float(np.sign(np.cross(r1, r3) @ axis)) or 1.0            # the turn that takes 3.1 toward 3.3
    # the angle scale: the margins' middles' angle (the weights below are the opening over it)
    full = max(abs(float(np.arctan2(np.cross(r1, r3) @ axis, r1 @ r3))), LID_OVERLAP)
    line_z = inner[2] + (along - (inner - centre) @ axis) / (2 * half) * (outer[2] - inner[2])
    upper = skin[:, 2] > line_z
    opening = seen_opening(tpl, skin, eye, centre, axis, r1 / max(np.linalg.norm(r1), TINY), down)
    front = np.clip(-rel[:, 1] / (LID_FRONT * r_margin), 0, 1)      # the socket behind the eye stays
    w = (np.clip((LID_REACH * r_margin - radial) / ((LID_REACH - 1.0) * r_margin), 0, 1)
         * opening(along) / full * front * lid)
    out = {}
    for which, mask in (("upper", (w > 0) & upper), ("lower", (w > 0) & ~upper)):
        v = np.flatnonzero(mask)
        out[which] = (v, w[v], full * (1.0 if which == "upper" else LOWER_LID_SHARE), axis)
    return out


def seen_opening(tpl, skin, eye, centre, axis, up, down):
    """The turn (rad) that closes the eye at each place along the lid axis, as a function of that place
    (m from the centre): the angle about the axis between the top and the bottom of the eyeball seen
    from the front at rest (up: a unit direction across the axis, down: the sign of the closing turn),
    LID_OVERLAP more where it is open, fading to 0 over LID_TAPER at its ends. No eyeball seen (the
    eye closed at rest): 0."""
    vis = tpl.skin.tris[~tpl.hidden[tpl.skin.tris].any(axis=1)]
    seen, _ = sight.eyeball_in_sight(skin, vis, eye[0], eye[1])
    if len(seen) < 2:
        return lambda a: np.zeros(np.shape(a))
    rel = seen - centre
    a = rel @ axis
    across = rel - np.outer(a, axis)
    angle = down * np.arctan2(across @ np.cross(axis, up), across @ up)
    edges = np.arange(a.min(), a.max() + LID_SIGHT_BIN, LID_SIGHT_BIN)
    k = np.clip(np.digitize(a, edges) - 1, 0, len(edges) - 2)
    top, bottom = np.full(len(edges) - 1, np.inf), np.full(len(edges) - 1, -np.inf)
    np.minimum.at(top, k, angle)
    np.maximum.at(bottom, k, angle)
    ok = np.isfinite(top)
    at = 0.5 * (edges[1:] + edges[:-1])[ok]
    height = (bottom - top)[ok]
    turn = height + LID_OVERLAP * np.clip(height / LID_OVERLAP_FULL, 0, 1)
    turn *= np.clip((at - a.min()) / LID_TAPER, 0, 1) * np.clip((a.max() - at) / LID_TAPER, 0, 1)
    at, turn = np.r_[a.min() - LID_SIGHT_BIN, at, a.max() + LID_SIGHT_BIN], np.r_[0.0, turn, 0.0]
    return lambda x: np.interp(x, at, turn, left=0.0, right=0.0)
