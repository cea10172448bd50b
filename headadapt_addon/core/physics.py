"""Three-layer skin (paper sec 6.1) driven by muscles, jaw and lids, solved quasi-statically.

Layers: epidermis (the skin mesh), dermis and hypodermis below it along the inward normal, at
fractions of the local soft-tissue depth to the skull. Springs within each layer (along mesh
edges), between layers (vertical and diagonal) and from the hypodermis to the bone under it
(cranium fixed, mandible turning about the jaw pivot). The dermis is the most deformable layer.
Springs are linearised about the rest shape (energy sum k |(x_i - x_j) - (X_i - X_j)|^2), so the
equilibrium for any set of controls is one solve with the same sparse factorisation: fast and
stable, no time steps.

Controls, each with an activation (0 = rest, 1 = full):
- linear muscles (Waters-style angular and radial fall-off) and sphincters (on their ellipse)
  pull the hypodermis inside their regions;
- `jaw_open` turns the mandible about the jaw pivot, `jaw_thrust` / `jaw_shift` slide it; the
  skin follows through its springs to the bone;
- `upper_lid_l/r`, `lower_lid_l/r` turn the lids about the eyeball's centre (the tarsal plate
  riding on the eye), 1 = the margin reaches the opposite lid's margin;
- `cheek_puff_l/r` push the cheeks out (air pressure in the mouth);
- `lip_push_upper/lower` push the lips forward (the lip's own protrusion).
Template frame (or the adapted head's, same axes), metres.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy import sparse
from scipy.sparse.linalg import splu
from scipy.spatial.transform import Rotation

from . import geometry, spatial

LAYER_DEPTHS = (0.0, 0.3, 0.7)        # fractions of the tissue depth: epidermis, dermis, hypodermis
STIFFNESS = {"epidermis": 1.0, "dermis": 0.3, "hypodermis": 0.8, "vertical": 0.6, "diagonal": 0.2}
BONE_STIFFNESS = 2.0                  # hypodermis to bone
LOOSE_BONE_STIFFNESS = 0.15           # under the lips and cheeks, where the skin slides
LOOSE_REGIONS = ("upper_lip", "lower_lip", "cheek_l", "cheek_r", "mouth_interior", "neck")
JAW_STIFFNESS = 50.0                  # hypodermis on the mandible (outside the lips)
LID_REACH = 1.7                       # the lid's turn fades to 0 at this many margin radii from the eye axis
LID_STIFFNESS = 5.0                   # lid skin on its tarsal plate
MUSCLE_CONE_DEG = 15.0               # Waters' angular fall-off: zero at this angle off the muscle axis
MUSCLE_BAND = 0.15                    # radial fall-off: zero this fraction of the length from the insertion
MUSCLE_MIN_REACH = 0.008              # short muscles still spread their pull this far (m)
PUFF_REGIONS = ("cheek_l", "mouth_interior")
PUFF_FORWARD = 3.0
FUNNEL_FORWARD = 1.0
PUFF_OFFSET, PUFF_RADIUS = 0.5, 0.9  # puff centre beside the lip corner and reach, in mouth widths
UNFOLD_STEPS = 80                     # most local relaxation steps against folded triangles
NON_PENETRATION = 0.001               # skin stays at least this far outside the bone, m
HIDDEN_REGIONS = ("mouth_interior", "eye_socket_l", "eye_socket_r")

# Pull of each control at activation 1 (total force, stiffness units x m; angles in degrees,
# slides in m). Fitted so that activation 1 is about the amplitude of the matching ARKit face
# unit of faceunits01 on the template (headless_tests/bench/bench_expressions.py prints the fit).
STRENGTH = {
    "frontalis_inner": 0.35, "frontalis_outer": 0.45, "corrugator": 0.4,
    "levator_labii_superioris": 0.6, "zygomaticus_minor": 0.6, "zygomaticus_major": 1.0,
    "risorius": 0.6, "depressor_anguli_oris": 0.8, "depressor_labii_inferioris": 0.8,
    "mentalis": 1.5, "buccinator": 0.6, "nasalis": 0.4,
    "orbicularis_oris": 0.8, "orbicularis_oculi": 0.6,
    "cheek_puff": 0.8, "lip_push": 0.5, "lip_funnel": 0.6, "depressor_septi": 1.0,
}
JAW_OPEN_DEG = 22.0                   # jaw_open = 1: a wide-open mouth (ARKit jawOpen turns about 27 deg)
JAW_SLIDE = 0.004                     # jaw_thrust / jaw_shift = 1, m


def strength_of(name):
    """Force scale of a control at activation 1 (muscle family name without _l/_r)."""
    base = name[:-2] if name.endswith(("_l", "_r")) else name
    base = base.replace("_upper", "").replace("_lower", "")
    return STRENGTH.get(base, 0.5)


@dataclasses.dataclass
class SkinModel:
    """The assembled mass-spring model: rest positions (3n,3), factorised stiffness, controls."""
    n: int
    rest: np.ndarray
    solve: object
    matrix: object                # the (3n,3n) sparse stiffness the solve factorised
    forces: dict                  # control -> (dof index (k,), force (k,3) at activation 1)
    bone_k: np.ndarray            # (n,) hypodermis-to-bone stiffness
    on_mandible: np.ndarray       # (n,) hypodermis vertex rides on the mandible
    jaw_pivot: np.ndarray
    jaw_axis: np.ndarray
    lids: dict                    # control -> (dofs (k,), stiffness (k,), eye centre, full angle rad, weight (k,), axis)
    bone_point: np.ndarray        # (n,3) nearest bone point of each skin vertex at rest
    bone_normal: np.ndarray       # (n,3) outward bone normal there
    free: np.ndarray              # (n,) vertices the non-penetration applies to
    clearance: np.ndarray         # (n,) least gap kept to the bone
    tris: np.ndarray              # (t,3) skin triangles
    rest_tri_normal: np.ndarray   # (t,3) their normals at rest (area-weighted)
    tri_ok: np.ndarray            # (t,) not degenerate at rest
    adjacency: object             # (n,n) sparse, row-normalised vertex neighbours

    @property
    def controls(self):
        """Names of every control this model takes an activation for."""
        return (*self.forces, "jaw_open", "jaw_thrust", "jaw_shift", *self.lids)

    def mandible_transform(self, activations):
        """(R, t) of the mandible for the jaw controls: x -> R (x - pivot) + pivot + t, metres."""
        a = activations or {}
        rot = Rotation.from_rotvec(np.radians(JAW_OPEN_DEG * a.get("jaw_open", 0.0)) * self.jaw_axis).as_matrix()
        t = JAW_SLIDE * (a.get("jaw_thrust", 0.0) * np.array([0.0, -1.0, 0.0])
                         + a.get("jaw_shift", 0.0) * np.array([-1.0, 0.0, 0.0]))
        return rot, t

    def equilibrium(self, activations=None):
        """Skin (epidermis) positions (n,3) at equilibrium for {control: activation}, metres."""
        activations = {k: float(v) for k, v in (activations or {}).items() if v}
        unknown = set(activations) - set(self.controls)
        if unknown:
            raise KeyError(f"unknown control(s): {', '.join(sorted(unknown))}")
        f = np.zeros_like(self.rest)
        for name, (idx, force) in self.forces.items():
            if name in activations:
                np.add.at(f, idx, activations[name] * force)
        rot, t = self.mandible_transform(activations)
        jaw_moves = bool(activations.keys() & {"jaw_open", "jaw_thrust", "jaw_shift"})
        if jaw_moves:
            hyp = slice(2 * self.n, 3 * self.n)
            rest_h = self.rest[hyp]
            target = (rest_h - self.jaw_pivot) @ rot.T + self.jaw_pivot + t
            f[hyp] += np.where(self.on_mandible[:, None], self.bone_k[:, None] * (target - rest_h), 0.0)
        for name, (idx, k, centre, full, weight, axis) in self.lids.items():
            if name in activations:
                sign = 1.0 if name.startswith("upper") else -1.0
                angle = (sign * full * activations[name] * weight)[:, None]
                rel = self.rest[idx] - centre                 # Rodrigues, one angle per dof
                turned = (rel * np.cos(angle) + np.cross(axis, rel) * np.sin(angle)
                          + np.outer(rel @ axis, axis) * (1 - np.cos(angle)))
                f[idx] += k[:, None] * (turned - rel)
        u = self.solve(f)
        x = self.rest[: self.n] + u[: self.n]
        # skull non-penetration: no skin closer than the clearance to the bone (tangent plane of
        # the nearest bone point, which moves with the mandible)
        bp, bn = self.bone_point, self.bone_normal
        if jaw_moves:
            bp = np.where(self.on_mandible[:, None], (bp - self.jaw_pivot) @ rot.T + self.jaw_pivot + t, bp)
            bn = np.where(self.on_mandible[:, None], bn @ rot.T, bn)
        x = self._keep_out_of_bone(x, bp, bn)
        return self._unfold(x, bp, bn)

    def _keep_out_of_bone(self, x, bp, bn):
        gap = np.einsum("ij,ij->i", x - bp, bn)
        deficit = np.where(self.free, np.maximum(self.clearance - gap, 0.0), 0.0)
        for _ in range(3):              # neighbours share part of a push, so it shears no triangle
            deficit = np.maximum(deficit, 0.6 * (self.adjacency @ deficit)) * self.free
        return x + deficit[:, None] * bn

    def flipped(self, x):
        """Indices of skin triangles whose normal turned against its rest normal at positions x (n,3)."""
        t = self.tris
        nrm = np.cross(x[t[:, 1]] - x[t[:, 0]], x[t[:, 2]] - x[t[:, 0]])
        return np.flatnonzero((np.einsum("ij,ij->i", nrm, self.rest_tri_normal) <= 0) & self.tri_ok)

    def _unfold(self, x, bp, bn):
        """Relax the displacement around folded triangles (Jacobi steps toward the neighbours' mean).

        Springs that only resist stretch let tiny triangles (lip corners, lid margins) fold under
        concentrated pulls; a few local smoothing steps of the displacement field undo that.
        """
        rest = self.rest[: self.n]
        patch = np.zeros(self.n, bool)
        for _ in range(UNFOLD_STEPS):
            bad = self.flipped(x)
            if not len(bad):
                break
            patch[self.tris[bad].ravel()] = True
            patch |= (self.adjacency @ patch.astype(float)) > 0        # the patch grows until it unfolds
            for _ in range(10):
                u = x - rest
                x[patch] = rest[patch] + (self.adjacency @ u)[patch]
            x = self._keep_out_of_bone(x, bp, bn)
        return x


def _edges(tris):
    e = np.sort(np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]]), axis=1)
    return np.unique(e, axis=0)


def _regions(tpl, names):
    return np.isin(tpl.region, [tpl.region_names.index(r) for r in names])


def _mirror_dofs(tpl, idx_l, n):
    """The right side's dof indices (any layer) of left ones, through hm08.mirror."""
    layer, v = np.divmod(idx_l, n)
    return layer * n + tpl.skin_mirror[v]


def _mirror_control(tpl, idx_l, vec_l, n):
    """The right side's force of a left control: vertex through hm08.mirror, x flipped."""
    return _mirror_dofs(tpl, idx_l, n), vec_l * [-1.0, 1.0, 1.0]


def _normalised(idx, direction, weight, strength):
    keep = weight > 0
    return idx[keep], direction[keep] * (strength * weight[keep] / max(weight.sum(), 1e-12))[:, None]


def build(tpl, anatomy=None):
    """Assemble the skin model of the template, or of an adapted head from its transferred Anatomy."""
    if anatomy is None:
        parts = {k: p.verts for k, p in tpl.parts.items()}
        fdps = tpl.fdp_points()
        muscles = [{"name": m["name"], "regions": m["regions"], "attachment": tpl.surface_point(m["attachment"]),
                    "insertion": tpl.surface_point(m["insertion"])} for m in tpl.meta["muscles"]]
        sphincters, jaw_pivot = tpl.meta["sphincters"], tpl.meta["jaw"]["pivot"]
    else:
        parts, fdps = anatomy.parts, anatomy.fdps
        muscles, sphincters, jaw_pivot = anatomy.muscles, anatomy.sphincters, anatomy.jaw_pivot
    skin, tris = parts["skin"], tpl.skin.tris
    n = len(skin)
    normals = geometry.vertex_normals(skin, tris)
    bone_v = np.vstack([parts["cranium"], parts["mandible"]])
    bone_t = np.vstack([tpl.parts["cranium"].tris, tpl.parts["mandible"].tris + len(parts["cranium"])])
    closest, face, depth = spatial.MeshQuery(bone_v, bone_t, backend="numpy").closest_points(skin)
    on_mandible = face >= len(tpl.parts["cranium"].tris)
    # outward direction of the distance to the bone (robust at the bone's openings and folds)
    bone_fn = skin - closest
    bone_fn /= np.maximum(np.linalg.norm(bone_fn, axis=1, keepdims=True), 1e-12)
    # the head is symmetric by construction: make the bone data exactly so (mirrored controls
    # then give mirrored shapes to rounding)
    if anatomy is None:
        right, mir = skin[:, 0] < 0, tpl.skin_mirror
        closest[right], bone_fn[right] = closest[mir[right]] * [-1, 1, 1], bone_fn[mir[right]] * [-1, 1, 1]
        depth[right], on_mandible[right] = depth[mir[right]], on_mandible[mir[right]]
        mid = np.abs(skin[:, 0]) < 1e-9                    # midline: the bone normal has no sideways part
        closest[mid, 0], bone_fn[mid, 0] = 0.0, 0.0
        bone_fn[mid] /= np.maximum(np.linalg.norm(bone_fn[mid], axis=1, keepdims=True), 1e-12)

    hidden = _regions(tpl, HIDDEN_REGIONS)
    depth = np.clip(np.where(hidden, 0.002, depth), 0.001, 0.02)
    rest = np.vstack([skin - (f * depth)[:, None] * normals for f in LAYER_DEPTHS])

    e = _edges(tris)
    rows, cols, ks = [], [], []
    for layer, name in enumerate(("epidermis", "dermis", "hypodermis")):
        rows.append(e[:, 0] + layer * n), cols.append(e[:, 1] + layer * n), ks.append(np.full(len(e), STIFFNESS[name]))
    idx = np.arange(n)
    for a, b in ((0, 1), (1, 2)):
        rows.append(idx + a * n), cols.append(idx + b * n), ks.append(np.full(n, STIFFNESS["vertical"]))
        for s, t in ((0, 1), (1, 0)):
            rows.append(e[:, s] + a * n), cols.append(e[:, t] + b * n), ks.append(np.full(len(e), STIFFNESS["diagonal"]))
    r, c, k = np.concatenate(rows), np.concatenate(cols), np.concatenate(ks)
    m = 3 * n
    A = sparse.coo_matrix((np.r_[-k, -k], (np.r_[r, c], np.r_[c, r])), shape=(m, m)).tocsr()
    A = A - sparse.diags(np.asarray(A.sum(axis=1)).ravel())
    loose = _regions(tpl, LOOSE_REGIONS)
    bone_k = np.where(loose, LOOSE_BONE_STIFFNESS, BONE_STIFFNESS)
    bone_k = np.where(on_mandible & ~loose, JAW_STIFFNESS, bone_k)      # the chin follows the mandible
    neck = geometry.boundary_vertices(tris, n) & tpl.region_mask("neck")   # the cut edge holds the head
    anchor = np.zeros(m)
    anchor[2 * n:] = bone_k
    anchor[np.flatnonzero(neck)] += 10.0

    lids = _lid_controls(tpl, skin, parts, fdps, n)
    for idx_l, k_l, *_ in lids.values():
        np.add.at(anchor, idx_l, k_l)
    matrix = (A + sparse.diags(anchor)).tocsc()
    lu = splu(matrix)

    def solve(f):
        return np.column_stack([lu.solve(np.ascontiguousarray(f[:, d])) for d in range(3)])

    forces = _muscle_forces(tpl, rest, normals, n, muscles, sphincters)
    forces.update(_pressure_controls(tpl, skin, normals, fdps, n))

    rest_gap = np.einsum("ij,ij->i", skin - closest, bone_fn)
    jaw = tpl.meta["jaw"]
    tri_n = np.cross(skin[tris[:, 1]] - skin[tris[:, 0]], skin[tris[:, 2]] - skin[tris[:, 0]])
    adj = sparse.coo_matrix((np.ones(2 * len(e)), (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])), shape=(n, n)).tocsr()
    adj = sparse.diags(1.0 / np.maximum(np.asarray(adj.sum(axis=1)).ravel(), 1)) @ adj
    return SkinModel(tris=tris, rest_tri_normal=tri_n, tri_ok=np.linalg.norm(tri_n, axis=1) > 1e-14, adjacency=adj,
                     n=n, rest=rest, solve=solve, matrix=matrix, forces=forces, bone_k=bone_k, on_mandible=on_mandible,
                     jaw_pivot=np.asarray(jaw_pivot, dtype=float), jaw_axis=np.asarray(jaw["axis"]), lids=lids,
                     bone_point=closest, bone_normal=bone_fn, free=~hidden & (rest_gap > 0),
                     clearance=np.minimum(NON_PENETRATION, 0.9 * np.maximum(rest_gap, 0)))


