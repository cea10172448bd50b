"""Radial basis functions of the adaptation (paper sec 3.2 and 3.3), vector valued.

GlobalRBF: phi(r) = r with an affine part, smoothing rho (eq 5-10).
CSRBF: Wendland phi_sigma(r) = (1 - r/sigma)^4_+ (4 r/sigma + 1) with a local first-order fit g_j
at each centre (eq 11-16) and a sparse system for the coefficients c_j (eq 13), solved by
a sparse direct factorization (measured faster than preconditioned CG on these matrices).
Coordinates and values in any consistent unit (the template frame, metres, in HeadAdapt).
"""

import numpy as np
import scipy.linalg
from scipy import sparse
from scipy.sparse.linalg import splu
from scipy.spatial import cKDTree

from ..exceptions import LandmarkError
from ..tol import TINY

_CHUNK = 4096


def _sum_rows(index, values, n):
    """Row sums: out[r] = sum of values[p] with index[p] == r, for values of any trailing shape."""
    if len(values) == 0:
        return np.zeros((n,) + values.shape[1:])
    flat = values.reshape(len(values), -1)
    out = np.stack([np.bincount(index, weights=flat[:, c], minlength=n) for c in range(flat.shape[1])], axis=1)
    return out.reshape((n,) + values.shape[1:])


class GlobalRBF:
    """f(x) = sum_j c_j |x - p_j| + R x + t, fitted to centres (m,3) and values (m,k)."""

    def __init__(self, centres, coef, affine, origin):
        self.centres, self.coef, self.affine, self.origin = centres, coef, affine, origin

    def __call__(self, x):
        """Values (n,k) at points x (n,3)."""
        x = np.atleast_2d(np.asarray(x, dtype=np.float64)) - self.origin
        out = np.empty((len(x), self.coef.shape[1]))
        for s in range(0, len(x), _CHUNK):
            xs = x[s:s + _CHUNK]
            r = np.sqrt(np.maximum(np.sum(xs * xs, 1)[:, None] - 2 * xs @ self.centres.T
                                   + np.sum(self.centres ** 2, 1)[None], 0.0))
            out[s:s + _CHUNK] = r @ self.coef + np.c_[xs, np.ones(len(xs))] @ self.affine
        return out


def fit_rbf(centres, values, rho=0.0):
    """Fit the paper's global RBF (eq 9: the phi block minus rho I) to centres (m,3) and values (m,k)."""
    origin = np.mean(centres, axis=0)
    p = np.asarray(centres, dtype=np.float64) - origin      # centred: better conditioned affine block
    v = np.asarray(values, dtype=np.float64).reshape(len(p), -1)
    m = len(p)
    if m < 4:
        raise LandmarkError(f"an RBF with an affine part needs at least 4 point pairs, got {m}")
    a = np.zeros((m + 4, m + 4))
    a[:m, :m] = np.linalg.norm(p[:, None] - p[None], axis=2) - rho * np.eye(m)
    a[:m, m:] = np.c_[p, np.ones(m)]
    a[m:, :m] = a[:m, m:].T
    b = np.zeros((m + 4, v.shape[1]))
    b[:m] = v
    try:
        x = scipy.linalg.solve(a, b, assume_a="sym")
    except (np.linalg.LinAlgError, scipy.linalg.LinAlgError) as exc:
        raise LandmarkError("the RBF system is singular: two point pairs coincide or all points lie "
                            "in one plane") from exc
    if not np.isfinite(x).all() or np.linalg.norm(a @ x - b) > 1e-6 * max(np.linalg.norm(b), TINY):
        raise LandmarkError("the RBF system is singular: two point pairs coincide or all points lie in one plane")
    return GlobalRBF(p, x[:m], x[m:], origin)


def wendland(r, sigma):
    """Wendland's C2 function phi(r/sigma) = (1 - r/sigma)^4_+ (4 r/sigma + 1)."""
    q = np.clip(np.asarray(r) / sigma, 0.0, 1.0)
    return (1 - q) ** 4 * (4 * q + 1)


