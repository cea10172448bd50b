"""Three-layer skin (paper sec 6.1) driven by muscles, jaw and lids, solved quasi-statically.

Layers: epidermis (the skin mesh), dermis and hypodermis below it along the inward normal, at
fractions of the local soft-tissue depth to the skull. Springs within each layer (along mesh
edges), between layers (vertical and diagonal) and from the hypodermis to the bone under it
(cranium fixed, mandible turning about the jaw pivot). The dermis is the most deformable layer.
Springs are linearised about the rest shape (energy sum k |(x_i - x_j) - (X_i - X_j)|^2), so the
equilibrium for any set of controls is one solve with the same sparse factorisation: fast and
stable, no time steps.

After the solve the skin is kept out of the bone (cranium, mandible where the jaw put it): points
that may be near it (a 1-Lipschitz bound on their distance) are pushed out along the way out, a
point at one of the bone's openings (judged by the winding number) that no push gets out gives up
part of its displacement, and a local relaxation undoes folded triangles.

Controls, each with an activation (0 = rest, 1 = full):
- linear muscles (Waters-style angular and radial fall-off) and sphincters (on their ellipse)
  pull the hypodermis inside their regions;
- `jaw_open` turns the mandible about the jaw pivot, `jaw_thrust` / `jaw_shift` slide it; the
  skin follows through its springs to the bone;
- `upper_lid_l/r`, `lower_lid_l/r` turn the lids about the eyeball's centre (the tarsal plate
  riding on the eye); at 1 the upper margin meets the lower all along the fissure, the lower
  rises LOWER_LID_SHARE of the opening (the upper then stops on it);
- `cheek_puff_l/r` push the cheeks out (air pressure in the mouth);
- `lip_push_upper/lower` push the lips forward (the lip's own protrusion).
Template frame (or the adapted head's, same axes), metres.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy import sparse
from scipy.sparse.linalg import splu
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from ..mesh import geometry, spatial
from ..mesh.inside import winding_numbers
from ..tol import TINY

LAYER_DEPTHS = (0.0, 0.3, 0.7)        # fractions of the tissue depth: epidermis, dermis, hypodermis
STIFFNESS = {"epidermis": 1.0, "dermis": 0.3, "hypodermis": 0.8, "vertical": 0.6, "diagonal": 0.2}
BONE_STIFFNESS = 2.0                  # hypodermis to bone
LOOSE_BONE_STIFFNESS = 0.15           # under the lips and cheeks, where the skin slides
LOOSE_REGIONS = ("upper_lip", "lower_lip", "cheek_l", "cheek_r", "mouth_interior", "neck")
JAW_STIFFNESS = 50.0                  # hypodermis on the mandible (outside the lips)
LID_REACH = 1.7                       # the lid's turn fades to 0 at this many margin radii from the eye axis
LOWER_LID_SHARE = 0.35                # the lower lid at 1 rises this share of the opening (as in a blink)
LID_STIFFNESS = 5.0                   # lid skin on its tarsal plate
MUSCLE_CONE_DEG = 15.0               # Waters' angular fall-off: zero at this angle off the muscle axis
MUSCLE_BAND = 0.15                    # radial fall-off: zero this fraction of the length from the insertion
MUSCLE_MIN_REACH = 0.008              # short muscles still spread their pull this far (m)
PUFF_REGIONS = ("cheek_l", "mouth_interior")
PUFF_FORWARD = 3.0
FUNNEL_FORWARD = 1.0
PUFF_OFFSET, PUFF_RADIUS = 0.5, 0.9  # puff centre beside the lip corner and reach, in mouth widths
UNFOLD_STEPS = 80                     # most local relaxation steps against folded triangles
SLIVER = 0.01                         # a triangle whose least height is under this fraction of its
                                      # longest edge (under ~0.6 deg) has no orientation to keep
CONTACT_ROUNDS = 4                    # pushes per contact step (a point at a bone opening may need more)
OPENING_REACH = 0.01                  # bone faces this close to a hole of the bone are 'by an opening', m
RETRACT_STEPS = 8                     # bisection steps of the last guard against penetration
NON_PENETRATION = 0.001               # skin stays at least this far outside the bone, m
HIDDEN_REGIONS = ("mouth_interior", "eye_socket_l", "eye_socket_r")

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
    bone_dist: np.ndarray         # (n,2) rest distance of each skin vertex to the cranium, the mandible
    bone_normal: np.ndarray       # (n,3) outward bone normal there
    free: np.ndarray              # (n,) vertices the non-penetration applies to
    clearance: np.ndarray         # (n,) least gap kept to the bone
    tris: np.ndarray              # (t,3) skin triangles
    folds: geometry.FoldCheck     # folded skin triangles against their rest orientation (slivers: SLIVER)
    adjacency: object             # (n,n) sparse, row-normalised vertex neighbours
    bone: tuple                   # cranium and mandible: (queries, face normals), verts, bone tris

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

    def on_jaw(self, points, rot, t):
        """Points (k,3) of the mandible's rest frame carried where the jaw (rot, t) puts them, metres."""
        return (points - self.jaw_pivot) @ rot.T + self.jaw_pivot + t

    def _jaw_local(self, points, rot, t):
        """Points (k,3) taken back into the mandible's rest frame (the inverse of on_jaw), metres."""
        return (points - self.jaw_pivot - t) @ rot + self.jaw_pivot

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
            target = self.on_jaw(rest_h, rot, t)
            f[hyp] += np.where(self.on_mandible[:, None], self.bone_k[:, None] * (target - rest_h), 0.0)
        for name, (idx, k, centre, full, weight, axis) in self.lids.items():
            if name in activations:
                sign, act = (1.0 if name.startswith("upper") else -1.0), activations[name]
                if sign > 0:                   # the upper margin stops where the risen lower one is
                    act = min(act, 1.0 - LOWER_LID_SHARE * max(activations.get(name.replace("upper", "lower"), 0.0), 0.0))
                angle = (sign * full * act * weight)[:, None]
                rel = self.rest[idx] - centre                 # Rodrigues, one angle per dof
                turned = (rel * np.cos(angle) + np.cross(axis, rel) * np.sin(angle)
                          + np.outer(rel @ axis, axis) * (1 - np.cos(angle)))
                f[idx] += k[:, None] * (turned - rel)
        u = self.solve(f)
        x = self.rest[: self.n] + u[: self.n]
        # skull non-penetration, on the true bone (the mandible moved)
        bn = np.where(self.on_mandible[:, None], self.bone_normal @ rot.T, self.bone_normal)
        contact = _Contact(bn, (rot, t))
        x = self._keep_out_of_bone(x, contact)
        return self._unfold(self._retract_from_bone(x, contact), contact)

    def _bone_gap(self, pts, outward, rot, t, known):
        """Signed gap (k,) of skin points (k,3) above the bone with the mandible at (rot, t), the
        unit direction (k,3) that leads out, (k,) bools at an opening (odd) and inside, and how far
        each point may move and keep its side (k,), signed like the gap, NaN where `known` gave the
        side: metres. `known` (k,) is +1/-1 where the side is already known, 0 where not.

        Inside is a winding number over 1/2 (it sees the bone's openings right); it is computed
        only where the nearest face leaves a doubt, or by a hole in the bone (there the winding
        number's 1/2 level spans the hole, off the bone). A point in front of its nearest face that
        is inside sits at an opening: its way out is `outward`, its gap counts as 0."""
        (q_cr, n_cr, open_cr), (q_md, n_md, open_md), *_ = self.bone
        c_cr, f_cr, d_cr = q_cr.closest_points(pts)
        local = self._jaw_local(pts, rot, t)
        c_md, f_md, d_md = q_md.closest_points(local)
        use_md = d_md < d_cr
        dist = np.minimum(d_md, d_cr)
        closest = np.where(use_md[:, None], self.on_jaw(c_md, rot, t), c_cr)
        away = (pts - closest) / np.maximum(dist, TINY)[:, None]
        side = np.where(use_md, np.einsum("ij,ij->i", local - c_md, n_md[f_md]),
                        np.einsum("ij,ij->i", pts - c_cr, n_cr[f_cr]))
        face_out = side >= 0.999 * dist
        by_opening = open_cr[f_cr] | open_md[f_md]
        inside = known < 0
        keeps = np.where(known == 0, dist, np.nan)              # a plain face answer holds within the gap
        ask = (~face_out | by_opening | (dist < 2 * NON_PENETRATION)) & (known == 0)
        if ask.any():
            w = self._winding(pts[ask], rot, t)
            inside[ask] = w > 0.5
            # w is harmonic off the bone and within [-1/4, 5/4]: |grad w| <= 3 * 3/4 / dist, so w
            # stays on its side of 1/2 while the point moves less than this
            keeps[ask] = dist[ask] * -np.expm1(-np.abs(w - 0.5) / 2.25)
        odd = inside & face_out
        gap = np.where(inside, np.where(odd, 0.0, -dist), dist)
        way_out = np.where(odd[:, None], outward, np.where(inside[:, None], -away, away))
        return gap, way_out, odd, inside, np.where(inside, -keeps, keeps)

    def _winding(self, pts, rot, t):
        """Winding number (k,) of skin points (k,3) in the bone (cranium, mandible at (rot, t))."""
        _, _, v_cr, v_md, bone_t = self.bone
        return winding_numbers(pts, np.vstack([v_cr, self.on_jaw(v_md, rot, t)]), bone_t)

    def _inside(self, pts, rot, t):
        """Whether skin points (k,3) are inside the bone (cranium and the mandible at (rot, t))."""
        return self._winding(pts, rot, t) > 0.5

    def _keep_out_of_bone(self, x, contact, only=None):
        """Skin x (n,3) pushed out to the clearance above the (moved) bone, metres: a few rounds of
        pushes along the way out, each shared with the neighbours so it shears no triangle. `only`
        (n,) bool limits the look to vertices that moved since the last look."""
        rot, t = contact.jaw
        for _ in range(CONTACT_ROUNDS):
            near = self._near_bone(x, contact, only)
            if not len(near):
                break
            gap, way_out, odd, _, keeps = self._bone_gap(x[near], contact.outward[near], rot, t,
                                                         contact.known_side(x, near))
            fresh = ~np.isnan(keeps)
            contact.sided_at[near[fresh]], contact.sided_keep[near[fresh]] = x[near[fresh]], keeps[fresh]
            contact.normal[near] = way_out
            deficit = np.zeros(self.n)
            deficit[near] = np.maximum(self.clearance[near] - gap, 0.0)
            for _ in range(3):          # neighbours share part of a push, so it shears no triangle
                deficit = np.maximum(deficit, 0.6 * (self.adjacency @ deficit)) * self.free
            x = x + deficit[:, None] * contact.normal
            if not odd.any():
                break
        return x

    def _near_bone(self, x, contact, only=None):
        """Indices of free skin vertices at x (n,3) that may be within their clearance of the bone:
        the rest distance to each bone, less how far the vertex moved relative to that bone, bounds
        its distance now (distance is 1-Lipschitz)."""
        rot, t = contact.jaw
        rest = self.rest[: self.n]
        local = self._jaw_local(x, rot, t)
        bound = np.minimum(self.bone_dist[:, 0] - np.linalg.norm(x - rest, axis=1),
                           self.bone_dist[:, 1] - np.linalg.norm(local - rest, axis=1))
        near = self.free & (bound < self.clearance)
        return np.flatnonzero(near if only is None else near & only)

    def _retract_from_bone(self, x, contact, only=None):
        """Skin x (n,3) with each vertex still inside the bone drawn back toward its rest place on
        its bone (moved with the mandible) until it is out by its clearance, metres.

        The last guard, for a point at a bone opening that no push along a normal gets out (the
        lower lip's inner roll behind the maxilla's rim): it gives up part of its displacement.
        `only` (n,) bool limits the look to vertices that moved since the last look."""
        rot, t = contact.jaw
        near = self._near_bone(x, contact, only)
        if not len(near):
            return x
        inside = self._bone_gap(x[near], contact.outward[near], rot, t, contact.known_side(x, near))[3]
        bad = near[inside]
        if not len(bad):
            return x
        rest = self.rest[: self.n]
        home = np.where(self.on_mandible[:, None], self.on_jaw(rest, rot, t), rest)
        home[bad] = np.where(self._inside(home[bad], rot, t)[:, None], rest[bad], home[bad])
        lo, hi = np.zeros(len(bad)), np.ones(len(bad))                 # fraction of the way home
        for _ in range(RETRACT_STEPS):
            mid = 0.5 * (lo + hi)
            ins = self._inside(x[bad] + mid[:, None] * (home[bad] - x[bad]), rot, t)
            lo, hi = np.where(ins, mid, lo), np.where(ins, hi, mid)
        span = np.maximum(np.linalg.norm(home[bad] - x[bad], axis=1), TINY)
        frac = np.zeros(self.n)
        frac[bad] = np.minimum(hi + self.clearance[bad] / span, 1.0)
        for _ in range(3):                     # neighbours give up part of theirs too
            frac = np.maximum(frac, 0.6 * (self.adjacency @ frac)) * self.free
        return x + frac[:, None] * (home - x)

    def flipped(self, x):
        """Indices of skin triangles whose normal turned against its rest normal at positions x (n,3)."""
        return self.folds(x)

    def _unfold(self, x, contact):
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
            moved = patch | (self.adjacency @ patch.astype(float) > 0)
            x = self._retract_from_bone(self._keep_out_of_bone(x, contact, moved), contact, moved)
        return x


