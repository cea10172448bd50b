"""Fewer clicks: propose the missing FDPs on a scan from the ones already placed."""

from __future__ import annotations

import numpy as np

from ..mesh import spatial
from ..template import Template
from . import calibration, rbf
from .options import SCANNER_VISIBLE_PARTS, AdaptOptions
from .pipeline import adapt


def suggest_fdps(tpl: Template, scan_verts: np.ndarray, scan_tris: np.ndarray,
                 placed: dict[str, np.ndarray], snap=None, options: AdaptOptions | None = None,
                 calibrated: tuple | None = None, flagged: dict | None = None,
                 progress=None) -> dict[str, np.ndarray]:
    """{FDP id: (3,)} proposals in the scan's frame for every visible template FDP not in `placed`.

    Where the adaptation from the placed FDPs puts them: the skin's FDPs on the adapted skin, the
    eyes' (their pupils, which the skin does not carry) through the calibration and the level-0 RBF
    of the placed FDPs; then snapped to the nearest point of the scan surface: snap(points (k,3)) ->
    (k,3) if given (the panel's: the scan as Calibrate prepared it, whose tree is made already), else
    the scan's closest points. options, calibrated: as adapt.adapt's (the panel hands both over, so
    the scan is not prepared again). flagged: a dict the adaptation's wrong-click verdicts go into
    ({FDP id: reason}; AdaptOptions.drop_flagged leaves them out of the fit proposed from). progress:
    the adaptation's progress(fraction, message), if given.

    Accepted whole, the RBF's proposals alone (this function until stop 59) made the fit worse than
    the 8 clicks they came from on 11 of tuning heads 0-11, by 2.0 mm of correspondence on average and
    up to 5.2; these leave it within -0.64 and +0.29 mm of it (mean -0.08), for an adaptation's time
    (about 1 s) instead of 0.05 s (docs/MEASUREMENTS.md, stop 59).
    """
    tpl_pts = {k: p for k, p in tpl.fdp_points().items() if tpl.meta["fdps"][k]["part"] in SCANNER_VISIBLE_PARTS}
    given = calibration.validate_landmarks(placed, what="scan")
    given = {k: v for k, v in given.items() if k in tpl_pts}
    todo = [k for k in tpl_pts if k not in given]
    if not todo:
        return {}
    on_skin = [k for k in todo if tpl.meta["fdps"][k]["part"] == "skin"]
    others = [k for k in todo if k not in on_skin]
    guess = np.zeros((len(todo), 3))
    if on_skin:
        res = adapt(tpl, scan_verts, scan_tris, given, options, progress=progress, calibrated=calibrated)
        skin = res.verts_scan
        if flagged is not None:
            flagged.update(res.flagged)
        refs = [tpl.meta["fdps"][k] for k in on_skin]
        corners = skin[tpl.skin.tris[[r["face"] for r in refs]]]                 # (k,3,3)
        guess[:len(on_skin)] = np.einsum("kj,kjd->kd", np.array([r["bary"] for r in refs]), corners)
    if others:
        sim, _ = calibration.calibrate(given, tpl_pts)
        names = list(given)
        P = np.array([tpl_pts[k] for k in names])
        Q = sim.apply(np.array([given[k] for k in names]))
        f0 = rbf.fit_rbf(P, Q - P, rho=0.0)
        X = np.array([tpl_pts[k] for k in others])
        guess[len(on_skin):] = sim.inverse().apply(X + f0(X))
    if snap is None:
        snap = lambda x: spatial.MeshQuery(np.asarray(scan_verts, float), np.asarray(scan_tris)).closest_points(x)[0]
    return dict(zip(on_skin + others, snap(guess)))


def snap_to_prepared(scan_side, sim):
    """A snap for suggest_fdps: points in the scan's frame to their closest points on the scan as
    calibrate() prepared it (a ScanSide in the template frame: a dense scan's clusters), back in the
    scan's frame."""
    inverse = sim.inverse()
    return lambda points: inverse.apply(scan_side.query.closest_points(sim.apply(points))[0])
