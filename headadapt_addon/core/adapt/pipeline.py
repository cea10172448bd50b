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
from scipy import sparse
from scipy.sparse.linalg import splu
from scipy.spatial import Delaunay, cKDTree

from . import calibration, metrics, rbf
from ..mesh import geometry, spatial
from .. import mpeg4
from ..exceptions import LandmarkError

MM = 1000.0
TINY = 1e-12
JACOBI_STEPS = 250      # a level's solve factorises (sparse LU) after this many diagonal-preconditioned CG steps
LU_STEPS = 30           # ... and refactorises when CG preconditioned by that LU takes more
DENSE_SPACING = 0.002   # a scan whose median edge is shorter is paired by tangent planes, m
SCANNER_VISIBLE_PARTS = ("skin", "eye_l", "eye_r")
# the face: what the outcome judges the fit by (hair, a crown or a collar may cover scalp and neck)
FACE_REGIONS = ("forehead", "brow_l", "brow_r", "eyelid_l", "eyelid_r", "nose", "cheek_l", "cheek_r",
                "upper_lip", "lower_lip", "chin_jaw")


@dataclasses.dataclass(frozen=True)
class AdaptOptions:
    """Settings of one adaptation run (lengths in metres of the template frame)."""
    max_levels: int = 4                 # levels after level 0
    rho: float = 0.0                    # level-0 smoothing (eq 9), m
    support: float | None = None        # fixed CSRBF support sigma (m); default: support_factor x spacing
    calibration: str = "auto"           # "paper", "umeyama" or "auto"
    drop_flagged: bool = True           # drop FDPs confirmed as wrongly clicked and refit level 0
    confirm_mm: float = 10.0            # a click this far from where a coarse fit to the surface and the
                                        # other clicks puts its FDP is wrong, mm (people disagree by ~3 mm,
                                        # a coarse fit errs by ~5; a slip of the hand is 20)
    confirm_factor: float = 3.0         # ... or this x the clicks' median distance there, if larger
    off_surface_mm: float = 12.0        # an FDP farther than this from the scan surface is an error
    curvature_points: int = 150         # scan curvature points at level 1 (doubles per level)
    sample_spacing: float = 0.016       # spacing of the CSRBF centres at level 1 (halves per level), m
    min_sample_spacing: float = 0.002   # finest centre spacing, m
    support_factor: float = 3.0         # CSRBF support = this x the level's spacing
    centre_density: float = 3.0         # a level's CSRBF centres lie its support / this apart
    reach_factor: float = 1.0           # closest-point pairs are kept within this x width/10 at level 1 (halving)
    min_reach: float = 0.002            # closest-point pairs are kept within threshold/2^(k-1), at least this, m
    use_feature_mesh: bool = True       # pairs from feature-mesh subdivision (sec 4.1, Kahler et al.)
    use_curvature: bool = True          # pairs from the scan's mean-curvature search (sec 4.1, appendix)
    curvature_reach: float = 0.004      # farthest a curvature point may be from the template, m
    feature_weight: float = 1.0         # weight of a feature-mesh pair (a surface pair weighs 1)
    curvature_weight: float = 1.0       # weight of a curvature pair
    affine_iterations: int = 8          # ICP rounds of the whole-skin affine map before the clicks' RBF
    affine_skip: tuple = ()             # regions the affine map does not fit
    affine_ridge: float = 1e-3          # how firmly the affine map's linear part is held to the identity
    rays_from_level: int = 2            # from this level on, pairs along the template's normal (sec 4.1)
    fold_rounds: int = 2                # refits of a level without pairs around the triangles it folded
    icp_iterations: int = 3             # closest-point pairing and refit rounds per level
    stiffness: float = 10.0             # smoothness of a level: ridge on its CSRBF coefficients, relative
                                        # to the data weight a centre carries (nricp's stiffness, in effect)
    stiffness_decay: float = 0.2        # the stiffness per level falls by this factor
    min_stiffness: float = 0.0          # down to this
    robust_scale: float = 0.5           # Cauchy weight scale of a surface pair, x the level's reach
    click_weight: float = 20.0          # a click weighs as much as this many surface pairs at level 1
    click_decay: float = 0.25           # and this factor less at each finer level (evidence, not law)
    seam_band: float = 0.004            # no pairs within this of the inner-lip seam (template frame), m
    alpha: float = 1.0                  # weight of E_d in E (eq 24)
    beta: float = 0.01                  # weight of E_m in E (E_m sums over markers, E_d averages)
    stop_at_minimum: bool = True        # stop when E rises (sec 5.3)
    anatomy_support: float = 0.024      # bone, eyes and pivots follow the levels of at least this support, m
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
    anatomy_support: float = 0.0      # map_points uses the levels with at least this support, m

    def map_points(self, points):
        """Carry template-frame points (k,3) inside the head (bone, eyes, pivots) through the
        adaptation map (template frame): the levels whose support reaches under the skin
        (AdaptOptions.anatomy_support); the finer ones shape the skin's surface only, and would
        bend bone a few millimetres under it (anatomy.keep_inside keeps the bone under the skin)."""
        points = np.asarray(points, dtype=np.float64)
        return points + sum(f(points) for f in self.functions
                            if getattr(f, "sigma", np.inf) >= self.anatomy_support)

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