def _muscle_forces(tpl, rest, normals, n, muscles, sphincters):
    """Muscle forces on the hypodermis at activation 1: {name: (dof index, force (k,3))}."""
    hyp = rest[2 * n:]
    out = {}
    for mm in muscles:
        inside = _regions(tpl, mm["regions"])
        a_pt, i_pt = np.asarray(mm["attachment"]), np.asarray(mm["insertion"])
        axis = i_pt - a_pt
        length = np.linalg.norm(axis)
        rel = hyp - a_pt
        dist = np.linalg.norm(rel, axis=1)
        cosang = rel @ axis / np.maximum(dist * length, 1e-12)
        cone = np.cos(max(np.radians(MUSCLE_CONE_DEG), np.arctan2(MUSCLE_MIN_REACH, length)))
        angular = np.clip((cosang - cone) / (1 - cone), 0, 1)
        radial = np.clip(1 - np.abs(dist - length) / max(MUSCLE_BAND * length, MUSCLE_MIN_REACH), 0, 1)
        w = angular * radial * inside
        direction = -rel                                             # toward the attachment, along the skin
        direction -= np.einsum("ij,ij->i", direction, normals)[:, None] * normals
        direction /= np.maximum(np.linalg.norm(direction, axis=1, keepdims=True), 1e-12)
        out[mm["name"]] = _normalised(np.arange(n) + 2 * n, direction, w, strength_of(mm["name"]))
    for sph in sphincters:
        inside = _regions(tpl, sph["regions"])
        centre = np.asarray(sph["centre"])
        a, b = (np.asarray(x) for x in sph["axes"])
        rel = hyp - centre
        u, v = rel @ a / (a @ a), rel @ b / (b @ b)
        rho = np.sqrt(u ** 2 + v ** 2)
        w = np.clip(1 - np.abs(rho - 0.8) / 0.6, 0, 1) * inside
        inward = -(u[:, None] * a + v[:, None] * b)
        inward /= np.maximum(np.linalg.norm(inward, axis=1, keepdims=True), 1e-12)
        out[sph["name"]] = _normalised(np.arange(n) + 2 * n, inward, w, strength_of(sph["name"]))
    return out


