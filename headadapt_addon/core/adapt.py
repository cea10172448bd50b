"""Multilevel adaptation of the template skin onto a scan (paper sections 3 to 5).

Frames: the scan arrives in its own frame and unit; calibration maps it into the template frame
(metres, Z up, face toward -Y), where all fitting happens; results go back through the inverse.
Every level function is a function of the *undeformed* template position x (paper eq 18):
f^k(x) = f^{k-1}(x) + o^k(x), so the same map carries skull, muscles and eyes later.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np
from scipy.spatial import Delaunay, cKDTree

from . import calibration, geometry, metrics, mpeg4, rbf, spatial
from .exceptions import LandmarkError

MM = 1000.0
SCANNER_VISIBLE_PARTS = ("skin", "eye_l", "eye_r")


@dataclasses.dataclass(frozen=True)
class AdaptOptions:
    """Settings of one adaptation run (lengths in metres of the template frame)."""
    max_levels: int = 4                 # levels after level 0
    pair_threshold: int = 500           # below: global RBF on all pairs; above: CSRBF offsets (sec 4.3)
    rho: float = 0.0                    # level-0 smoothing (eq 9), m
    support: float | None = None        # fixed CSRBF support sigma (m); default: support_factor x spacing
    calibration: str = "auto"           # "paper", "umeyama" or "auto"
    drop_flagged: bool = True           # drop FDPs flagged as wrongly clicked and refit level 0
    flag_mm: float = 8.0                # leave-one-out residual above which an FDP is flagged, mm
    off_surface_mm: float = 12.0        # an FDP farther than this from the scan surface is an error
    curvature_points: int = 150         # scan curvature points at level 1 (doubles per level)
    sample_spacing: float = 0.016       # spacing of surface samples at level 1 (halves per level), m
    use_feature_mesh: bool = True       # pairs from feature-mesh subdivision (sec 4.1, Kahler et al.)
    use_curvature: bool = True          # pairs from the scan's mean-curvature search (sec 4.1, appendix)
    curvature_reach: float = 0.004      # farthest a curvature point may be from the template, m
    seam_band: float = 0.004            # no pairs within this of the inner-lip seam (template frame), m
    min_sample_spacing: float = 0.002   # finest surface-sample spacing, m
    thin_pairs: float = 0.5             # drop pairs closer than this x the level's spacing (0: keep all)
    support_factor: float = 3.0         # CSRBF support = this x the level's sample spacing (halves per level)
    alpha: float = 1.0                  # weight of E_d in E (eq 24)
    beta: float = 0.01                  # weight of E_m in E (E_m sums over markers, E_d averages)
    stop_at_minimum: bool = True        # stop when E rises (sec 5.3)
    bad_fit_rms_mm: float = 1.5         # seen-skin distance RMS above this is a failed fit: 3x the
                                        # noise of a range scanner (0.1-0.5 mm), mm


@dataclasses.dataclass
class Level:
    """The report of one level: pairs used, errors (mm^2 as in the paper, RMS mm), seconds."""
    level: int
    method: str
    pairs: int
    new_pairs: int
    E_d: float
    E_d_rms_mm: float
    E_m: float | None
    E: float
    coverage: float
    seconds: float
    support_mm: float | None = None


@dataclasses.dataclass
class AdaptResult:
    """The adapted skin and everything needed to carry anatomy along (template frame unless named)."""
    verts: np.ndarray                 # (n,3) adapted skin, template frame, metres
    verts_scan: np.ndarray            # (n,3) adapted skin in the scan's frame and unit
    similarity: calibration.Similarity  # scan frame -> template frame
    levels: list
    best_level: int
    functions: list                   # level functions, each x (template) -> displacement
    flagged: dict                     # FDP id -> reason
    dropped: list
    calibration_info: dict
    seconds: float
    distances: np.ndarray             # (n,) distance of each adapted skin vertex to the scan, m (nan: no match)
    scan: object = None               # the calibrated scan (template frame) with its queries
    unfolded: dict = None             # folded triangles after the fit, vertices relaxed, folds left
    outcome: dict = None              # how it ended: folds left, seen-skin RMS, marker RMS, warnings, ok

    def map_points(self, points):
        """Carry template-frame points (k,3) through the final adaptation map (template frame)."""
        points = np.asarray(points, dtype=np.float64)
        return points + sum(f(points) for f in self.functions)

    def to_scan(self, points):
        """Template-frame points (k,3) into the scan's frame and unit."""
        return self.similarity.inverse().apply(points)

    def report(self):
        """A JSON-ready dict: per level pairs/E_d/E_m/E/seconds, totals, flagged FDPs."""
        return {
            "levels": [dataclasses.asdict(lv) for lv in self.levels],
            "best_level": self.best_level,
            "stopped_because": ("E reached its minimum at level %d" % self.best_level
                                if self.best_level < self.levels[-1].level else "last level reached"),
            "seconds": self.seconds,
            "calibration": self.calibration_info,
            "flagged_fdps": self.flagged,
            "dropped_fdps": self.dropped,
            "unfolded": self.unfolded,
            "outcome": self.outcome,
            "units": "E_d, E_m, E in mm^2 of the template frame (paper eq 22-24); *_mm in mm",
        }


