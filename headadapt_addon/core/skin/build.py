"""Assembly of the three-layer skin model (paper sec 6.1) of the template or of an adapted head."""

from __future__ import annotations

import numpy as np
from scipy import sparse
from scipy.sparse.linalg import splu

from ..mesh import geometry, spatial
from ..tol import TINY
from .contact import NON_PENETRATION, near_opening
from .controls import lid_controls, muscle_forces, pressure_controls, sheet_muscles
from .jaw import JAW_STIFFNESS
from .model import SkinModel

LAYER_DEPTHS = (0.0, 0.3, 0.7)        # fractions of the tissue depth: epidermis, dermis, hypodermis
STIFFNESS = {"epidermis": 1.0, "dermis": 0.3, "hypodermis": 0.8, "vertical": 0.6, "diagonal": 0.2}
BONE_STIFFNESS = 2.0                  # hypodermis to bone
LOOSE_BONE_STIFFNESS = 0.15           # under the lips and cheeks, where the skin slides
LOOSE_REGIONS = ("upper_lip", "lower_lip", "cheek_l", "cheek_r", "mouth_interior", "neck")
SLIVER = 0.01                         # a triangle whose least height is under this fraction of its
                                      # longest edge (under ~0.6 deg) has no orientation to keep


def _edges(tris):
    e = np.sort(np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]]), axis=1)
    return np.unique(e, axis=0)


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

    hidden = tpl.hidden
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
    loose = tpl.region_mask(*LOOSE_REGIONS)
    bone_k = np.where(loose, LOOSE_BONE_STIFFNESS, BONE_STIFFNESS)
    bone_k = np.where(on_mandible & ~loose, JAW_STIFFNESS, bone_k)      # the chin follows the mandible
    neck = geometry.boundary_vertices(tris, n) & tpl.region_mask("neck")   # the cut edge holds the head
    anchor = np.zeros(m)
    anchor[2 * n:] = bone_k
    anchor[np.flatnonzero(neck)] += 10.0

    lids = lid_controls(tpl, skin, parts, fdps, n)
    for idx_l, k_l, *_ in lids.values():
        np.add.at(anchor, idx_l, k_l)
    matrix = (A + sparse.diags(anchor)).tocsc()
    lu = splu(matrix)

    def solve(f):             # the three columns at once: each column's answer to the bit, in 0.6 of the time
        return lu.solve(np.asfortranarray(f))

    forces = muscle_forces(tpl, rest, normals, n, muscles, sphincters)
    forces.update(pressure_controls(tpl, skin, normals, fdps, n))
    forces.update(sheet_muscles(tpl, skin, normals, fdps, n))

    rest_gap = np.einsum("ij,ij->i", skin - closest, bone_fn)
    jaw = tpl.meta["jaw"]
    jaw_axis = np.asarray(jaw["axis"], dtype=float)
    if anatomy is None:                   # the symmetric head's jaw turns about the left-right axis (the
        jaw_axis = np.array([np.sign(jaw_axis[0]), 0.0, 0.0])   # stored one is tilted 0.15 deg by its fit)
    adj = geometry.neighbour_mean(tris, n)
    bone = tuple((queries[k], geometry.face_normals(parts[k], tpl.parts[k].tris),
                  near_opening(parts[k], tpl.parts[k].tris)) for k in ("cranium", "mandible"))
    bone += (np.asarray(parts["cranium"], float), np.asarray(parts["mandible"], float), bone_t)
    return SkinModel(bone=bone, tris=tris, folds=geometry.FoldCheck(skin, tris, SLIVER), adjacency=adj,
                     n=n, rest=rest, solve=solve, matrix=matrix, forces=forces, bone_k=bone_k, on_mandible=on_mandible,
                     jaw_pivot=np.asarray(jaw_pivot, dtype=float), jaw_axis=jaw_axis, lids=lids,
                     bone_dist=bone_dist, bone_normal=bone_fn, free=~hidden & (rest_gap > 0),
                     clearance=np.minimum(NON_PENETRATION, 0.9 * np.maximum(rest_gap, 0)),
                     mirror=tpl.skin_mirror if anatomy is None else None)