def _pressure_controls(tpl, skin, normals, fdps, n):
    """Cheek puff (outward, around 5.1/5.2) and lip push (forward, around 8.1/8.2) on the hypodermis."""
    out = {}
    mw = np.linalg.norm(fdps["8.3"] - fdps["8.4"])
    hyp = np.arange(n) + 2 * n
    side_l = np.clip(0.5 + skin[:, 0] / 1e-3, 0, 1)          # 1 on the left, 1/2 on the midline
    cheek = _regions(tpl, PUFF_REGIONS)
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
        near = _regions(tpl, (region, "mouth_interior"))
        d = np.linalg.norm(skin - fdps[fdp], axis=1)
        w = np.clip(1 - d / (0.6 * mw), 0, 1) * near
        out[name] = _normalised(hyp, forward, w, strength_of(name))
    # funnel: the lips flare away from the mouth's centre line and forward (an O-shaped mouth)
    mouth = 0.5 * (fdps["2.2"] + fdps["2.3"])
    lips = _regions(tpl, ("upper_lip", "lower_lip", "mouth_interior"))
    flare = np.zeros((n, 3))
    flare[:, 2] = np.sign(skin[:, 2] - mouth[2])
    flare += FUNNEL_FORWARD * np.array([0.0, -1.0, 0.0])
    flare /= np.linalg.norm(flare, axis=1, keepdims=True)
    d = np.linalg.norm((skin - mouth)[:, [0, 2]], axis=1)
    w = np.clip(1 - d / (0.5 * mw), 0, 1) * lips
    out["lip_funnel"] = _normalised(hyp, flare, w, strength_of("lip_funnel"))
    # depressor septi: the nose's base (columella, subnasale) pulled down toward the upper lip
    d = np.linalg.norm(skin - fdps["9.15"], axis=1)
    w = np.clip(1 - d / (0.5 * mw), 0, 1) * _regions(tpl, ("nose",))
    out["depressor_septi"] = _normalised(hyp, np.tile([0.0, 0.0, -1.0], (n, 1)), w, strength_of("depressor_septi"))
    return out