def _loo_residuals(centres, values):
    """Leave-one-out residuals of an interpolating phi(r)=r RBF with affine part (Rippa's formula)."""
    m = len(centres)
    a = np.zeros((m + 4, m + 4))
    a[:m, :m] = np.linalg.norm(centres[:, None] - centres[None], axis=2)
    a[:m, m:] = np.c_[centres, np.ones(m)]
    a[m:, :m] = a[:m, m:].T
    inv = np.linalg.pinv(a)
    coef = inv[:m, :m] @ values
    return np.linalg.norm(coef / np.diag(inv)[:m, None], axis=1)


def feature_mesh(points):
    """Triangles (k,3) over FDP positions (template frame): Delaunay on a cylinder around the head axis."""
    p = np.asarray(points)
    c = p.mean(axis=0)
    angle = np.arctan2(p[:, 0] - c[0], -(p[:, 1] - c[1]))
    radius = np.median(np.linalg.norm(p[:, :2] - c[:2], axis=1))
    uv = np.c_[angle * radius, p[:, 2]]
    tris = Delaunay(uv).simplices
    edges = np.linalg.norm(p[tris] - p[np.roll(tris, 1, axis=1)], axis=2)
    keep = edges.max(axis=1) < 0.45 * radius * 2
    # drop slivers along the convex hull of the parameter domain
    area = 0.5 * np.linalg.norm(np.cross(p[tris[:, 1]] - p[tris[:, 0]], p[tris[:, 2]] - p[tris[:, 0]]), axis=1)
    keep &= area > 1e-3 * edges.max(axis=1) ** 2
    return tris[keep]


def _face_weights(tpl):
    w = tpl.region_weights[tpl.region]
    return w[tpl.skin.tris].min(axis=1)


class _ScanSide:
    """The calibrated scan with its queries, normals, boundary and curvature (computed once)."""

    def __init__(self, verts, tris):
        self.verts, self.tris = verts, tris
        self.query = spatial.MeshQuery(verts, tris)
        self.face_normals = geometry.face_normals(verts, tris)
        self.vertex_normals = geometry.vertex_normals(verts, tris)
        self.boundary_faces = geometry.boundary_faces(tris)
        self._curv = None

    def curvature(self, region=None):
        """(H, valid) per scan vertex; with a vertex mask, computed on the triangles inside it only
        (the cut's border counts as boundary, so its vertices are not valid)."""
        if self._curv is None:
            tris = self.tris if region is None else self.tris[region[self.tris].all(axis=1)]
            self._curv = geometry.mean_curvature(self.verts, tris)
        return self._curv


