"""Three-layer skin (paper sec 6.1) with muscles, solved quasi-statically with one prefactored matrix.

Layers: epidermis (the skin mesh), dermis and hypodermis below it along the inward normal, at
fractions of the local soft-tissue depth to the skull. Springs within each layer (along mesh
edges), between layers (vertical and diagonal) and from the hypodermis to the bone under it
(cranium fixed, mandible turning about the jaw pivot). The dermis is the most deformable layer.
Springs are linearised about the rest shape (energy sum k |(x_i - x_j) - (X_i - X_j)|^2), so the
equilibrium for any muscle forces is one solve with the same sparse factorisation: fast and
stable, no time steps. Muscles (Waters-style linear with angular and radial fall-off, and
sphincters on their ellipse) pull the hypodermis inside their regions. Template frame, metres.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy import sparse
from scipy.sparse.linalg import splu

from . import geometry, spatial

LAYER_DEPTHS = (0.0, 0.3, 0.7)        # fractions of the tissue depth: epidermis, dermis, hypodermis
STIFFNESS = {"epidermis": 1.0, "dermis": 0.3, "hypodermis": 0.8, "vertical": 0.6, "diagonal": 0.2}
BONE_STIFFNESS = 1.0                  # hypodermis to bone
LOOSE_BONE_STIFFNESS = 0.15           # under the lips and cheeks, where the skin slides
LOOSE_REGIONS = ("upper_lip", "lower_lip", "cheek_l", "cheek_r", "mouth_interior")
JAW_STIFFNESS = 50.0                  # hypodermis on the mandible (outside the lips)
NON_PENETRATION = 0.001               # skin stays at least this far outside the bone, m
MUSCLE_STRENGTH = 0.5                 # total pull of a muscle at activation 1 (stiffness units x m)


@dataclasses.dataclass
class SkinModel:
    """The assembled mass-spring model: rest positions (3n,3), factorised stiffness, muscle data."""
    n: int
    rest: np.ndarray
    solve: object
    bone_k: np.ndarray
    on_mandible: np.ndarray
    muscles: dict
    jaw_pivot: np.ndarray
    jaw_axis: np.ndarray
    bone_point: np.ndarray        # (n,3) nearest bone point of each skin vertex at rest
    bone_normal: np.ndarray       # (n,3) outward bone normal there
    on_bone_mandible: np.ndarray  # (n,) that bone point is on the mandible
    free: np.ndarray              # (n,) vertices the non-penetration applies to (not the hidden pockets)
    clearance: np.ndarray         # (n,) least gap kept to the bone: 1 mm, or less where the rest gap is less

    def equilibrium(self, activations=None, jaw_deg=0.0):
        """Skin (epidermis) positions (n,3) at equilibrium for {muscle: activation 0..1} and a jaw angle."""
        f = np.zeros_like(self.rest)
        for name, a in (activations or {}).items():
            if a:
                idx, direction, weight = self.muscles[name]
                np.add.at(f, idx, (a * MUSCLE_STRENGTH * weight)[:, None] * direction)
        if jaw_deg:
            from scipy.spatial.transform import Rotation
            rot = Rotation.from_rotvec(np.radians(jaw_deg) * self.jaw_axis).as_matrix()
            hyp = slice(2 * self.n, 3 * self.n)
            rest_h = self.rest[hyp]
            target = (rest_h - self.jaw_pivot) @ rot.T + self.jaw_pivot
            u_bone = np.where(self.on_mandible[:, None], target - rest_h, 0.0)
            f[hyp] += self.bone_k[:, None] * u_bone
        u = self.solve(f)
        x = self.rest[: self.n] + u[: self.n]
        # skull non-penetration: no skin closer than 1 mm to the bone (tangent plane of the nearest
        # bone point, which turns with the jaw)
        bp, bn = self.bone_point, self.bone_normal
        if jaw_deg:
            bp = np.where(self.on_bone_mandible[:, None], (bp - self.jaw_pivot) @ rot.T + self.jaw_pivot, bp)
            bn = np.where(self.on_bone_mandible[:, None], bn @ rot.T, bn)
        gap = np.einsum("ij,ij->i", x - bp, bn)
        push = self.free & (gap < self.clearance)
        x[push] += (self.clearance[push] - gap[push])[:, None] * bn[push]
        return x


def _edges(tris):
    e = np.sort(np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]]), axis=1)
    return np.unique(e, axis=0)


def build(tpl, parts=None, muscles=None, sphincters=None, jaw_pivot=None):
    """Assemble the skin model of a head (the template, or a transferred Anatomy's parts/muscles)."""
    tpl_parts_default = parts = parts or {k: p.verts for k, p in tpl.parts.items()}
    skin, tris = parts["skin"], tpl.skin.tris
    n = len(skin)
    normals = geometry.vertex_normals(skin, tris)
    bone_v = np.vstack([parts["cranium"], parts["mandible"]])
    bone_t = np.vstack([tpl.parts["cranium"].tris, tpl.parts["mandible"].tris + len(parts["cranium"])])
    closest, face, depth = spatial.MeshQuery(bone_v, bone_t, backend="numpy").closest_points(skin)
    hidden = np.isin(tpl.region, [tpl.region_names.index(r) for r in ("mouth_interior", "eye_socket_l", "eye_socket_r")])
    depth = np.clip(np.where(hidden, 0.002, depth), 0.001, 0.02)
    rest = np.vstack([skin - (f * depth)[:, None] * normals for f in LAYER_DEPTHS])
    on_mandible = face >= len(tpl.parts["cranium"].tris)

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
    loose = np.isin(tpl.region, [tpl.region_names.index(x) for x in LOOSE_REGIONS])
    bone_k = np.where(loose, LOOSE_BONE_STIFFNESS, BONE_STIFFNESS)
    on_mand = face >= len(tpl.parts["cranium"].tris)
    bone_k = np.where(on_mand & ~loose, JAW_STIFFNESS, bone_k)      # the chin follows the mandible
    neck = geometry.boundary_vertices(tris, n) & (tpl.region == tpl.region_names.index("neck"))   # the cut edge
    anchor = np.zeros(m)
    anchor[2 * n:] = bone_k
    anchor[np.flatnonzero(neck)] += 10.0          # the neck's cut edge holds the head still
    A = (A + sparse.diags(anchor)).tocsc()
    lu = splu(A)

    tm = {}
    meta_muscles = muscles if muscles is not None else [
        {"name": mm["name"], "regions": mm["regions"], "attachment": tpl.surface_point(mm["attachment"]),
         "insertion": tpl.surface_point(mm["insertion"])} for mm in tpl.meta["muscles"]]
    hyp = rest[2 * n:]
    for mm in meta_muscles:
        inside = np.isin(tpl.region, [tpl.region_names.index(x) for x in mm["regions"]])
        a_pt, i_pt = np.asarray(mm["attachment"]), np.asarray(mm["insertion"])
        axis = i_pt - a_pt
        length = np.linalg.norm(axis)
        rel = hyp - a_pt
        dist = np.linalg.norm(rel, axis=1)
        cosang = rel @ axis / np.maximum(dist * length, 1e-12)
        angular = np.clip((cosang - np.cos(np.radians(35))) / (1 - np.cos(np.radians(35))), 0, 1)
        radial = np.clip(1 - np.abs(dist - length) / (0.6 * length), 0, 1) * (dist < 1.4 * length)
        w = angular * radial * inside
        sel = np.flatnonzero(w > 0)
        direction = -rel[sel] / np.maximum(dist[sel, None], 1e-12)          # toward the attachment
        tm[mm["name"]] = (sel + 2 * n, direction, w[sel] / max(w.sum(), 1e-12))   # total pull = strength
    for sph in (sphincters if sphincters is not None else tpl.meta["sphincters"]):
        inside = np.isin(tpl.region, [tpl.region_names.index(x) for x in sph["regions"]])
        centre = np.asarray(sph["centre"])
        a, b = (np.asarray(x) for x in sph["axes"])
        rel = hyp - centre
        u, v = rel @ a / (a @ a), rel @ b / (b @ b)
        rho = np.sqrt(u ** 2 + v ** 2)
        w = np.clip(1 - np.abs(rho - 0.8) / 0.6, 0, 1) * inside
        sel = np.flatnonzero(w > 0)
        inward = -(u[sel, None] * a + v[sel, None] * b)
        inward /= np.maximum(np.linalg.norm(inward, axis=1, keepdims=True), 1e-12)
        tm[sph["name"]] = (sel + 2 * n, inward, w[sel] / max(w.sum(), 1e-12))

    def solve(f):
        return np.column_stack([lu.solve(np.ascontiguousarray(f[:, d])) for d in range(3)])

    # outward direction of the distance to the bone (robust at the bone's openings and folds)
    bone_fn = skin - closest
    bone_fn /= np.maximum(np.linalg.norm(bone_fn, axis=1, keepdims=True), 1e-12)
    if parts is tpl_parts_default:           # the template is symmetric: make the bone data exactly so
        right = skin[:, 0] < 0
        mir = tpl.skin_mirror[right]
        closest[right], bone_fn[right] = closest[mir] * [-1, 1, 1], bone_fn[mir] * [-1, 1, 1]
        on_mandible[right] = on_mandible[mir]
        mid = np.abs(skin[:, 0]) < 1e-9                       # midline: the bone normal has no sideways part
        closest[mid, 0], bone_fn[mid, 0] = 0.0, 0.0
        bone_fn[mid] /= np.maximum(np.linalg.norm(bone_fn[mid], axis=1, keepdims=True), 1e-12)
    # the lips sit in front of the teeth opening, not on bone (the teeth hold them): the bone
    # plane at the opening's edge is no barrier for them, and pushing their tiny triangles folds them
    lips = np.isin(tpl.region, [tpl.region_names.index(r) for r in ("upper_lip", "lower_lip")])
    rest_gap = np.einsum("ij,ij->i", skin - closest, bone_fn)
    jaw = tpl.meta["jaw"]
    return SkinModel(bone_point=closest, bone_normal=bone_fn, on_bone_mandible=on_mandible,
                     free=~hidden & ~lips & (rest_gap > 0), clearance=np.minimum(NON_PENETRATION, 0.9 * np.maximum(rest_gap, 0)),
                     n=n, rest=rest, solve=solve, bone_k=bone_k, on_mandible=on_mandible, muscles=tm,
                     jaw_pivot=np.asarray(jaw_pivot if jaw_pivot is not None else jaw["pivot"]),
                     jaw_axis=np.asarray(jaw["axis"]))