def feature_mesh(points, centre):
    """Triangles (k,3) over FDP positions (template frame): Delaunay on a cylinder around the head's
    vertical axis through `centre` (the head's, not the points': a few clicks on the face are all in
    front of it)."""
    p = np.asarray(points)
    c = np.asarray(centre)
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
        self.boundary_verts = np.zeros(len(verts), bool)
        self.boundary_verts[tris[self.boundary_faces].ravel()] = True
        self.vertex_tree = cKDTree(verts)
        self.coarse = np.median(np.linalg.norm(verts[tris[:, 0]] - verts[tris[:, 1]], axis=1)) > DENSE_SPACING
        self._curv = None

    def nearest_on_plane(self, points):
        """(point, normal, distance, on a hole's border) per query point for ICP pairs: on a dense scan
        the nearest scan vertex's tangent plane (a fast stand-in for the closest surface point: off
        by curvature x spacing^2 / 2, under 0.05 mm at 2 mm spacing), else the closest point."""
        if self.coarse:
            q, f, d = self.query.closest_points(points)
            return q, self.face_normals[f], d, self.boundary_faces[f]
        _, i = self.vertex_tree.query(points)
        n = self.vertex_normals[i]
        q = points - np.einsum("ij,ij->i", points - self.verts[i], n)[:, None] * n
        return q, n, np.linalg.norm(q - points, axis=1), self.boundary_verts[i]

    def curvature(self, region=None):
        """(H, valid) per scan vertex; with a vertex mask, computed on the triangles inside it only
        (the cut's border counts as boundary, so its vertices are not valid)."""
        if self._curv is None:
            tris = self.tris if region is None else self.tris[region[self.tris].all(axis=1)]
            self._curv = geometry.mean_curvature(self.verts, tris)
        return self._curv


@dataclasses.dataclass
class Pairs:
    """Feature-point pairs: template points at rest (k,3), their targets (k,3), weights (k,), and the
    skin vertex each template point is (-1: a point between vertices)."""
    p: np.ndarray
    q: np.ndarray
    w: np.ndarray
    vertex: np.ndarray = None

    def __post_init__(self):
        if self.vertex is None:
            self.vertex = np.full(len(self.p), -1)

    @staticmethod
    def empty():
        return Pairs(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0))

    def __len__(self):
        return len(self.p)

    def __add__(self, other):
        return Pairs(np.vstack([self.p, other.p]), np.vstack([self.q, other.q]), np.concatenate([self.w, other.w]),
                     np.concatenate([self.vertex, other.vertex]))

    def take(self, mask):
        return Pairs(self.p[mask], self.q[mask], self.w[mask], self.vertex[mask])