def adapt(tpl, scan_verts, scan_tris, scan_fdps, options=AdaptOptions(), markers=None, progress=None):
    """Adapt the template skin onto a scan; scan and FDPs in the scan's frame/unit; returns AdaptResult.

    scan_fdps: {FDP id: (3,)} clicked on the scan. markers: optional {marker name: (3,)} on the
    scan (held out, for E_m). progress: optional callable(fraction 0..1, message).
    """
    t_start = time.perf_counter()
    say = progress or (lambda f, msg: None)
    scan_verts = np.asarray(scan_verts, dtype=np.float64)
    scan_tris = np.asarray(scan_tris)
    geometry.check_mesh(scan_verts, scan_tris, "scan")
    tpl_fdps = {k: p for k, p in tpl.fdp_points().items() if tpl.meta["fdps"][k]["part"] in SCANNER_VISIBLE_PARTS}
    given = calibration.validate_landmarks(scan_fdps, what="scan")
    unused = [k for k in given if k not in tpl_fdps]
    given = {k: v for k, v in given.items() if k in tpl_fdps}

    # 1. calibration (sec 3.1)
    say(0.02, "calibrating")
    sim, cal_info = calibration.calibrate(given, tpl_fdps, method=options.calibration)
    sv = sim.apply(scan_verts)
    q_fdp = {k: sim.apply(v) for k, v in given.items()}
    # normals out of the head, whatever winding the file has (pairs are matched by normals)
    scan_tris, flipped = geometry.orient_outward(sv, scan_tris, tpl.parts["cranium"].verts.mean(axis=0))
    cal_info = {**cal_info, "scan_pieces_turned": flipped}
    scan = _ScanSide(sv, scan_tris)
    width = float(np.ptp(tpl.skin.verts[:, 0]))
    threshold = width / 10.0

    # FDPs must lie on the scan
    names = list(q_fdp)
    _, _, dist = scan.query.closest_points(np.array([q_fdp[k] for k in names]))
    for k, d in zip(names, dist):
        limit = options.off_surface_mm * (2 if k in ("3.5", "3.6") else 1)
        if d * MM > limit:
            raise LandmarkError(f"FDP {k} ({mpeg4.FDPS[k].label}) is {d * MM:.1f} mm from the scan surface "
                                f"after calibration: landmarks must be picked on this scan (wrong file or unit?)")

    # 2. level 0 (sec 3.2) with wrong-click detection
    say(0.08, "level 0: global RBF on the FDPs")
    t0 = time.perf_counter()
    P = np.array([tpl_fdps[k] for k in names])
    Q = np.array([q_fdp[k] for k in names])
    loo = _loo_residuals(P, Q - P) * MM
    median = float(np.median(loo))
    dnn = np.sort(np.linalg.norm(P[:, None] - P[None], axis=2), axis=1)[:, 1] * MM   # isolation of each FDP
    limit = np.maximum.reduce([np.full(len(loo), options.flag_mm), 4 * median * np.ones(len(loo)), 0.6 * dnn])
    flagged = {k: f"leave-one-out residual {r:.1f} mm (median {median:.1f} mm, limit {lim:.1f} mm): "
                  "probably clicked at the wrong spot"
               for k, r, lim in zip(names, loo, limit) if r > lim}
    dropped = []
    if flagged and options.drop_flagged:
        keep = np.array([k not in flagged for k in names])
        dropped = [k for k in names if k in flagged]
        names = [k for k in names if k not in flagged]
        P, Q = P[keep], Q[keep]
    Q = _closed_mouth(names, P, Q)
    f0 = rbf.fit_rbf(P, Q - P, rho=options.rho)
    functions = [f0]
    V = tpl.skin.verts
    disp = f0(V)
    pairs_p, pairs_q = P, Q

    face_w = _face_weights(tpl)
    seam = lip_seam(tpl)
    vert_w = tpl.region_weights[tpl.region]
    # held-out markers: the template's named markers, or FDPs the user clicked but held out
    known = {**tpl.fdp_points(), **tpl.marker_points()}
    marker_names = [m for m in (markers or {}) if m in known and m not in names]
    marker_tpl = np.array([known[m] for m in marker_names]) if marker_names else None
    marker_scan = sim.apply(np.array([markers[m] for m in marker_names])) if marker_names else None

    last_dist = [None]

    def evaluate(disp_now):
        cur = V + disp_now
        de = metrics.distance_error(cur, geometry.vertex_normals(cur, tpl.skin.tris), scan.query,
                                    scan.face_normals, vert_w, threshold, scan.boundary_faces)
        e_d = float(np.sum(de.w * (de.dist * MM) ** 2) / len(cur))
        rms = float(np.sqrt(np.sum(de.w * (de.dist * MM) ** 2) / max(np.sum(de.w), 1e-12)))
        cover = float(np.sum(de.w > 0) / max(np.sum(vert_w > 0), 1))
        e_m = None
        if marker_tpl is not None:
            pred = marker_tpl + sum(f(marker_tpl) for f in functions)
            e_m = float(np.sum(((pred - marker_scan) * MM) ** 2))
        e = options.alpha * e_d + (options.beta * e_m if e_m is not None else 0.0)
        last_dist[0] = np.where(de.matched, de.dist, np.nan)
        return e_d, rms, e_m, e, cover

    e_d, rms, e_m, e, cover = evaluate(disp)
    levels = [Level(0, "rbf", len(P), len(P), e_d, rms, e_m, e, cover, time.perf_counter() - t0)]
    best, best_disp, best_funcs, best_dist = 0, disp, list(functions), last_dist[0]

    # feature mesh over the FDPs in use (missing FDPs simply have no triangles)
    fm_q = Q.copy()          # feature-mesh vertices, scan side (calibrated); the template side is
    fm_t = feature_mesh(P)   # where they sit on the deformed template, which interpolates them
    # the paper's box for the curvature search: eye to eye across, head top to mouth bottom
    box_names = [n for n in ("3.7", "3.12", "11.1", "2.1") if n in q_fdp]
    if len(box_names) == 4:
        lo_x, hi_x = sorted((q_fdp["3.12"][0], q_fdp["3.7"][0]))
        face_box = ((scan.verts[:, 0] > lo_x) & (scan.verts[:, 0] < hi_x) &
                    (scan.verts[:, 2] < q_fdp["11.1"][2]) & (scan.verts[:, 2] > q_fdp["2.1"][2]))
    else:
        face_box = np.ones(len(scan.verts), bool)
    dead = np.zeros(len(fm_t), bool)

    for k in range(1, options.max_levels + 1):
        say(0.1 + 0.85 * k / (options.max_levels + 1), f"level {k}: searching feature points")
        t0 = time.perf_counter()
        reach = max(threshold / 2 ** (k - 1), 0.002)
        new_p, new_q = [], []

        cur = V + disp
        cur_query = spatial.MeshQuery(cur, tpl.skin.tris)
        cur_n = geometry.face_normals(cur, tpl.skin.tris)

        # (a) feature-mesh subdivision (Kahler et al.): the deformed template and the scan share the
        #     feature mesh (its vertices are FP pairs), so one ray from each triangle's barycentre
        #     along its normal meets both surfaces: a new pair, and the triangle splits in three
        live = np.flatnonzero(~dead) if options.use_feature_mesh else np.zeros(0, int)
        if len(live):
            tri = fm_t[live]
            bq = fm_q[tri].mean(axis=1)
            nq = geometry.face_normals(fm_q, tri)
            size = np.linalg.norm(fm_q[tri] - bq[:, None], axis=2).max(axis=1)
            lim = np.minimum(0.5 * size, reach)
            ht = cur_query.ray_cast(bq, nq, lim)
            hs = scan.query.ray_cast(bq, nq, lim)
            ft, fs = np.where(ht.hit, ht.face, 0), np.where(hs.hit, hs.face, 0)
            ok = ht.hit & hs.hit & (face_w[ft] > 0) & ~scan.boundary_faces[fs]
            ok &= np.einsum("ij,ij->i", cur_n[ft], scan.face_normals[fs]) > 0.5
            dead[live[~ok]] = True
            acc = live[ok]
            if len(acc):
                tp = np.einsum("ij,ijk->ik", ht.bary[ok], V[tpl.skin.tris[ft[ok]]])
                base = len(fm_q)
                fm_q = np.vstack([fm_q, hs.point[ok]])
                idx = base + np.arange(len(acc))
                a, b, c = fm_t[acc, 0], fm_t[acc, 1], fm_t[acc, 2]
                fm_t[acc] = np.c_[a, b, idx]
                fm_t = np.vstack([fm_t, np.c_[b, c, idx], np.c_[c, a, idx]])
                dead = np.concatenate([dead, np.zeros(2 * len(acc), bool)])
                new_p.append(tp)
                new_q.append(hs.point[ok])

        # (b) mean-curvature search on the scan (appendix), inside the face box the paper uses,
        #     matched to the current template by rays along the scan normal
        H, valid = scan.curvature(face_box)
        cand = np.flatnonzero(valid & ~_near_boundary(scan) & face_box)
        n_pick = options.curvature_points * 2 ** (k - 1)
        if len(cand) and options.use_curvature:
            order = cand[np.argsort(-np.abs(H[cand]))]
            pick = _spread(scan.verts[order[: n_pick * 6]], threshold / 2 ** (k + 1))[:n_pick]
            src = order[pick]
            hit = cur_query.ray_cast(scan.verts[src], scan.vertex_normals[src], min(reach, options.curvature_reach))
            f = np.where(hit.hit, hit.face, 0)
            ok = hit.hit & (face_w[f] > 0)
            ok &= np.einsum("ij,ij->i", cur_n[f], scan.vertex_normals[src]) > 0.7
            if ok.any():
                tp = np.einsum("ij,ijk->ik", hit.bary[ok], V[tpl.skin.tris[f[ok]]])
                new_p.append(tp)
                new_q.append(scan.verts[src[ok]])

        # (c) surface samples: template vertices spread `spacing` apart, along the current normal to the
        #     scan (Kahler-style rays on a denser set; spacing halves per level)
        spacing = max(options.sample_spacing / 2 ** (k - 1), options.min_sample_spacing)
        cur_vn = geometry.vertex_normals(cur, tpl.skin.tris)
        seen = np.flatnonzero(vert_w > 0)
        pick = seen[_spread(V[seen], spacing)]
        hit = scan.query.ray_cast(cur[pick], cur_vn[pick], reach)
        f = np.where(hit.hit, hit.face, 0)
        ok = hit.hit & ~scan.boundary_faces[f] & (np.einsum("ij,ij->i", cur_vn[pick], scan.face_normals[f]) > 0.5)
        if ok.any():
            new_p.append(V[pick[ok]])
            new_q.append(hit.point[ok])

        if not new_p:
            break
        add_p, add_q = np.vstack(new_p), np.vstack(new_q)
        # the inner-lip seam: no pairs next to it (a ray there may land on the other lip); instead the
        # seam vertices are anchored where the previous level put them, so the lips stay closed
        far = cKDTree(V[seam]).query(add_p, distance_upper_bound=options.seam_band)[0] == np.inf
        add_p, add_q = add_p[far], add_q[far]
        pairs_p, pairs_q = np.vstack([pairs_p, add_p]), np.vstack([pairs_q, add_q])
        pairs_p, pairs_q = _dedupe(pairs_p, pairs_q, 2e-4)
        if options.thin_pairs > 0:     # at most one pair per thin_pairs x spacing (FDPs and older pairs first)
            keep = np.sort(_spread(pairs_p, options.thin_pairs * spacing))
            keep = np.union1d(keep, np.arange(len(P)))
            pairs_p, pairs_q = pairs_p[keep], pairs_q[keep]
        fit_p = np.vstack([pairs_p, V[seam]])
        fit_q = np.vstack([pairs_q, V[seam] + disp[seam]])
        fit_p, fit_q = _dedupe(fit_p, fit_q, 5e-4)
        say(0.1 + 0.85 * (k + 0.5) / (options.max_levels + 1), f"level {k}: fitting {len(pairs_p)} pairs")
        if len(pairs_p) < options.pair_threshold:
            fk = rbf.fit_rbf(fit_p, fit_q - fit_p, rho=options.rho)
            functions = [fk]
            method, sigma = "rbf", None
        else:
            sigma = options.support or options.support_factor * spacing
            resid = fit_q - (fit_p + sum(f(fit_p) for f in functions))
            functions = functions + [rbf.fit_csrbf(fit_p, resid, sigma)]
            method = "csrbf"
        disp = sum(f(V) for f in functions)
        e_d, rms, e_m, e, cover = evaluate(disp)
        levels.append(Level(k, method, len(pairs_p), len(add_p), e_d, rms, e_m, e, cover,
                            time.perf_counter() - t0, None if sigma is None else sigma * MM))
        if e < levels[best].E:
            best, best_disp, best_funcs, best_dist = k, disp, list(functions), last_dist[0]
        elif options.stop_at_minimum:
            break

    verts = V + best_disp
    # where the scan has no room for the template's detail (closed eyes under open lids) the fit
    # folds a few triangles over: relax the displacement around them until none is folded
    n_folded = len(geometry.folded(V, verts, tpl.skin.tris))
    verts, moved, left = geometry.unfold(V, verts, tpl.skin.tris)
    again = np.flatnonzero(moved & np.isfinite(best_dist))
    if len(again):                  # the relaxed vertices' distances to the scan, measured anew
        best_dist = best_dist.copy()
        best_dist[again] = scan.query.closest_points(verts[again])[2]
    unfolded = {"folded_triangles": n_folded, "vertices_relaxed": int(moved.sum()), "folded_left": left}
    marker_rms = None
    if marker_tpl is not None:
        pred = marker_tpl + sum(f(marker_tpl) for f in best_funcs)
        marker_rms = float(np.sqrt(np.mean(np.sum((pred - marker_scan) ** 2, axis=1)))) * MM
    outcome = fit_outcome(best_dist, vert_w, left, marker_rms, flagged, options)
    say(1.0, f"done: best level {best}")
    result = AdaptResult(verts=verts, verts_scan=sim.inverse().apply(verts), similarity=sim, levels=levels,
                         best_level=best, functions=best_funcs, flagged=flagged, dropped=dropped,
                         calibration_info={**cal_info, "unused_fdps": unused},
                         seconds=time.perf_counter() - t_start, distances=best_dist, scan=scan,
                         unfolded=unfolded, outcome=outcome)
    return result


