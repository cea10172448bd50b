"""What the levels share: feature-point pairs (Pairs) and the fit in progress (Fit: template, scan,
options, the level functions so far); the calibrated scan with its queries (ScanSide) is scan.py's."""

from __future__ import annotations

import dataclasses
from concurrent.futures import Future

import numpy as np
from scipy import sparse
from scipy.spatial import cKDTree

from .. import threads
from ..mesh import geometry
from . import metrics, rbf


def face_weights(tpl):
    w = tpl.region_weights[tpl.region]
    return w[tpl.skin.tris].min(axis=1)


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


def _by_region(tpl, base, weights):
    """A copy of per-skin-vertex values `base` with each (region, weight) of `weights` set over its region."""
    out = np.array(base, dtype=np.float64)
    for region, weight in weights:
        out[tpl.region_mask(region)] = weight
    return out


class Fit:
    """What the level loop shares: template, scan, options, the fitted level functions so far."""

    def __init__(self, tpl, scan, options, threshold):
        self.tpl, self.scan, self.options, self.threshold = tpl, scan, options, threshold
        self.V = tpl.skin.verts
        self.tris = tpl.skin.tris
        self.vert_w = tpl.region_weights[tpl.region]
        # each skin vertex's weight in its surface pairs: its region's weight in E_d, unless
        # AdaptOptions.pair_weights says otherwise
        self.pair_w = _by_region(tpl, self.vert_w, options.pair_weights)
        self.face_w = face_weights(tpl)
        # what depends on the template alone is made once per template in a process (template_side)
        side = template_side(tpl, *_skin_entry(tpl, options))
        self.seam, self.near_seam, self.folds, self.ring, self.laplacian, self.adjacency = side
        self.functions = []
        self.level0_memo = None     # (the clicks' bytes, level 0's map) of the last level-0 fit
        self.quiet = np.zeros(len(self.V), bool)     # vertices a level leaves to its smoothness term
        # each skin vertex's weight in the global affine map (AdaptOptions.affine_weights)
        self.affine_weight = _by_region(tpl, np.ones(len(self.V)), options.affine_weights)
        self._at_skin = {}
        self._between = None       # (functions and points, their deformed places) of the last at()
        self.warm = {}              # last coefficients per support: the next ICP round starts there
        self.factor = {}            # a sparse LU per support, once a level's system needed one

    def distance_error(self, verts, exact=False):
        """metrics.DistanceError of skin positions (n,3) against the scan (sec 5.1): nearest points
        by the scan's tangent planes while fitting (exact=False: only the vertices E_d weighs; the
        others unmatched), exact closest points to report."""
        normals = geometry.vertex_normals(verts, self.tris)
        if exact:
            return metrics.distance_error(verts, normals, self.scan.query, self.scan.normal_at, self.vert_w,
                                          self.threshold, self.scan.on_border)
        # only the vertices E_d weighs are looked up (the rest: unmatched, distance 0, weight 0)
        use = np.flatnonzero(self.vert_w > 0)
        d = np.zeros(len(verts))
        matched = np.zeros(len(verts), bool)
        _, n, d[use], border = self.scan.nearest_on_plane(verts[use])
        matched[use] = (d[use] <= self.threshold) & (np.einsum("ij,ij->i", normals[use], n) > 0) & ~border
        w = np.where(matched, self.vert_w, 0.0)
        return metrics.DistanceError(float(np.sum(w * d ** 2) / len(verts)), d, w, matched)

    def level_basis(self, sigma):
        """(centres, their kd-tree, the umbrella Laplacian of their Wendland functions on the skin,
        its Gram matrix, the functions at the skin's vertices) of a level with support sigma, made once
        per template and support."""
        return template_side(self.tpl, *_basis_entry(self.tpl, self.options, sigma))

    def reach(self, k):
        """How far a closest-point pair may reach at level k (halving per level), m."""
        return max(self.options.reach_factor * self.threshold / 2 ** (k - 1), self.options.min_reach)

    def grown(self, mask, rings=1):
        """The skin vertices (n,) bools within `rings` edge rings of the vertex mask (self.ring holds each
        vertex with its neighbours)."""
        for _ in range(rings):
            mask = (self.ring @ mask) > 0
        return mask

    def displacement(self, x, functions=None):
        fs = self.functions if functions is None else functions
        return sum((f(x) for f in fs), np.zeros_like(np.asarray(x, dtype=np.float64)))

    def current(self):
        """The deformed skin now (n,3); each level function is evaluated on the skin once."""
        for f in self.functions:
            if id(f) not in self._at_skin:
                # a level's CSRBF brings its offsets at the skin (its basis there times its coefficients)
                at_skin = getattr(f, "on_skin", None)
                self._at_skin[id(f)] = (f, f(self.V) if at_skin is None else at_skin)
        return self.V + sum((self._at_skin[id(f)][1] for f in self.functions), np.zeros_like(self.V))

    def at(self, pairs):
        """The deformed template at the pairs' template points (the skin's vertices looked up). The points
        between vertices (a level's feature-mesh, curvature and click pairs, the same in each of its
        rounds, under the same levels below) are evaluated once per set of level functions."""
        cur = self.current()
        out = np.empty_like(pairs.p)
        on = pairs.vertex >= 0
        out[on] = cur[pairs.vertex[on]]
        between = pairs.p[~on]
        key = (tuple(self.functions), between.tobytes())      # the functions themselves: no id reused
        if self._between is None or self._between[0] != key:
            self._between = (key, between + self.displacement(between))
        out[~on] = self._between[1]
        return out