class _Fit:
    """What the level loop shares: template, scan, options, the fitted level functions so far."""

    def __init__(self, tpl, scan, options, threshold):
        self.tpl, self.scan, self.options, self.threshold = tpl, scan, options, threshold
        self.V = tpl.skin.verts
        self.tris = tpl.skin.tris
        self.vert_w = tpl.region_weights[tpl.region]
        self.face_w = _face_weights(tpl)
        self.seam = lip_seam(tpl)
        self.near_seam = cKDTree(self.V[self.seam]).query(self.V, distance_upper_bound=options.seam_band)[0] < np.inf
        self.functions = []
        self.folds = geometry.FoldCheck(self.V, self.tris)
        adjacency = geometry.neighbour_mean(self.tris, len(self.V))
        self.ring = (adjacency + sparse.identity(len(self.V))).tocsr()   # a vertex and its neighbours
        self.quiet = np.zeros(len(self.V), bool)     # vertices a level leaves to its smoothness term
        # the global affine map is fitted to these regions (a scan's neck is cut and posed anyhow)
        self.affine_mask = ~np.isin(tpl.region, [tpl.region_names.index(r) for r in options.affine_skip])
        self._at_skin = {}
        self._bases = {}
        self.warm = {}              # last coefficients per support: the next ICP round starts there
        self.factor = {}            # a sparse LU per support, once a level's system needed one
        # umbrella Laplacian of the skin (x_i minus its neighbours' mean) for the smoothness term
        self.laplacian = (sparse.identity(len(self.V), format="csr") - geometry.neighbour_mean(self.tris, len(self.V))).tocsr()

    def distance_error(self, verts, exact=False):
        """metrics.DistanceError of skin positions (n,3) against the scan (sec 5.1): nearest points
        by the scan's tangent planes while fitting (exact=False), exact closest points to report."""
        normals = geometry.vertex_normals(verts, self.tris)
        if exact:
            return metrics.distance_error(verts, normals, self.scan.query, self.scan.face_normals, self.vert_w,
                                          self.threshold, self.scan.boundary_faces)
        _, n, d, border = self.scan.nearest_on_plane(verts)
        matched = (d <= self.threshold) & (np.einsum("ij,ij->i", normals, n) > 0) & ~border
        w = np.where(matched, self.vert_w, 0.0)
        return metrics.DistanceError(float(np.sum(w * d ** 2) / len(verts)), d, w, matched)

    def level_basis(self, sigma):
        """(centres, their kd-tree, the umbrella Laplacian of their Wendland functions on the skin,
        its Gram matrix) of a level with support sigma, built once per support."""
        if sigma not in self._bases:
            centres = self.V[_spread(self.V, sigma / self.options.centre_density)]
            tree = cKDTree(centres)
            res = cKDTree(self.V).sparse_distance_matrix(tree, sigma, output_type="ndarray")
            phi = sparse.csr_matrix((rbf.wendland(res["v"], sigma), (res["i"], res["j"])),
                                    shape=(len(self.V), len(centres)))
            bend = (self.laplacian @ phi).tocsr()
            self._bases[sigma] = (centres, tree, bend, (bend.T @ bend).tocsc())
        return self._bases[sigma]

    def reach(self, k):
        """How far a closest-point pair may reach at level k (halving per level), m."""
        return max(self.options.reach_factor * self.threshold / 2 ** (k - 1), self.options.min_reach)

    def displacement(self, x, functions=None):
        fs = self.functions if functions is None else functions
        return sum((f(x) for f in fs), np.zeros_like(np.asarray(x, dtype=np.float64)))

    def current(self):
        """The deformed skin now (n,3); each level function is evaluated on the skin once."""
        for f in self.functions:
            if id(f) not in self._at_skin:
                self._at_skin[id(f)] = (f, f(self.V))
        return self.V + sum((self._at_skin[id(f)][1] for f in self.functions), np.zeros_like(self.V))

    def at(self, pairs):
        """The deformed template at the pairs' template points (the skin's vertices looked up)."""
        cur = self.current()
        out = np.empty_like(pairs.p)
        on = pairs.vertex >= 0
        out[on] = cur[pairs.vertex[on]]
        out[~on] = pairs.p[~on] + self.displacement(pairs.p[~on])
        return out


def global_rbf(P, Q, rho=0.0):
    """Level 0 (sec 3.2): the global RBF phi(r) = r with an affine part and smoothing rho, taking the
    template's FDPs P (m,3) onto the clicked ones Q (m,3); returns the displacement function."""
    return rbf.fit_rbf(P, Q - P, rho=rho)


class AffineMap:
    """The displacement x -> (M x + t) - x of an affine map (a level-0 function like the others)."""

    def __init__(self, matrix, shift):
        self.matrix, self.shift = matrix, shift

    def __call__(self, x):
        x = np.atleast_2d(np.asarray(x, dtype=np.float64))
        return x @ (self.matrix - np.eye(3)).T + self.shift