def fit_outcome(distances, weights, folds_left, marker_rms_mm, flagged, options):
    """How a fit ended, honestly: folds left, distance RMS over the seen skin (mm), marker RMS (mm),
    one warning line per problem, and ok (False: no folds may be left, the RMS must stay under
    options.bad_fit_rms_mm)."""
    seen = np.isfinite(distances) & (weights > 0)
    rms = float(np.sqrt(np.mean(distances[seen] ** 2)) * MM) if seen.any() else float("nan")
    warnings = [f"FDP {k}: {why}" for k, why in flagged.items()]
    ok = True
    if folds_left:
        ok = False
        warnings.append(f"{folds_left} folded triangles left in the adapted skin")
    if not np.isfinite(rms) or rms > options.bad_fit_rms_mm:
        ok = False
        warnings.append(f"the adapted skin lies {rms:.2f} mm RMS from the scan over {int(seen.sum())} seen "
                        f"vertices (limit {options.bad_fit_rms_mm:.2f} mm): the fit did not reach the scan")
    return {"folds_left": int(folds_left), "seen_rms_mm": rms, "seen_vertices": int(seen.sum()),
            "marker_rms_mm": marker_rms_mm, "warnings": warnings, "ok": ok}


def lip_seam(tpl):
    """Skin vertex indices along the inner-lip seam (upper and lower lip vertices next to the mouth interior)."""
    q, region = tpl.skin.quads, tpl.region
    inside = region == tpl.region_names.index("mouth_interior")
    e = np.concatenate([q[:, [0, 1]], q[:, [1, 2]], q[:, [2, 3]], q[:, [3, 0]]])
    rim = np.zeros(len(region), bool)
    rim[e[inside[e[:, 0]] ^ inside[e[:, 1]]].ravel()] = True
    lips = np.isin(region, [tpl.region_names.index("upper_lip"), tpl.region_names.index("lower_lip")])
    return np.flatnonzero(rim & lips)