def template_side(tpl, key, make):
    """Data of the fit that depends on the template (and the options in `key`) alone, made by make()
    once per template in a process and kept in tpl.derived: a batch of heads, the benchmark or the
    panel's next Adapt skip it (0.37 s of a 2.2 s adaptation of a 31k-vertex scan). Begun by
    prefetch, it is waited for (made here if that failed)."""
    if key not in tpl.derived:
        tpl.derived[key] = make()
    value = tpl.derived[key]
    if isinstance(value, Future):
        value = tpl.derived[key] = value.result() if value.exception() is None else make()
    return value


def level_sigma(options, k):
    """The CSRBF support of level k (sec 3.3): support_factor x the level's centre spacing, which
    halves per level down to min_sample_spacing (or options.support if fixed), m."""
    o = options
    return o.support or o.support_factor * max(o.sample_spacing / 2 ** (k - 1), o.min_sample_spacing)


def prefetch(tpl, options):
    """Begin, on a worker thread, what template_side keeps for a fit with these options (Fit's skin
    side, every level's basis) and has not made yet: a process's first adaptation (a batch command)
    makes it, 0.19 s, while this thread calibrates and clusters the scan. Returns the worker's future
    (None if all was made): the caller waits for it before it leaves (pipeline.adapt)."""
    jobs = dict([_skin_entry(tpl, options)] + [_basis_entry(tpl, options, level_sigma(options, k))
                                                for k in range(1, options.max_levels + 1)])
    jobs = {key: make for key, make in jobs.items() if key not in tpl.derived}
    if not jobs:
        return None
    futures = {key: Future() for key in jobs}
    tpl.derived.update(futures)

    def run():                  # in order: the bases read the skin side's Laplacian
        for key, make in jobs.items():
            futures[key].set_running_or_notify_cancel()
            try:
                futures[key].set_result(make())
            except BaseException as exc:      # template_side then makes it on the caller's thread
                futures[key].set_exception(exc)

    return threads.pool().submit(run)


def _skin_entry(tpl, options):
    """(template_side's key, its make) of Fit's skin side."""
    return ("fit", options.seam_band), lambda: _skin_side(tpl, options.seam_band)


def _basis_entry(tpl, options, sigma):
    """(template_side's key, its make) of the level basis of support sigma (on the skin side's Laplacian)."""
    density = options.centre_density
    return ("basis", sigma, density), lambda: _level_basis(
        tpl.skin.verts, template_side(tpl, *_skin_entry(tpl, options))[4], sigma, density)


def _skin_side(tpl, seam_band):
    """(lip seam, skin near it, the fold check, each vertex with its ring, umbrella Laplacian, the
    neighbours' mean: geometry.neighbour_mean)."""
    V, tris = tpl.skin.verts, tpl.skin.tris
    seam = lip_seam(tpl)
    near_seam = cKDTree(V[seam]).query(V, distance_upper_bound=seam_band)[0] < np.inf
    adjacency = geometry.neighbour_mean(tris, len(V))
    ring = (adjacency + sparse.identity(len(V))).tocsr()              # a vertex and its neighbours
    # umbrella Laplacian of the skin (x_i minus its neighbours' mean) for the smoothness term
    laplacian = (sparse.identity(len(V), format="csr") - adjacency).tocsr()
    return seam, near_seam, geometry.FoldCheck(V, tris), ring, laplacian, adjacency


def _level_basis(V, laplacian, sigma, density):
    """Fit.level_basis, made."""
    centres = V[spread(V, sigma / density)]
    tree = cKDTree(centres)
    res = cKDTree(V).sparse_distance_matrix(tree, sigma, output_type="ndarray")
    phi = sparse.csr_matrix((rbf.wendland(res["v"], sigma), (res["i"], res["j"])), shape=(len(V), len(centres)))
    bend = (laplacian @ phi).tocsr()
    return centres, tree, bend, (bend.T @ bend).tocsc(), phi


def lip_seam(tpl):
    """Skin vertex indices along the inner-lip seam (upper and lower lip vertices next to the mouth interior)."""
    q, region = tpl.skin.quads, tpl.region
    inside = region == tpl.region_names.index("mouth_interior")
    e = np.concatenate([q[:, [0, 1]], q[:, [1, 2]], q[:, [2, 3]], q[:, [3, 0]]])
    rim = np.zeros(len(region), bool)
    rim[e[inside[e[:, 0]] ^ inside[e[:, 1]]].ravel()] = True
    lips = np.isin(region, [tpl.region_names.index("upper_lip"), tpl.region_names.index("lower_lip")])
    return np.flatnonzero(rim & lips)


def spread(points, radius):
    """Indices of a greedy subset of points (in the given priority order) at least radius apart.

    Exact greedy: a kd-tree lists every pair of points closer than radius; a point with no earlier
    neighbour is always taken, and the Python loop runs only over points that have one.
    """
    if len(points) == 0:
        return np.zeros(0, int)
    points = np.asarray(points)
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