def global_affine(fit, clicks, reach, iterations, ridge=1e-3):
    """Level 0, first half: the affine map that best takes the whole template skin onto the scan
    (closest points, robust weights) and the clicks onto their places, by a few ICP rounds from the
    calibrated pose. The clicks sit on the front of the face and cannot say how deep or wide the
    head is; the scan can. The map's linear part is held near the identity by a small ridge."""
    centre = fit.V.mean(axis=0)
    fit.functions = [AffineMap(np.eye(3), np.zeros(3))]
    for _ in range(iterations):
        pairs = surface_pairs(fit, reach, mask=fit.affine_mask) + clicks
        X = np.c_[pairs.p - centre, np.ones(len(pairs))]
        XtW = X.T * pairs.w
        reg = ridge * pairs.w.sum() * np.diag([np.mean((fit.V - centre) ** 2)] * 3 + [0.0])
        D = np.linalg.solve(XtW @ X + reg, XtW @ (pairs.q - pairs.p))     # displacement, affine in x
        matrix = np.eye(3) + D[:3].T
        fit.functions = [AffineMap(matrix, D[3] - D[:3].T @ centre)]
    return fit.functions[0]


def feature_mesh_pairs(fit, mesh, reach):
    """Pairs from feature-mesh subdivision (sec 4.1, Kahler et al.): the deformed template and the scan
    share the feature mesh (its vertices are FP pairs), so one ray from each live triangle's
    barycentre along its normal meets both surfaces: a new pair, and the triangle splits in three.
    `mesh` is (fm_q scan-side vertices, fm_t triangles, dead mask) and is updated in place."""
    fm_q, fm_t, dead = mesh["q"], mesh["t"], mesh["dead"]
    live = np.flatnonzero(~dead)
    if not len(live):
        return Pairs.empty()
    cur = fit.current()
    cur_query = spatial.MeshQuery(cur, fit.tris)
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


def curvature_pairs(fit, face_box, count, reach, spread):
    """Pairs from the scan's mean-curvature extremes (sec 4.1, appendix: Meyer et al.) inside the
    paper's face box, `spread` apart, matched to the current template by rays along the scan normal."""
    scan = fit.scan
    H, valid = scan.curvature(face_box)
    cand = np.flatnonzero(valid & ~_near_boundary(scan) & face_box)
    if not len(cand):
        return Pairs.empty()
    order = cand[np.argsort(-np.abs(H[cand]))]
    src = order[_spread(scan.verts[order[: count * 6]], spread)[:count]]
    cur = fit.current()
    hit = spatial.MeshQuery(cur, fit.tris).ray_cast(scan.verts[src], scan.vertex_normals[src], reach)
    f = np.where(hit.hit, hit.face, 0)
    ok = hit.hit & (fit.face_w[f] > 0)
    ok &= np.einsum("ij,ij->i", geometry.face_normals(cur, fit.tris)[f], scan.vertex_normals[src]) > 0.7
    tp = np.einsum("ij,ijk->ik", hit.bary[ok], fit.V[fit.tris[f[ok]]])
    return Pairs(tp, scan.verts[src[ok]], np.full(len(tp), fit.options.curvature_weight))


def surface_pairs(fit, reach, along_normal=False, mask=None):
    """Pairs of the seen template vertices with the scan, kept when within `reach`, the normals agree
    within 60 degrees and the point is not on a hole's border, weighted by region and by a robust
    (Cauchy) weight on the distance. Coarse levels take the closest point (non-rigid ICP: the
    template slides until its shapes meet the scan's); fine levels cast along the template's normal
    (the paper's rays: no sideways pull, so nothing folds where the scan lacks the template's detail)."""
    cur = fit.current()
    normals = geometry.vertex_normals(cur, fit.tris)
    use = np.flatnonzero((fit.vert_w > 0) & ~fit.near_seam & ~fit.quiet & (True if mask is None else mask))
    if along_normal:
        hit = fit.scan.query.ray_cast(cur[use], normals[use], reach)
        f = np.where(hit.hit, hit.face, 0)
        q, n, d, border = np.nan_to_num(hit.point), fit.scan.face_normals[f], np.abs(np.nan_to_num(hit.t, nan=np.inf)), \
            fit.scan.boundary_faces[f] | ~hit.hit
    else:
        q, n, d, border = fit.scan.nearest_on_plane(cur[use])
    ok = (d < reach) & ~border & (np.einsum("ij,ij->i", normals[use], n) > 0.5)
    w = fit.vert_w[use] / (1.0 + (np.minimum(d, reach) / (fit.options.robust_scale * reach)) ** 2)
    return Pairs(fit.V[use[ok]], q[ok], w[ok], use[ok])