def _lid_controls(tpl, skin, parts, fdps, n):
    """Lid plates: {control: (dofs, anchor stiffness, eye centre, full close angle rad, weight, axis)}.

    A lid turns about the axis through the eyeball's centre parallel to the line of its corners;
    the turn fades from the margin (1) to the orbit's rim (0) and to 0 at the corners, so the
    canthi stay and nothing shears at the plate's edge.
    """
    out = {}
    centre = parts["eye_l"].mean(axis=0)
    outer, inner = fdps["3.7"], fdps["3.11"]
    axis = (outer - inner) / np.linalg.norm(outer - inner)
    axis = np.array([axis[0], 0.0, axis[2]]) / np.linalg.norm([axis[0], axis[2]])   # no forward tilt
    lid = _regions(tpl, ("eyelid_l", "eye_socket_l"))
    rel = skin - centre
    along = rel @ axis
    radial = np.linalg.norm(rel - np.outer(along, axis), axis=1)      # distance from the axis
    r_margin = np.linalg.norm(fdps["3.1"] - centre)
    half = 0.5 * np.linalg.norm(outer - inner)
    mid = 0.5 * ((outer - centre) @ axis + (inner - centre) @ axis)
    w = (np.clip((LID_REACH * r_margin - radial) / ((LID_REACH - 1.0) * r_margin), 0, 1)
         * np.clip(1 - np.abs(along - mid) / half, 0, 1) ** 0.5 * lid)
    r1, r3 = (fdps[k] - centre for k in ("3.1", "3.3"))
    r1, r3 = r1 - (r1 @ axis) * axis, r3 - (r3 @ axis) * axis
    full = abs(float(np.arctan2(np.cross(r1, r3) @ axis, r1 @ r3)))   # margin to margin, about the axis
    line_z = inner[2] + (along - (inner - centre) @ axis) / (2 * half) * (outer[2] - inner[2])
    for which, mask in (("upper", (w > 0) & (skin[:, 2] > line_z)), ("lower", (w > 0) & (skin[:, 2] <= line_z))):
        v = np.flatnonzero(mask)
        idx = np.concatenate([v + layer * n for layer in range(3)])
        wk = np.tile(w[v], 3)
        out[f"{which}_lid_l"] = (idx, LID_STIFFNESS * wk, centre, full, wk, axis)
        out[f"{which}_lid_r"] = (_mirror_dofs(tpl, idx, n), LID_STIFFNESS * wk, parts["eye_r"].mean(axis=0),
                                 full, wk, axis * [1.0, -1.0, -1.0])   # an axis is a pseudovector
    return out