@dataclasses.dataclass
class _Contact:
    """Skin-bone contact during one equilibrium: per skin vertex its outward rest bone direction
    (moved with the mandible), the mandible's (rot, t), the direction a push moves it (out of the
    bone), and where its side of the bone was last decided with how far it may move and keep it,
    signed: + outside, - inside (0: never)."""
    outward: np.ndarray
    jaw: tuple
    normal: np.ndarray = None
    sided_at: np.ndarray = None
    sided_keep: np.ndarray = None

    def __post_init__(self):
        self.normal = self.outward.copy()
        self.sided_at = np.zeros_like(self.outward)
        self.sided_keep = np.zeros(len(self.outward))

    def known_side(self, x, idx):
        """+1 / -1 where vertices idx of skin x (n,3) are known outside / inside the bone, 0 where
        not: a point keeps its side while it moves less than its distance to the bone."""
        moved = np.linalg.norm(x[idx] - self.sided_at[idx], axis=1)
        old = self.sided_keep[idx]
        return np.where(moved < np.abs(old), np.sign(old), 0.0)


def _near_opening(verts, tris):
    """(f,) bool: faces with a vertex within OPENING_REACH of the mesh's open boundary (metres)."""
    rim = np.flatnonzero(geometry.boundary_vertices(tris, len(verts)))
    if not len(rim):
        return np.zeros(len(tris), bool)
    d, _ = cKDTree(np.asarray(verts)[rim]).query(np.asarray(verts))
    return (d < OPENING_REACH)[tris].any(axis=1)