def _pairs(tree_a, tree_b, sigma):
    """(i, j, r) of every pair of points of a and b closer than sigma (zero distances kept)."""
    res = tree_a.sparse_distance_matrix(tree_b, sigma, output_type="ndarray")
    return res["i"], res["j"], res["v"]


def _solve_spd(A, b):
    """Solve the sparse symmetric positive definite system A x = b (k right-hand sides).

    Sparse LU with a fill-reducing ordering: measured faster than Jacobi-preconditioned CG here,
    because Wendland matrices with many neighbours per centre are poorly conditioned.
    """
    return splu(A.tocsc(), permc_spec="MMD_AT_PLUS_A").solve(np.ascontiguousarray(b))


class CSRBF:
    """o(x) = sum_j [g_j(x) + c_j] phi_sigma(|x - p_j|); exactly zero farther than sigma from every centre."""

    def __init__(self, centres, sigma, g_const, g_lin, coef, matrix):
        self.centres, self.sigma = centres, sigma
        self.g_const, self.g_lin, self.coef = g_const, g_lin, coef
        self.matrix = matrix
        self.tree = cKDTree(centres)
        # the levels' offsets have no local fits (zeros): their evaluation skips that term
        self.has_local = bool(np.any(g_const) or np.any(g_lin))

    def __call__(self, x):
        """Offsets (n,k) at points x (n,3)."""
        x = np.atleast_2d(np.asarray(x, dtype=np.float64))
        i, j, r = _pairs(cKDTree(x), self.tree, self.sigma)
        phi = wendland(r, self.sigma)
        value = self.coef[j]
        if self.has_local:
            value = value + self.g_const[j] + np.einsum("pk,pkd->pd", x[i] - self.centres[j], self.g_lin[j])
        return _sum_rows(i, value * phi[:, None], len(x))


def fit_csrbf(centres, values, sigma):
    """Fit the CSRBF offset function of sec 3.3 to centres (m,3) and values (m,k) with support sigma."""
    p = np.asarray(centres, dtype=np.float64)
    v = np.asarray(values, dtype=np.float64).reshape(len(p), -1)
    m, k = v.shape
    tree = cKDTree(p)
    i, j, r = _pairs(tree, tree, sigma)
    phi = wendland(r, sigma)
    A = sparse.csr_matrix((phi, (i, j)), shape=(m, m))
    # local first-order fits g_j(x) = a_j + (x - p_j) B_j to the neighbours' values, weighted by phi (eq 15)
    d = p[i] - p[j]                                  # neighbour i relative to centre j
    X = np.c_[np.ones(len(i)), d]                    # (pairs, 4)
    M = _sum_rows(j, phi[:, None, None] * X[:, :, None] * X[:, None, :], m)
    rhs = _sum_rows(j, phi[:, None, None] * X[:, :, None] * v[i][:, None, :], m)
    count = np.bincount(j, minlength=m)
    ridge = (1e-6 * np.trace(M[:, 1:, 1:], axis1=1, axis2=2) + 1e-9 * sigma ** 2)[:, None, None] * np.eye(4)
    ridge[:, 0, 0] = TINY
    coefs = np.linalg.solve(M + ridge, rhs)           # (m, 4, k)
    few = count < 8                                  # too few neighbours for a plane: constant fit
    coefs[few, 1:] = 0.0
    coefs[few, 0] = rhs[few, 0] / np.maximum(M[few, 0, 0], 1e-300)[:, None]
    norm = np.asarray(A.sum(axis=1)).ravel()          # partition of unity: g_j / sum_i phi_ij
    g_const, g_lin = coefs[:, 0] / norm[:, None], coefs[:, 1:] / norm[:, None, None]
    G = _sum_rows(i, (g_const[j] + np.einsum("pk,pkd->pd", p[i] - p[j], g_lin[j])) * phi[:, None], m)
    b = v - G
    coef = _solve_spd(A, b)
    return CSRBF(p, sigma, g_const, g_lin, coef, A)
