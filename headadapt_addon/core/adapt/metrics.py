"""Error measures of an adaptation (paper sec 5): distance error E_d, marker error E_m, combined E."""

import dataclasses

import numpy as np


@dataclasses.dataclass
class DistanceError:
    """E_d (unit^2, eq 22), per-vertex distance to the scan (unit), weights used, matched mask."""
    E_d: float
    dist: np.ndarray
    w: np.ndarray
    matched: np.ndarray


def distance_error(src_verts, src_normals, scan, scan_normal, weights, threshold, border=None):
    """E_d = sum_i w_i dist^2(x_i, scan) / n (eq 22) with the paper's compatibility rule.

    A vertex matches the scan when its nearest scan point is within `threshold`, the normals are
    at most 90 degrees apart and (if given) that nearest point is not on a hole's border. Both are
    judged on the nearest point itself, so which face answers a tie (a vertex or edge several faces
    share; each spatial backend breaks ties its own way) does not matter: scan_normal is a callable
    (points (k,3), faces (k,)) -> normals (k,3) continuous across faces (ScanSide.normal_at: the
    vertex normals interpolated), border a callable (k,3) -> (k,) bool (ScanSide.on_border).
    Unmatched vertices get w = 0 (holes). `weights` are the per-vertex region weights (ears 0.2).
    Units: those of the inputs (E_d in unit^2).
    """
    near, face, dist = scan.closest_points(src_verts)
    matched = (dist <= threshold) & (np.einsum("ij,ij->i", src_normals, scan_normal(near, face)) > 0)
    if border is not None:
        matched &= ~border(near)
    w = np.where(matched, np.asarray(weights, dtype=float), 0.0)
    return DistanceError(float(np.sum(w * dist ** 2) / len(src_verts)), dist, w, matched)


def marker_error(pred, truth):
    """E_m = sum_i |u_i - v_i|^2 over held-out markers (eq 23), in the inputs' unit squared."""
    d = np.asarray(pred, float) - np.asarray(truth, float)
    return float(np.sum(d * d))


def combined_error(e_d, e_m, a=1.0, b=1.0):
    """E = a E_d + b E_m (eq 24); E_m may be None (no markers), then E = a E_d."""
    return a * e_d + (b * e_m if e_m is not None else 0.0)