def _fissure_opening(along, phi, upper, lid_skin, mid, half, bins=12):
    """Per vertex (n,): the angle (rad) between the lid margins in its column of the fissure
    (`along` the corner line, metres), from the visible lid skin: the upper margin is the most
    closed upper-lid vertex, the lower margin the most closed lower-lid vertex; 0 at the corners."""
    edges = np.linspace(mid - half, mid + half, bins + 1)
    col = np.digitize(along, edges) - 1
    top, bottom = np.full(bins, -np.inf), np.full(bins, np.inf)
    ok = np.ones(bins, bool)
    for side, out, pick in ((upper, top, np.maximum), (~upper, bottom, np.minimum)):
        m = (col >= 0) & (col < bins) & lid_skin & side
        pick.at(out, col[m], phi[m])
        ok &= np.bincount(col[m], minlength=bins) >= 3            # a sparse column has no margin
    gap = bottom - top
    centres = 0.5 * (edges[:-1] + edges[1:])
    gap = np.interp(centres, centres[ok], np.maximum(gap[ok], 0.0))
    return np.interp(along, np.r_[edges[0], centres, edges[-1]], np.r_[0.0, gap, 0.0])


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
    return idx[keep], direction[keep] * (strength * weight[keep] / max(weight.sum(), TINY))[:, None]


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
    bone_t = tpl.skull_tris
    queries = {k: spatial.MeshQuery(parts[k], tpl.parts[k].tris, backend="numpy") for k in ("cranium", "mandible")}
    (c_cr, _, d_cr), (c_md, _, d_md) = (queries[k].closest_points(skin) for k in ("cranium", "mandible"))
    on_mandible = d_md <= d_cr                                   # a tie (a shared rim) rides the jaw
    closest, depth = np.where(on_mandible[:, None], c_md, c_cr), np.minimum(d_cr, d_md)
    bone_dist = np.column_stack([d_cr, d_md])
    # outward direction of the distance to the bone (robust at the bone's openings and folds)
    bone_fn = skin - closest
    bone_fn /= np.maximum(np.linalg.norm(bone_fn, axis=1, keepdims=True), TINY)
    # the head is symmetric by construction: make the bone data exactly so (mirrored controls
    # then give mirrored shapes to rounding)
    if anatomy is None:
        right, mir = skin[:, 0] < 0, tpl.skin_mirror
        closest[right], bone_fn[right] = closest[mir[right]] * [-1, 1, 1], bone_fn[mir[right]] * [-1, 1, 1]
        depth[right], on_mandible[right] = depth[mir[right]], on_mandible[mir[right]]
        bone_dist[right] = bone_dist[mir[right]]
        mid = np.abs(skin[:, 0]) < 1e-9                    # midline: the bone normal has no sideways part
        closest[mid, 0], bone_fn[mid, 0] = 0.0, 0.0
        bone_fn[mid] /= np.maximum(np.linalg.norm(bone_fn[mid], axis=1, keepdims=True), TINY)

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
    adj = geometry.neighbour_mean(tris, n)
    bone = tuple((queries[k], geometry.face_normals(parts[k], tpl.parts[k].tris),
                  _near_opening(parts[k], tpl.parts[k].tris)) for k in ("cranium", "mandible"))
    bone += (np.asarray(parts["cranium"], float), np.asarray(parts["mandible"], float), bone_t)
    return SkinModel(bone=bone, tris=tris, folds=geometry.FoldCheck(skin, tris, SLIVER), adjacency=adj,
                     n=n, rest=rest, solve=solve, matrix=matrix, forces=forces, bone_k=bone_k, on_mandible=on_mandible,
                     jaw_pivot=np.asarray(jaw_pivot, dtype=float), jaw_axis=np.asarray(jaw["axis"]), lids=lids,
                     bone_dist=bone_dist, bone_normal=bone_fn, free=~hidden & (rest_gap > 0),
                     clearance=np.minimum(NON_PENETRATION, 0.9 * np.maximum(rest_gap, 0)))