def csrbf_level(fit, pairs, sigma, stiffness):
    """One level's offset function (sec 3.3) fitted to the pairs with a smoothness term: the CSRBF
    o(x) = sum_j c_j phi_sigma(|x - p_j|) on centres spread over the template skin sigma/support_factor
    apart, with c minimising sum_i w_i |f(p_i) + o(p_i) - q_i|^2 + lambda sum_j |c_j|^2, where
    lambda = stiffness x the mean data weight a centre carries (so it means the same at every level).
    Returns (the CSRBF, its coefficient system's size)."""
    centres, tree, bend, R = fit.level_basis(sigma)
    res = cKDTree(pairs.p).sparse_distance_matrix(tree, sigma, output_type="ndarray")
    phi = sparse.csr_matrix((rbf.wendland(res["v"], sigma), (res["i"], res["j"])), shape=(len(pairs), len(centres)))
    resid = pairs.q - fit.at(pairs)
    A = (phi.T @ sparse.diags(pairs.w) @ phi).tocsc()
    # the bending of the whole displacement (levels below included), so a level may undo what the
    # clicks' interpolation bent where the scan does not ask for it
    lam = stiffness * A.diagonal().sum() / max(R.diagonal().sum(), TINY)
    A = A + lam * R + 1e-6 * lam * sparse.identity(len(centres), format="csc")
    rhs = phi.T @ (pairs.w[:, None] * resid) - lam * (bend.T @ (fit.laplacian @ (fit.current() - fit.V)))
    coef, fit.factor[sigma] = _solve_spd(A.tocsr(), np.asarray(rhs), fit.warm.get(sigma), fit.factor.get(sigma))
    fit.warm[sigma] = coef
    zero = np.zeros((len(centres), 3))
    return rbf.CSRBF(centres, sigma, zero, np.zeros((len(centres), 3, 3)), coef, A)


def level_zero(fit, clicks):
    """Level 0 (sec 3.2): the whole-skin affine map fitted to the scan and the clicks (global_affine),
    or, when that is switched off, the paper's global RBF through the clicks."""
    o = fit.options
    if o.affine_iterations < 0:
        fit.functions = [AffineMap(np.eye(3), np.zeros(3))]
    elif o.affine_iterations:
        global_affine(fit, Pairs(clicks.p, clicks.q, clicks.w * o.click_weight),
                      o.reach_factor * fit.threshold, o.affine_iterations, o.affine_ridge)
    else:
        fit.functions = [global_rbf(clicks.p, clicks.q, o.rho)]


def fit_level(fit, clicks, k, fixed=None, rounds=None):
    """Level k (sec 4) as non-rigid ICP: a few rounds of surface pairs plus the level's fixed pairs
    (feature mesh, curvature) and the clicks as soft pairs, each round refitting the level's CSRBF
    (csrbf_level); then refits without the pairs around any triangle it folded. Returns (the last
    round's pairs, sigma)."""
    o = fit.options
    sigma = o.support or o.support_factor * max(o.sample_spacing / 2 ** (k - 1), o.min_sample_spacing)
    stiffness = max(o.stiffness * o.stiffness_decay ** (k - 1), o.min_stiffness)
    fixed = Pairs.empty() if fixed is None else fixed
    far = cKDTree(fit.V[fit.seam]).query(fixed.p, distance_upper_bound=o.seam_band)[0] == np.inf
    fixed = fixed.take(far)
    # clicks are evidence, not law: their weight falls per level so the surface decides the detail
    soft = Pairs(clicks.p, clicks.q, clicks.w * o.click_weight * o.click_decay ** (k - 1))
    below = list(fit.functions)
    fit.quiet[:] = False
    for _ in range(o.icp_iterations if rounds is None else rounds):
        pairs = surface_pairs(fit, fit.reach(k), k >= o.rays_from_level) + fixed + soft
        fit.functions = below + [csrbf_level(fit, pairs, sigma, stiffness)]
    if rounds is not None:
        return pairs, sigma
    # where the scan has no room for the template's detail (closed or carved eyes, a statue's ears)
    # the pairs fold the skin: those places are left to the smoothness term, and the level refitted
    for _ in range(o.fold_rounds):
        folds = fit.folds(fit.current())
        if not len(folds):
            break
        around = np.zeros(len(fit.V), bool)
        around[fit.tris[folds].ravel()] = True
        fit.quiet |= (fit.ring @ around) > 0
        pairs = surface_pairs(fit, fit.reach(k), k >= o.rays_from_level) + fixed + soft
        fit.functions = below + [csrbf_level(fit, pairs, sigma, stiffness)]
    return pairs, sigma


