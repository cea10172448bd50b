"""Level 0 (paper sec 3.2): the global map that takes the template onto the clicks (and, in
HeadAdapt, onto the scan's whole surface by an affine ICP), and the feature mesh over the clicks."""

from __future__ import annotations

import numpy as np
from scipy.spatial import Delaunay

from ..mesh import geometry
from . import rbf
from .fit import Fit, Pairs
from .pairs import surface_pairs


def global_rbf(P: np.ndarray, Q: np.ndarray, rho: float = 0.0) -> rbf.GlobalRBF:
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


def global_affine(fit: Fit, clicks: Pairs, reach: float, iterations: int, ridge: float = 1e-3,
                  along_normal: bool | None = None) -> AffineMap:
    """Level 0, first half: the affine map that best takes the template skin onto the scan (robust
    weights) and the clicks onto their places, by a few ICP rounds from the calibrated pose. The
    clicks sit on the front of the face and cannot say how deep or wide the head is; the scan can.
    The map's linear part is held near the identity by a small ridge. The skin's regions weigh as
    options.affine_weights say (by default the scalp and forehead not at all), and its pairs lie
    along the template's normals (options.affine_along_normal): fitted to the whole skin by closest
    points, the map went on tilting the face with every round, away from the best affine map even
    when started there (./ha bench adapt, README "What is different"). along_normal: the pairing
    (None: options.affine_along_normal)."""
    centre = fit.V.mean(axis=0)
    along = fit.options.affine_along_normal if along_normal is None else along_normal
    fit.functions = [AffineMap(np.eye(3), np.zeros(3))]
    for _ in range(iterations):
        pairs = surface_pairs(fit, reach, along, mask=fit.affine_weight > 0, exact=False)
        pairs = Pairs(pairs.p, pairs.q, pairs.w * fit.affine_weight[pairs.vertex], pairs.vertex) + clicks
        X = np.c_[pairs.p - centre, np.ones(len(pairs))]
        XtW = X.T * pairs.w
        reg = ridge * pairs.w.sum() * np.diag([np.mean((fit.V - centre) ** 2)] * 3 + [0.0])
        D = np.linalg.solve(XtW @ X + reg, XtW @ (pairs.q - pairs.p))     # displacement, affine in x
        matrix = np.eye(3) + D[:3].T
        fit.functions = [AffineMap(matrix, D[3] - D[:3].T @ centre)]
    return fit.functions[0]


def affine_scan_distance(fit: Fit, affine: AffineMap, clip: float) -> float:
    """How far the skin the affine map fits (its weighted, seen vertices) lies from the scan: the RMS
    of their distances to it (the nearest vertex's tangent plane, as its closest-point pairs), each
    clipped at `clip` (m) so that skin over a hole or past the scan's edge counts as a miss and no more."""
    x = fit.V[(fit.vert_w > 0) & (fit.affine_weight > 0)]
    _, _, dist, _ = fit.scan.nearest_on_plane(x + affine(x), exact_if_coarse=False)
    return float(np.sqrt(np.mean(np.minimum(dist, clip) ** 2)))


def level_zero(fit: Fit, clicks: Pairs) -> None:
    """Level 0 (sec 3.2): the whole-skin affine map fitted to the scan and the clicks (global_affine),
    both ways (pairs along the normals, and at the closest points) when options.affine_both_pairings,
    keeping the map whose skin lies nearer the scan (affine_scan_distance); or, when the affine map is
    switched off, the paper's global RBF through the clicks."""
    o = fit.options
    # the wrong-click check (clicks.check_clicks) fits level 0 to the same clicks first: when it kept
    # them all and the mouth is open, that map is this one (the same rounds from the same start)
    key = (clicks.p.tobytes(), clicks.q.tobytes(), clicks.w.tobytes())
    if fit.level0_memo is not None and fit.level0_memo[0] == key:
        fit.functions = [fit.level0_memo[1]]
        return
    if o.affine_iterations < 0:
        fit.functions = [AffineMap(np.eye(3), np.zeros(3))]
    elif o.affine_iterations:
        weighted = Pairs(clicks.p, clicks.q, clicks.w * o.click_weight)
        args = (weighted, o.reach_factor * fit.threshold, o.affine_iterations, o.affine_ridge)
        best = global_affine(fit, *args)
        if o.affine_both_pairings:
            other = global_affine(fit, *args, along_normal=not o.affine_along_normal)
            best = min(best, other, key=lambda m: affine_scan_distance(fit, m, o.affine_distance_clip))
        fit.functions = [best]
    else:
        fit.functions = [global_rbf(clicks.p, clicks.q, o.rho)]
    fit.level0_memo = (key, fit.functions[0])


def feature_mesh(points: np.ndarray, centre: np.ndarray) -> np.ndarray:
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
    area = geometry.face_areas(p, tris)
    keep &= area > 1e-3 * edges.max(axis=1) ** 2
    return tris[keep]