def _muscle_forces(tpl, rest, normals, n, muscles, sphincters):
    """Muscle forces on the hypodermis at activation 1: {name: (dof index, force (k,3))}."""
    hyp = rest[2 * n:]
    out = {}
    for mm in muscles:
        inside = _regions(tpl, mm["regions"])
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
        direction = -rel                                             # toward the attachment, along the skin
        direction -= np.einsum("ij,ij->i", direction, normals)[:, None] * normals
        direction /= np.maximum(np.linalg.norm(direction, axis=1, keepdims=True), TINY)
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
        inward /= np.maximum(np.linalg.norm(inward, axis=1, keepdims=True), TINY)
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
    the turn fades from the margin (1) to the orbit's rim (0), and along the fissure it is the
    local opening (the angle between the margins there) over the opening at the middle, so at 1 the
    margins meet all along and the canthi stay.
    """
    out = {}
    centre = parts["eye_l"].mean(axis=0)
    outer, inner = fdps["3.7"], fdps["3.11"]
    axis = (outer - inner) / np.linalg.norm(outer - inner)
    axis = np.array([axis[0], 0.0, axis[2]]) / np.linalg.norm([axis[0], axis[2]])   # no forward tilt
    lid = _regions(tpl, ("eyelid_l", "eye_socket_l"))
    rel = skin - centre
    along = rel @ axis
    flat = rel - np.outer(along, axis)                               # across the axis
    radial = np.linalg.norm(flat, axis=1)                            # distance from the axis
    r_margin = np.linalg.norm(fdps["3.1"] - centre)
    half = 0.5 * np.linalg.norm(outer - inner)
    mid = 0.5 * ((outer - centre) @ axis + (inner - centre) @ axis)
    r1, r3 = (fdps[k] - centre for k in ("3.1", "3.3"))
    r1, r3 = r1 - (r1 @ axis) * axis, r3 - (r3 @ axis) * axis
    turn = np.sign(np.cross(r1, r3) @ axis)
    full = abs(float(np.arctan2(np.cross(r1, r3) @ axis, r1 @ r3)))   # margin to margin, about the axis
    line_z = inner[2] + (along - (inner - centre) @ axis) / (2 * half) * (outer[2] - inner[2])
    upper = skin[:, 2] > line_z
    # angle of each vertex from the upper margin's middle toward the lower's, about the axis
    phi = turn * np.arctan2(np.cross(r1, flat) @ axis, flat @ r1)
    opening = _fissure_opening(along, phi, upper, _regions(tpl, ("eyelid_l",)), mid, half) / full
    w = (np.clip((LID_REACH * r_margin - radial) / ((LID_REACH - 1.0) * r_margin), 0, 1)
         * np.clip(opening, 0, 1) * lid)
    for which, mask in (("upper", (w > 0) & upper), ("lower", (w > 0) & ~upper)):
        v = np.flatnonzero(mask)
        idx = np.concatenate([v + layer * n for layer in range(3)])
        wk = np.tile(w[v], 3)
        angle = full * (1.0 if which == "upper" else LOWER_LID_SHARE)
        out[f"{which}_lid_l"] = (idx, LID_STIFFNESS * wk, centre, angle, wk, axis)
        out[f"{which}_lid_r"] = (_mirror_dofs(tpl, idx, n), LID_STIFFNESS * wk, parts["eye_r"].mean(axis=0),
                                 angle, wk, axis * [1.0, -1.0, -1.0])   # an axis is a pseudovector
    return out