def _cg_rtol_keyword():
    """scipy 1.12 renamed cg's relative tolerance tol -> rtol (Debian's Blender 3.4 brings scipy 1.10)."""
    import inspect

    from scipy.sparse.linalg import cg
    return "rtol" if "rtol" in inspect.signature(cg).parameters else "tol"


_CG_RTOL = _cg_rtol_keyword()


def _solve_spd(A, b, x0=None, factor=None, rtol=1e-5):
    """Solve a level's symmetric positive definite A x = b (k right-hand sides); returns (x, the
    sparse LU used or None). Conjugate gradients preconditioned by A's diagonal, started from x0
    (the last ICP round's solution: the rounds of a level change A little), answer well-posed
    systems fast: the finest level of a 31k-vertex scan-like head in about 130 steps (60 ms), where
    a sparse LU took 150 ms. Where few pairs reach the level's centres (a face-only scan: Fran, the
    CT) the smoothness term dominates and CG crawls (800 steps); after JACOBI_STEPS the system is
    factorised (sparse LU), and the level's later rounds use that factorisation, passed back in as
    `factor`, to precondition CG, refactorising only if that fails within LU_STEPS."""
    from scipy.sparse.linalg import LinearOperator, cg

    def krylov(precondition, steps):
        out = np.empty_like(b)
        for c in range(b.shape[1]):
            out[:, c], info = cg(A, b[:, c], x0=None if x0 is None else x0[:, c], atol=0.0, maxiter=steps,
                                 M=precondition, **{_CG_RTOL: rtol})
            if info > 0:
                return None
        return out

    if factor is None:
        x = krylov(sparse.diags(1.0 / A.diagonal()), JACOBI_STEPS)
    else:
        x = krylov(LinearOperator(A.shape, matvec=lambda v: factor.solve(np.ascontiguousarray(v))), LU_STEPS)
    if x is not None:
        return x, factor
    factor = splu(A.tocsc(), permc_spec="MMD_AT_PLUS_A")
    return factor.solve(np.ascontiguousarray(b)), factor


def check_clicks(fit, names, P, Q, weights):
    """Wrong-click detection (sec 8), by the scan's surface rather than by the other clicks alone:
    a coarse fit (level 0 and level 1) to the surface and all clicks as soft pairs puts each FDP
    where the surface and the others say; the click farthest from there, if over confirm_mm, is
    checked by the same fit without it and dropped only if it is still that far. A right click on a
    feature the others cannot predict (the nose tip) agrees with the surface and is kept; at least
    calibration.MIN_FDPS clicks always remain. Returns {name: reason} of the clicks to drop."""
    o = fit.options
    keep = np.ones(len(names), bool)
    out = {}

    def offsets():
        clicks = Pairs(P[keep], Q[keep], weights[keep])
        level_zero(fit, clicks)
        fit_level(fit, clicks, 1, rounds=1)
        return np.linalg.norm(P + fit.displacement(P) - Q, axis=1) * MM

    off = offsets()
    while keep.sum() > calibration.MIN_FDPS:
        i = int(np.argmax(np.where(keep, off, -1.0)))
        # a face far from the template (a statue, a coarse scan) puts every click farther off
        limit = max(o.confirm_mm, o.confirm_factor * float(np.median(off[keep])))
        if off[i] <= limit:
            break
        keep[i] = False
        without = offsets()
        if without[i] <= limit:               # the surface agrees with it after all
            keep[i] = True
            break
        out[names[i]] = (f"{without[i]:.1f} mm from where the scan's surface and the other clicks put it "
                         f"(limit {limit:.1f} mm): probably clicked at the wrong spot")
        off = without
    return out