INNER_LIP_PAIRS = (("2.2", "2.3"), ("2.6", "2.8"), ("2.7", "2.9"))


def _closed_mouth(names, P, Q, closed=0.003):
    """On a closed mouth (inner-lip clicks within 3 mm), give each upper/lower inner-lip FDP pair the
    template's own small offset about the clicks' midpoint, so click noise cannot cross the lips."""
    Q = Q.copy()
    pos = {k: i for i, k in enumerate(names)}
    for a, b in INNER_LIP_PAIRS:
        if a in pos and b in pos:
            i, j = pos[a], pos[b]
            if np.linalg.norm(Q[i] - Q[j]) < closed:
                mid, half = 0.5 * (Q[i] + Q[j]), 0.5 * (P[i] - P[j])
                Q[i], Q[j] = mid + half, mid - half
    return Q


def _near_boundary(scan):
    """Scan vertices on or next to a boundary (their curvature is not trusted, paper sec 4.1)."""
    mask = np.zeros(len(scan.verts), bool)
    mask[scan.tris[scan.boundary_faces].ravel()] = True
    return mask


def _spread(points, radius):
    """Indices of a greedy subset of points (in the given priority order) at least radius apart.

    Exact greedy on a grid: points are bucketed in cells of side radius; the Python loop runs
    over occupied cells' candidates only where two candidates could conflict.
    """
    from scipy.spatial import cKDTree

    if len(points) == 0:
        return np.zeros(0, int)
    points = np.asarray(points)
    # first pass (vectorised): the first point of each cell of side radius/sqrt(3) is taken for sure
    # if no earlier-taken point can be within radius -- resolved by the exact greedy below on few points
    tree = cKDTree(points)
    pairs = tree.query_pairs(radius, output_type="ndarray")
    if len(pairs) == 0:
        return np.arange(len(points))
    # conflicts: for each point, its earlier neighbours
    lo, hi = np.minimum(pairs[:, 0], pairs[:, 1]), np.maximum(pairs[:, 0], pairs[:, 1])
    order = np.argsort(hi, kind="stable")
    lo, hi = lo[order], hi[order]
    starts = np.searchsorted(hi, np.arange(len(points)))
    ends = np.searchsorted(hi, np.arange(len(points)), side="right")
    taken = np.zeros(len(points), bool)
    has_earlier = ends > starts
    taken[~has_earlier] = True           # no earlier neighbour: always taken
    for i in np.flatnonzero(has_earlier):  # only points with earlier neighbours need the greedy test
        taken[i] = not taken[lo[starts[i]:ends[i]]].any()
    return np.flatnonzero(taken)


def _dedupe(p, q, tol):
    """Drop pairs whose template point repeats an earlier one within tol (keeps the first)."""
    key = np.round(p / tol).astype(np.int64)
    _, first = np.unique(key, axis=0, return_index=True)
    first = np.sort(first)
    return p[first], q[first]
