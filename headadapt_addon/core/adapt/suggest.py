"""Fewer clicks: propose the missing FDPs on a scan from the ones already placed."""

from __future__ import annotations

import numpy as np

from ..mesh import spatial
from ..template import Template
from . import calibration, rbf
from .options import SCANNER_VISIBLE_PARTS


def suggest_fdps(tpl: Template, scan_verts: np.ndarray, scan_tris: np.ndarray,
                 placed: dict[str, np.ndarray], snap=None) -> dict[str, np.ndarray]:
    """{FDP id: (3,)} proposals in the scan's frame for every visible template FDP not in `placed`.

    The template FDPs go through the calibration and the level-0 RBF of the placed FDPs, then snap
    to the nearest point of the scan surface: snap(points (k,3)) -> (k,3) if given (the panel's: the
    scan as Calibrate prepared it, whose tree is made already), else the scan's closest points.
    """
    tpl_pts = {k: p for k, p in tpl.fdp_points().items() if tpl.meta["fdps"][k]["part"] in SCANNER_VISIBLE_PARTS}
    given = calibration.validate_landmarks(placed, what="scan")
    given = {k: v for k, v in given.items() if k in tpl_pts}
    sim, _ = calibration.calibrate(given, tpl_pts)
    names = list(given)
    P = np.array([tpl_pts[k] for k in names])
    Q = sim.apply(np.array([given[k] for k in names]))
    f0 = rbf.fit_rbf(P, Q - P, rho=0.0)
    todo = [k for k in tpl_pts if k not in given]
    if not todo:
        return {}
    X = np.array([tpl_pts[k] for k in todo])
    guess = sim.inverse().apply(X + f0(X))
    if snap is None:
        snap = lambda x: spatial.MeshQuery(np.asarray(scan_verts, float), np.asarray(scan_tris)).closest_points(x)[0]
    snapped = snap(guess)
    return dict(zip(todo, snapped))


def snap_to_prepared(scan_side, sim):
    """A snap for suggest_fdps: points in the scan's frame to their closest points on the scan as
    calibrate() prepared it (a ScanSide in the template frame: a dense scan's clusters), back in the
    scan's frame."""
    inverse = sim.inverse()
    return lambda points: inverse.apply(scan_side.query.closest_points(sim.apply(points))[0])