def adapt(tpl, scan_verts, scan_tris, scan_fdps, options=AdaptOptions(), markers=None, progress=None):
    """Adapt the template skin onto a scan; scan and FDPs in the scan's frame/unit; returns AdaptResult.

    scan_fdps: {FDP id: (3,)} clicked on the scan. markers: optional {marker name or held-out FDP id:
    (3,)} on the scan (for E_m). progress: optional callable(fraction 0..1, message).
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

    # 1. calibration (sec 3.1), after left/right labels that look swapped are put right
    say(0.02, "calibrating")
    given, handed = calibration.check_handedness(given, tpl_fdps)
    sim, cal_info = calibration.calibrate(given, tpl_fdps, method=options.calibration)
    sv = sim.apply(scan_verts)
    q_fdp = {k: sim.apply(v) for k, v in given.items()}
    # normals out of the head, whatever winding the file has (pairs are matched by normals)
    scan_tris, flipped = geometry.orient_outward(sv, scan_tris, tpl.parts["cranium"].verts.mean(axis=0))
    notes = _handedness_notes(handed, flipped)
    cal_info = {**cal_info, "scan_pieces_turned": flipped, "handedness": {**handed, "notes": notes}}
    scan = _ScanSide(sv, scan_tris)
    width = float(np.ptp(tpl.skin.verts[:, 0]))
    threshold = width / 10.0
    fit = _Fit(tpl, scan, options, threshold)

    # FDPs must lie on the scan
    names = list(q_fdp)
    _, _, dist = scan.query.closest_points(np.array([q_fdp[k] for k in names]))
    for k, d in zip(names, dist):
        limit = options.off_surface_mm * (2 if k in ("3.5", "3.6") else 1)
        if d * MM > limit:
            raise LandmarkError(f"FDP {k} ({mpeg4.FDPS[k].label}) is {d * MM:.1f} mm from the scan surface "
                                f"after calibration: landmarks must be picked on this scan (wrong file or unit?)")

    # 2. level 0 (sec 3.2), after wrong-click detection
    say(0.08, "level 0: global RBF on the FDPs")
    t0 = time.perf_counter()
    P = np.array([tpl_fdps[k] for k in names])
    Q = np.array([q_fdp[k] for k in names])
    click_w = np.ones(len(names))
    flagged = check_clicks(fit, names, P, Q, click_w)
    dropped = []
    if flagged and options.drop_flagged:
        keep = np.array([k not in flagged for k in names])
        dropped = [k for k in names if k in flagged]
        names = [k for k in names if k not in flagged]
        P, Q, click_w = P[keep], Q[keep], click_w[keep]
    Q = _closed_mouth(names, P, Q)
    V = fit.V
    clicks = Pairs(P, Q, click_w)
    level_zero(fit, clicks)

    # held-out markers: the template's named markers, or FDPs the user clicked but held out
    known = {**tpl.fdp_points(), **tpl.marker_points()}
    marker_names = [m for m in (markers or {}) if m in known and m not in names]
    marker_tpl = np.array([known[m] for m in marker_names]) if marker_names else None
    marker_scan = sim.apply(np.array([markers[m] for m in marker_names])) if marker_names else None

    def evaluate():
        cur = fit.current()
        de = fit.distance_error(cur)
        e_d = float(np.sum(de.w * (de.dist * MM) ** 2) / len(cur))
        rms = float(np.sqrt(np.sum(de.w * (de.dist * MM) ** 2) / max(np.sum(de.w), TINY)))
        cover = float(np.sum(de.w > 0) / max(np.sum(fit.vert_w > 0), 1))
        e_m = None
        if marker_tpl is not None:
            e_m = float(np.sum(((marker_tpl + fit.displacement(marker_tpl) - marker_scan) * MM) ** 2))
        e = options.alpha * e_d + (options.beta * e_m if e_m is not None else 0.0)
        return cur, np.where(de.matched, de.dist, np.nan), (e_d, rms, e_m, e, cover)

    cur, dist_now, errs = evaluate()
    levels = [Level(0, "rbf", len(P), len(P), *errs, time.perf_counter() - t0)]
    best, best_verts, best_funcs, best_dist = 0, cur, list(fit.functions), dist_now

    # the feature mesh over the FDPs in use (its template side is where they sit on the deformed template)
    fmesh = {"q": Q.copy(), "t": feature_mesh(P, V.mean(axis=0)), "dead": None}
    fmesh["dead"] = np.zeros(len(fmesh["t"]), bool)
    face_box = _face_box(scan, q_fdp)

    # 3. levels 1..K (sec 4): new pairs, then a CSRBF offset with support halving per level
    for k in range(1, options.max_levels + 1):
        say(0.1 + 0.85 * k / (options.max_levels + 1), f"level {k}: searching feature points")
        t0 = time.perf_counter()
        fixed = Pairs.empty()
        reach = fit.reach(k)
        if options.use_feature_mesh:
            fixed = fixed + feature_mesh_pairs(fit, fmesh, reach)
        if options.use_curvature:
            fixed = fixed + curvature_pairs(fit, face_box, options.curvature_points * 2 ** (k - 1),
                                            min(reach, options.curvature_reach), threshold / 2 ** (k + 1))
        say(0.1 + 0.85 * (k + 0.5) / (options.max_levels + 1), f"level {k}: fitting")
        pairs, sigma = fit_level(fit, clicks, k, fixed)
        cur, dist_now, errs = evaluate()
        levels.append(Level(k, "csrbf", len(pairs), len(fixed), *errs,
                            time.perf_counter() - t0, sigma * MM))
        if errs[3] < levels[best].E:
            best, best_verts, best_funcs, best_dist = k, cur, list(fit.functions), dist_now
        elif options.stop_at_minimum:
            break

    # where the scan has no room for the template's detail (closed eyes under open lids) the fit
    # folds a few triangles over: relax the displacement around them until none is folded
    n_folded = len(geometry.folded(V, best_verts, fit.tris))
    verts, moved, left = geometry.unfold(V, best_verts, fit.tris)
    # the distances reported: exact closest points on the scan, by the paper's compatibility rule
    de = fit.distance_error(verts, exact=True)
    best_dist = np.where(de.matched, de.dist, np.nan)
    unfolded = {"folded_triangles": n_folded, "vertices_relaxed": int(moved.sum()), "folded_left": left}
    marker_rms = None
    if marker_tpl is not None:
        pred = marker_tpl + fit.displacement(marker_tpl, best_funcs)
        marker_rms = float(np.sqrt(np.mean(np.sum((pred - marker_scan) ** 2, axis=1)))) * MM
    face = np.isin(tpl.region, [tpl.region_names.index(r) for r in FACE_REGIONS])
    outcome = fit_outcome(best_dist, face, left, marker_rms, flagged, options, notes)
    say(1.0, f"done: best level {best}")
    return AdaptResult(verts=verts, verts_scan=sim.inverse().apply(verts), similarity=sim, levels=levels,
                       best_level=best, functions=best_funcs, flagged=flagged, dropped=dropped,
                       calibration_info={**cal_info, "unused_fdps": unused},
                       seconds=time.perf_counter() - t_start, distances=best_dist, scan=scan,
                       unfolded=unfolded, outcome=outcome, anatomy_support=options.anatomy_support)


def _face_box(scan, q_fdp):
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


def _handedness_notes(handed, flipped):
    """Warning lines for left/right labels put right (calibration.check_handedness). All pairs
    swapped on a scan wound inward is named a mirrored scan (mirroring a mesh turns its winding)."""
    if handed["all"]:
        if flipped:
            return ["the scan looks mirrored (left and right reversed; its triangles are wound inward): "
                    "its left/right FDP labels were swapped to match; mirror the scan back on X for a "
                    "head with the person's own sides"]
        return ["left and right FDP labels look swapped (clicked from the viewer's side?): "
                "every left/right pair was swapped back (" + ", ".join("/".join(p) for p in handed["swapped"]) + ")"]
    return [f"FDP {a} and FDP {b} look swapped (left/right): swapped back" for a, b in handed["swapped"]]


def fit_outcome(distances, face, folds_left, marker_rms_mm, flagged, options, notes=()):
    """How a fit ended, honestly: folds left, distance RMS over the face the scan shows (mm; `face` a
    vertex mask, FACE_REGIONS), marker RMS (mm), one warning line per problem, and ok (False: no
    folds may be left, the RMS must stay under options.bad_fit_rms_mm)."""
    seen = np.isfinite(distances) & face
    rms = float(np.sqrt(np.mean(distances[seen] ** 2)) * MM) if seen.any() else float("nan")
    warnings = list(notes) + [f"FDP {k}: {why}" for k, why in flagged.items()]
    ok = True
    if folds_left:
        ok = False
        warnings.append(f"{folds_left} folded triangles left in the adapted skin")
    if not np.isfinite(rms) or rms > options.bad_fit_rms_mm:
        ok = False
        warnings.append(f"the adapted face lies {rms:.2f} mm RMS from the scan over {int(seen.sum())} seen "
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


# FDPs a closed mouth puts within a few millimetres of each other: the upper/lower inner lip points,
# and the inner/outer lip corners (people may click both at the commissure, one spot)
CLOSE_LIP_PAIRS = (("2.2", "2.3"), ("2.6", "2.8"), ("2.7", "2.9"), ("2.4", "8.3"), ("2.5", "8.4"))


def _closed_mouth(names, P, Q, closed=0.003):
    """On a closed mouth (clicks of a CLOSE_LIP_PAIRS pair within 3 mm), give the pair the template's
    own small offset about the clicks' midpoint, so click noise cannot cross the lips or turn a lip
    corner inside out."""
    Q = Q.copy()
    pos = {k: i for i, k in enumerate(names)}
    for a, b in CLOSE_LIP_PAIRS:
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
