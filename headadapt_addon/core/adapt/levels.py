"""Levels 1..K (paper sec 3.3 and 4): each a compactly supported RBF offset (csrbf_level) fitted to
its pairs with a smoothness term, as a few rounds of non-rigid ICP (fit_level)."""

from __future__ import annotations

import math

import numpy as np
from scipy import sparse
from scipy.sparse.linalg import splu
from scipy.spatial import cKDTree

from .. import threads
from ..tol import TINY
from . import rbf
from .fit import Fit, Pairs, level_sigma
from .pairs import surface_pairs

try:        # the kernel of scipy's csr A @ v, called without its dispatch (a level's solve makes ~4,000)
    from scipy.sparse._sparsetools import csr_matvec as _csr_matvec
except ImportError:                 # a scipy that moved it: A @ v computes the same
    _csr_matvec = None


def csrbf_level(fit: Fit, pairs: Pairs, sigma: float, stiffness: float) -> rbf.CSRBF:
    """One level's offset function (sec 3.3) fitted to the pairs with a smoothness term: the CSRBF
    o(x) = sum_j c_j phi_sigma(|x - p_j|) on centres spread over the template skin sigma/support_factor
    apart, with c minimising sum_i w_i |f(p_i) + o(p_i) - q_i|^2 + lambda sum_j |c_j|^2, where
    lambda = stiffness x the mean data weight a centre carries (so it means the same at every level).
    Returns the CSRBF, with its offsets at the skin's vertices as `on_skin` (Fit.current uses them)."""
    centres, tree, bend, R, on_skin = fit.level_basis(sigma)
    # a pair at a skin vertex takes its row of the basis on the skin (made once per template); the
    # others (feature mesh, curvature: points between vertices) are evaluated, after them
    pairs = pairs.take(np.argsort(pairs.vertex < 0, kind="stable"))
    between = np.flatnonzero(pairs.vertex < 0)
    res = cKDTree(pairs.p[between]).sparse_distance_matrix(tree, sigma, output_type="ndarray")
    phi = sparse.vstack([on_skin[pairs.vertex[:len(pairs) - len(between)]],
                         sparse.csr_matrix((rbf.wendland(res["v"], sigma), (res["i"], res["j"])),
                                           shape=(len(between), len(centres)))], format="csr")
    resid = pairs.q - fit.at(pairs)
    A = (phi.T @ sparse.diags(pairs.w) @ phi).tocsc()
    # the bending of the whole displacement (levels below included), so a level may undo what the
    # clicks' interpolation bent where the scan does not ask for it
    lam = stiffness * A.diagonal().sum() / max(R.diagonal().sum(), TINY)
    A = A + lam * R + 1e-6 * lam * sparse.identity(len(centres), format="csc")
    rhs = phi.T @ (pairs.w[:, None] * resid) - lam * (bend.T @ (fit.laplacian @ (fit.current() - fit.V)))
    o = fit.options
    coef, fit.factor[sigma] = solve_spd(A.tocsr(), np.asarray(rhs), fit.warm.get(sigma), fit.factor.get(sigma),
                                        o.solve_rtol, o.jacobi_steps, o.lu_steps)
    fit.warm[sigma] = coef
    zero = np.zeros((len(centres), 3))
    out = rbf.CSRBF(centres, sigma, zero, np.zeros((len(centres), 3, 3)), coef, A)
    out.on_skin = on_skin @ coef            # its offsets at the skin's vertices (Fit.current)
    return out


def fit_level(fit: Fit, clicks: Pairs, k: int, fixed: Pairs | None = None,
              rounds: int | None = None) -> tuple[Pairs, float]:
    """Level k (sec 4) as non-rigid ICP: a few rounds of surface pairs plus the level's fixed pairs
    (feature mesh, curvature) and the clicks as soft pairs, each round refitting the level's CSRBF
    (csrbf_level); then refits without the pairs around any triangle it folded. Returns (the last
    round's pairs, sigma)."""
    o = fit.options
    sigma = level_sigma(o, k)
    stiffness = max(o.stiffness * o.stiffness_decay ** (k - 1), o.min_stiffness)
    fixed = Pairs.empty() if fixed is None else fixed
    far = cKDTree(fit.V[fit.seam]).query(fixed.p, distance_upper_bound=o.seam_band)[0] == np.inf
    fixed = fixed.take(far)
    # clicks are evidence, not law: their weight falls per level so the surface decides the detail
    soft = Pairs(clicks.p, clicks.q, clicks.w * o.click_weight * o.click_decay ** (k - 1))
    below = list(fit.functions)
    fit.quiet[:] = False

    def refit(pairs):
        # each round's CSRBF replaces the last one's: it is fitted to what the levels below leave (the
        # pairs come from where the last round put the skin); fitted on top of the last round instead,
        # rounds alternated between the whole offset and a small correction of it
        fit.functions = below
        return csrbf_level(fit, pairs, sigma, stiffness)

    rays = k >= o.rays_from_level
    # closest points slide the skin along the scan a little each round: such a level goes on until the skin
    # settles (icp_settle); the rays' levels do not slide it, and the finest of them (the dearest) take fewer
    least = o.fine_icp_iterations if k >= o.fine_from_level else o.icp_iterations
    most = rounds if rounds is not None else least if rays else max(o.icp_max_rounds, least)
    settled = (fit.pair_w > 0) if rounds is None and not rays else None
    for i in range(most):
        before = None if settled is None else fit.current()[settled]
        pairs = surface_pairs(fit, fit.reach(k), rays) + fixed + soft
        fit.functions = below + [refit(pairs)]
        if i + 1 >= least and before is not None and \
                math.sqrt(np.mean(np.sum((fit.current()[settled] - before) ** 2, axis=1))) < o.icp_settle:
            break
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
        fit.quiet |= fit.grown(around)
        pairs = surface_pairs(fit, fit.reach(k), k >= o.rays_from_level) + fixed + soft
        fit.functions = below + [refit(pairs)]
    return pairs, sigma


