"""Feature-point pairs of a level (paper sec 4.1): by feature-mesh subdivision, by the scan's
mean curvature inside the face box, and (HeadAdapt) the seen template vertices with the scan."""

from __future__ import annotations

import numpy as np

from ..mesh import geometry, spatial
from .fit import Fit, Pairs, spread
from .scan import ScanSide


def feature_mesh_pairs(fit: Fit, mesh: dict, reach: float, query: spatial.MeshQuery | None = None) -> Pairs:
    """Pairs from feature-mesh subdivision (sec 4.1, Kahler et al.): the deformed template and the scan
    share the feature mesh (its vertices are FP pairs), so one ray from each live triangle's
    barycentre along its normal meets both surfaces: a new pair, and the triangle splits in three.
    `mesh` is (fm_q scan-side vertices, fm_t triangles, dead mask) and is updated in place. query: the
    deformed template's MeshQuery, if the caller has it (current_query)."""
    fm_q, fm_t, dead = mesh["q"], mesh["t"], mesh["dead"]
    live = np.flatnonzero(~dead)
    if not len(live):
        return Pairs.empty()
    cur = fit.current()
    cur_query = current_query(fit) if query is None else query
    cur_n = geometry.face_normals(cur, fit.tris)
    tri = fm_t[live]
    bq = fm_q[tri].mean(axis=1)
    nq = geometry.face_normals(fm_q, tri)
    size = np.linalg.norm(fm_q[tri] - bq[:, None], axis=2).max(axis=1)
    lim = np.minimum(0.5 * size, reach)
    ht = cur_query.ray_cast(bq, nq, lim)
    hs = fit.scan.query.ray_cast(bq, nq, lim)
    ft, fs = np.where(ht.hit, ht.face, 0), np.where(hs.hit, hs.face, 0)
    ok = ht.hit & hs.hit & (fit.face_w[ft] > 0) & ~fit.scan.boundary_faces[fs]
    ok &= np.einsum("ij,ij->i", cur_n[ft], fit.scan.face_normals[fs]) > 0.5
    dead[live[~ok]] = True
    acc = live[ok]
    if not len(acc):
        return Pairs.empty()
    tp = np.einsum("ij,ijk->ik", ht.bary[ok], fit.V[fit.tris[ft[ok]]])
    base = len(fm_q)
    idx = base + np.arange(len(acc))
    a, b, c = fm_t[acc, 0], fm_t[acc, 1], fm_t[acc, 2]
    fm_t[acc] = np.c_[a, b, idx]
    mesh["q"] = np.vstack([fm_q, hs.point[ok]])
    mesh["t"] = np.vstack([fm_t, np.c_[b, c, idx], np.c_[c, a, idx]])
    mesh["dead"] = np.concatenate([dead, np.zeros(2 * len(acc), bool)])
    return Pairs(tp, hs.point[ok], np.full(len(tp), fit.options.feature_weight))


def current_query(fit: Fit) -> spatial.MeshQuery:
    """Closest points and rays on the deformed template as the levels so far leave it."""
    return spatial.MeshQuery(fit.current(), fit.tris, backend=fit.options.backend)


def curvature_pairs(fit: Fit, box: np.ndarray, count: int, reach: float, spacing: float,
                    query: spatial.MeshQuery | None = None) -> Pairs:
    """Pairs from the scan's mean-curvature extremes (sec 4.1, appendix: Meyer et al.) inside the
    paper's face box, `spacing` apart, matched to the current template by rays along the scan normal.
    query: the deformed template's MeshQuery, if the caller has it (current_query)."""
    scan = fit.scan
    H, valid = scan.curvature(box)
    cand = np.flatnonzero(valid & ~scan.boundary_verts & box)    # not by a border (paper sec 4.1)
    if not len(cand):
        return Pairs.empty()
    order = cand[np.argsort(-np.abs(H[cand]))]
    src = order[spread(scan.verts[order[: count * 6]], spacing)[:count]]
    cur = fit.current()
    hit = (current_query(fit) if query is None else query).ray_cast(scan.verts[src], scan.vertex_normals[src], reach)
    f = np.where(hit.hit, hit.face, 0)
    ok = hit.hit & (fit.face_w[f] > 0)
    ok &= np.einsum("ij,ij->i", geometry.face_normals(cur, fit.tris)[f], scan.vertex_normals[src]) > 0.7
    tp = np.einsum("ij,ijk->ik", hit.bary[ok], fit.V[fit.tris[f[ok]]])
    return Pairs(tp, scan.verts[src[ok]], np.full(len(tp), fit.options.curvature_weight))


def surface_pairs(fit: Fit, reach: float, along_normal: bool = False, mask: np.ndarray | None = None,
                  exact: bool = True) -> Pairs:
    """Pairs of the seen template vertices with the scan, kept when within `reach`, the normals agree
    within 60 degrees and the point is not on a hole's border, weighted by region and by a robust
    (Cauchy) weight on the distance. Coarse levels take the closest point (non-rigid ICP: the
    template slides until its shapes meet the scan's); fine levels cast along the template's normal
    (the paper's rays: no sideways pull, so nothing folds where the scan lacks the template's detail).
    exact False: closest points by the nearest vertex's tangent plane on any scan (ScanSide.nearest_on_plane)."""
    cur = fit.current()
    normals = geometry.vertex_normals(cur, fit.tris)
    use = np.flatnonzero((fit.pair_w > 0) & ~fit.near_seam & ~fit.quiet & (True if mask is None else mask))
    if along_normal:
        q, n, d, border = normal_hits(fit.scan, cur[use], normals[use], reach)
    else:
        q, n, d, border = fit.scan.nearest_on_plane(cur[use], exact_if_coarse=exact)
    ok = (d < reach) & ~border & (np.einsum("ij,ij->i", normals[use], n) > 0.5)
    w = fit.pair_w[use] / (1.0 + (np.minimum(d, reach) / (fit.options.robust_scale * reach)) ** 2)
    return Pairs(fit.V[use[ok]], q[ok], w[ok], use[ok])


def normal_hits(scan: ScanSide, points: np.ndarray, normals: np.ndarray, reach: float):
    """(hit points (k,3; 0 for a miss), the scan's face normals there, how far (inf for a miss), on a
    hole's border or missed) of rays from points along their normals, both ways, within reach."""
    hit = scan.query.ray_cast(points, normals, reach)
    f = np.where(hit.hit, hit.face, 0)
    return (np.nan_to_num(hit.point), scan.face_normals[f], np.abs(np.nan_to_num(hit.t, nan=np.inf)),
            scan.boundary_faces[f] | ~hit.hit)


def face_box(scan: ScanSide, q_fdp: dict[str, np.ndarray]) -> np.ndarray:
    """The paper's box for the curvature search: eye to eye across (outer corners), from one and a half
    eye-to-mouth heights above the eyes down to the lowest FDP (the whole scan without eye corners)."""
    if not ("3.7" in q_fdp and "3.12" in q_fdp):
        return np.ones(len(scan.verts), bool)
    lo_x, hi_x = sorted((q_fdp["3.12"][0], q_fdp["3.7"][0]))
    eyes = 0.5 * (q_fdp["3.7"][2] + q_fdp["3.12"][2])
    low = min(p[2] for p in q_fdp.values())
    top = q_fdp["11.1"][2] if "11.1" in q_fdp else eyes + 1.5 * (eyes - low)
    z = scan.verts[:, 2]
    return (scan.verts[:, 0] > lo_x) & (scan.verts[:, 0] < hi_x) & (z < top) & (z > low - 0.01)