def conjugate_gradients(A, b, x0, rtol, maxiter, psolve):
    """Preconditioned conjugate gradients on a symmetric positive definite csr A for one right-hand side
    b: (x, 0) once |b - A x| < rtol |b|, (x, maxiter) if not within maxiter steps. The steps of scipy's
    cg (1.12 on), operation for operation, so the same answers to the bit; without its operator
    wrappers and checks, whose Python took about a third of a level's solve time on 3,000 centres
    (and held the GIL the three columns' threads share). psolve(r): the preconditioner applied to r."""
    n = A.shape[0]
    indptr, indices, data = A.indptr, A.indices, A.data

    def matvec(v):
        if _csr_matvec is None:
            return A @ v
        out = np.zeros(n)
        _csr_matvec(n, n, indptr, indices, data, v, out)
        return out

    x = np.zeros(n) if x0 is None else np.array(x0, dtype=np.float64)
    bnrm2 = np.linalg.norm(b)
    if bnrm2 == 0:
        return b.copy(), 0
    atol = rtol * bnrm2
    r = b - matvec(x) if x.any() else b.copy()
    rho_prev, p = None, None
    for iteration in range(maxiter):
        if math.sqrt(np.dot(r, r)) < atol:          # np.linalg.norm(r), as numpy computes it
            return x, 0
        z = psolve(r)
        rho = np.dot(r, z)
        if iteration > 0:
            p *= rho / rho_prev
            p += z
        else:
            p = z.copy()
        q = matvec(p)
        alpha = rho / np.dot(p, q)
        x += alpha * p
        r -= alpha * q
        rho_prev = rho
    return x, maxiter


def solve_spd(A, b, x0=None, factor=None, rtol=1e-5, jacobi_steps=250, lu_steps=30):
    """Solve a level's symmetric positive definite A x = b (k right-hand sides); returns (x, the
    sparse LU used or None). Conjugate gradients preconditioned by A's diagonal, started from x0
    (the last ICP round's solution: the rounds of a level change A little), answer well-posed
    systems fast: the finest level of a 31k-vertex scan-like head in about 130 steps (60 ms), where
    a sparse LU took 150 ms. Where few pairs reach the level's centres (a face-only scan: Fran, the
    CT) the smoothness term dominates and CG crawls (800 steps); after jacobi_steps the system is
    factorised (sparse LU), and the level's later rounds use that factorisation, passed back in as
    `factor`, to precondition CG, refactorising only if that fails within lu_steps."""
    A = A.tocsr()
    b = np.asarray(b, dtype=np.float64)

    def krylov(psolve, steps):
        def column(c):
            return conjugate_gradients(A, np.ascontiguousarray(b[:, c]), None if x0 is None else x0[:, c],
                                       rtol, steps, psolve)

        # the columns side by side: the sparse products release the GIL, so on 2 cores the three solves
        # of a level take about 0.8 of their time one after another (the answers are the same)
        solved = list(threads.pool().map(column, range(b.shape[1])))
        if any(info > 0 for _, info in solved):
            return None
        return np.stack([x for x, _ in solved], axis=1)

    if factor is None:
        inverse = 1.0 / A.diagonal()
        x = krylov(lambda r: inverse * r, jacobi_steps)
    else:
        x = krylov(lambda r: factor.solve(np.ascontiguousarray(r)), lu_steps)
    if x is not None:
        return x, factor
    factor = factor_spd(A.tocsc())
    return factor.solve(np.ascontiguousarray(b)), factor


def factor_spd(A):
    """SuperLU's factorisation of a symmetric positive definite csc matrix, pivoting on its diagonal in a
    symmetric minimum-degree ordering: about a third of the time of SuperLU's partial pivoting, which
    breaks the ordering's symmetry (Fran's finest level, 3,348 centres: 0.04 against 0.15 s; the
    solutions agree to 1e-12 of their size)."""
    return splu(A, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
