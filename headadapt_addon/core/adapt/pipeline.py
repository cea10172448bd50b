"""The adaptation of the template skin onto a scan, step by step as the paper's sections 3 to 5:
calibration (3.1), level 0 (3.2), then per level k the feature-point pairs (4.1: feature mesh,
curvature) and the CSRBF offset (3.3) fitted to them, stopping where E reaches its minimum (5.3).

Frames: the scan arrives in its own frame and unit; calibration maps it into the template frame
(metres, Z up, face toward -Y), where all fitting happens; results go back through the inverse.
Every level function is a function of the *undeformed* template position x (paper eq 18):
f^k(x) = f^{k-1}(x) + o^k(x), so the same map carries skull, muscles and eyes later.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from ..mesh import geometry, repair, simplify
from ..template import Template
from ..tol import MM, TINY
from . import calibration, metrics
from .clicks import calibrated_on, check_clicks, closed_mouth, handedness_notes
from .fit import Fit, Pairs, prefetch
from .level0 import feature_mesh, level_zero
from .levels import fit_level
from .options import FACE_REGIONS, SCANNER_VISIBLE_PARTS, AdaptOptions, AdaptResult, Level
from .outcome import fit_outcome, scan_beyond
from .pairs import current_query, curvature_pairs, face_box, feature_mesh_pairs
from .reach import check_in_reach, check_markers, check_on_surface
from .scan import ScanSide, start_spatial
from .snap import snap_to_scan
from .unfolding import Unfolding


def adapt(tpl: Template, scan_verts: np.ndarray, scan_tris: np.ndarray, scan_fdps: dict[str, np.ndarray],
          options: AdaptOptions | None = None, markers: dict[str, np.ndarray] | None = None,
          progress: Callable[[float, str], None] | None = None, calibrated: tuple | None = None) -> AdaptResult:
    """Adapt the template skin onto a scan; scan and FDPs in the scan's frame/unit; returns AdaptResult.

    scan_fdps: {FDP id: (3,)} clicked on the scan. markers: optional {marker name or held-out FDP id:
    (3,)} on the scan (for E_m). progress: optional callable(fraction 0..1, message). calibrated:
    calibrate()'s answer for this very scan, these clicks and options, if the caller kept one (the
    panel's Calibrate): its prepared scan (a dense scan's clusters, normals, spatial tree) is used
    as it is, and the fit is the same to the bit.
    """
    options = options or AdaptOptions()
    # the template's side of the fit, made on a worker while the scan is calibrated; waited for before
    # returning or raising, so that no worker outlives the call (Blender runs operators next)
    pending = prefetch(tpl, options)
    try:
        return _adapt(tpl, scan_verts, scan_tris, scan_fdps, options, markers, progress, calibrated)
    finally:
        _settle(pending)


def _adapt(tpl, scan_verts, scan_tris, scan_fdps, options, markers, progress, calibrated=None):
    """adapt's steps (the worker begun by adapt aside)."""
    t_start = time.perf_counter()
    say = progress or (lambda f, msg: None)

    # 1. calibration (sec 3.1), after left/right labels that look swapped are put right
    say(0.02, "calibrating")
    if calibrated is None:
        fit, tpl_fdps, q_fdp, sim, cal_info = calibrate(tpl, scan_verts, scan_tris, scan_fdps, options)
        spent = 0.0
    else:                       # the scan prepared before: a new fit on it (its seconds then are not this run's)
        kept, tpl_fdps, q_fdp, sim, cal_info = calibrated
        fit = Fit(tpl, kept.scan, options, kept.threshold)
        cal_info = {**cal_info, "scan_prepared_before": True}
        spent = kept.scan.seconds["build"] + kept.scan.seconds["curvature"]
    box = face_box(fit.scan, q_fdp)
    if options.use_curvature and options.max_levels > 0:
        fit.scan.curvature(box)             # level 1's, made while the scan's spatial tree is built
    check_on_surface(fit.scan, q_fdp, options)
    check_markers(fit.scan, tpl, markers, sim, scan_verts, options)
    t_cal = time.perf_counter() - t_start

    # 2. level 0 (sec 3.2), after wrong-click detection
    say(0.08, "level 0: the global map onto the scan and the clicks")
    t0 = time.perf_counter()
    names = list(q_fdp)
    P = np.array([tpl_fdps[k] for k in names])
    Q = np.array([q_fdp[k] for k in names])
    weights = np.ones(len(names))
    flagged = check_clicks(fit, names, P, Q, weights)
    dropped = [k for k in names if k in flagged] if options.drop_flagged else []
    keep = np.array([k not in dropped for k in names])
    names = [k for k in names if k not in dropped]
    P, Q, weights = P[keep], closed_mouth(names, P[keep], Q[keep]), weights[keep]
    clicks = Pairs(P, Q, weights)
    level_zero(fit, clicks)
    judge = Judge(fit, tpl, sim, markers, names)
    unfolding = Unfolding(fit)
    cur, unfolded = unfolding(fit.current())
    cur, _, errs = judge(cur)
    method = "affine" if options.affine_iterations > 0 else "rbf" if options.affine_iterations == 0 else "none"
    levels = [Level(0, method, len(P), len(P), *errs, time.perf_counter() - t0 - unfolding.last)]
    best, best_verts, best_funcs, best_unfolded = 0, cur, list(fit.functions), unfolded

    # the feature mesh over the FDPs in use (its template side is where they sit on the deformed template)
    tris = feature_mesh(P, fit.V.mean(axis=0))
    fmesh = {"q": Q.copy(), "t": tris, "dead": np.zeros(len(tris), bool)}

    # 3. levels 1..K (sec 4): new pairs, then a CSRBF offset with support halving per level
    for k in range(1, options.max_levels + 1):
        say(0.1 + 0.85 * k / (options.max_levels + 1), f"level {k}: searching feature points")
        t0 = time.perf_counter()
        fixed = Pairs.empty()
        reach = fit.reach(k)
        # the deformed template's tree, made once for both searches (the skin does not move between them)
        query = current_query(fit) if options.use_feature_mesh or options.use_curvature else None
        if options.use_feature_mesh:
            fixed = fixed + feature_mesh_pairs(fit, fmesh, reach, query)
        if options.use_curvature:
            fixed = fixed + curvature_pairs(fit, box, options.curvature_points * 2 ** (k - 1),
                                            min(reach, options.curvature_reach), fit.threshold / 2 ** (k + 1), query)
        say(0.1 + 0.85 * (k + 0.5) / (options.max_levels + 1), f"level {k}: fitting")
        pairs, sigma = fit_level(fit, clicks, k, fixed)          # csrbf_level in rounds of ICP
        # a level is judged as it would be delivered: its folds repaired (step 4 below)
        cur, unfolded = unfolding(fit.current())
        cur, _, errs = judge(cur)
        levels.append(Level(k, "csrbf", len(pairs), len(fixed), *errs,
                            time.perf_counter() - t0 - unfolding.last, sigma * MM))
        if errs[3] < levels[best].E:
            best, best_verts, best_funcs, best_unfolded = k, cur, list(fit.functions), unfolded
        elif options.stop_at_minimum:
            break

    # 4. the folds were repaired at every level (Unfolding), so the level kept is the best as delivered;
    # 5. then the skin is laid onto the scan where the scan shows it (snap.py; HeadAdapt, not the paper)
    t0 = time.perf_counter()       # (a fit far from the scan is delivered, and named, as the levels left it)
    hold = options.snap_reach > 0 and levels[best].E_d_rms_mm < options.bad_fit_rms_mm
    verts, snapped = snap_to_scan(fit, best_verts) if hold else (best_verts, None)
    t_snap, unfolded, t0 = time.perf_counter() - t0, best_unfolded, time.perf_counter()
    # the distances reported: exact closest points on the scan, by the paper's compatibility rule
    de = fit.distance_error(verts, exact=True)
    best_dist = np.where(de.matched, de.dist, np.nan)
    left, face = unfolded["folded_left"], tpl.region_mask(*FACE_REGIONS)
    outcome = fit_outcome(best_dist, face, left, judge.marker_rms_mm(best_funcs), flagged, options,
                          cal_info["handedness"]["notes"], scan_beyond(fit, verts))
    say(1.0, f"done: best level {best}")
    # the scan's preparation (ScanSide's normals and border, its spatial tree's wait, the curvature: all
    # before level 0) apart
    prep = fit.scan.seconds["build"] + fit.scan.seconds["curvature"] - spent
    stages = {"calibrate": t_cal - prep, "prepare": prep, **{f"level_{lv.level}": lv.seconds for lv in levels},
              "snap": t_snap, "unfold": unfolding.seconds + time.perf_counter() - t0}
    return AdaptResult(verts=verts, verts_scan=sim.inverse().apply(verts), similarity=sim, levels=levels,
                       best_level=best, functions=best_funcs, flagged=flagged, dropped=dropped,
                       calibration_info=cal_info, seconds=time.perf_counter() - t_start, distances=best_dist,
                       scan=fit.scan, unfolded=unfolded, snapped=snapped, outcome=outcome,
                       anatomy_support=options.anatomy_support, backend=options.backend, stages=stages)


def calibrate(tpl: Template, scan_verts: np.ndarray, scan_tris: np.ndarray, scan_fdps: dict[str, np.ndarray],
              options: AdaptOptions) -> tuple[Fit, dict, dict, calibration.Similarity, dict]:
    """Step 1 (sec 3.1): the scan and its clicks in the template frame. Returns (the Fit to come, the
    template's FDPs the scanner can see, the clicks in the template frame, the similarity scan ->
    template, the calibration's report)."""
    scan_verts = np.asarray(scan_verts, dtype=np.float64)
    scan_tris = np.asarray(scan_tris)
    geometry.check_mesh(scan_verts, scan_tris, "scan")
    tpl_fdps = {k: p for k, p in tpl.fdp_points().items() if tpl.meta["fdps"][k]["part"] in SCANNER_VISIBLE_PARTS}
    given = calibration.validate_landmarks(scan_fdps, what="scan")
    unused = [k for k in given if k not in tpl_fdps]
    given = {k: v for k, v in given.items() if k in tpl_fdps}
    given, handed = calibration.check_handedness(given, tpl_fdps)
    # the face's firm clicks place the head: a right click on the top of the skull or the hairline leaned
    # the least-squares similarity away from the face (clicks.calibrated_on); the levels take those clicks
    sim, info = calibration.calibrate(given, tpl_fdps, method=options.calibration, lean_on=calibrated_on(given))
    scan_verts, scan_tris, info = repair.put_right(scan_verts, scan_tris, info)   # as exporters write them
    sv = sim.apply(scan_verts)
    q_fdp = {k: sim.apply(v) for k, v in given.items()}
    check_in_reach(sv, q_fdp, options, hint=lambda: calibration.unit_hint(np.array(geometry.bounds(scan_verts)), given))
    # a dense scan is clustered once to the detail the fit can use (mesh/simplify.py)
    border, clustered = None, simplify.cluster_if_finer(sv, scan_tris, options.scan_cell)
    if clustered is not None:
        before = len(sv)
        sv, scan_tris, border = clustered                                    # border: the scan's own
        info = {**info, "scan_clustered": {"cell_mm": options.scan_cell * MM, "vertices": before, "kept": len(sv)}}
    # windings mixed in a surface made one way (a dense scan's clusters keep its scanner's: 0.1 s spared)
    scan_tris, mixed = repair.consistent_winding(scan_tris, len(sv)) if clustered is None else (scan_tris, 0)
    # the scan's spatial tree, begun on a worker thread before the winding check below: kept unless it
    # turns a piece (a turned triangle's corners come in another order, and so its rounding)
    early = start_spatial(sv, scan_tris, options) if options.backend != "bvh" else None
    # normals out of the head, whatever winding the file has (pairs are matched by normals)
    # (the triangles' cross products and their sums per vertex serve the check and the scan's normals:
    # computed once, the products again only for the triangles turned, the sums then anew)
    try:
        fc = geometry.face_cross(sv, scan_tris)
        sums = geometry.vertex_sums(scan_tris, fc, len(sv))
        turned, flipped = geometry.orient_outward(sv, scan_tris, tpl.parts["cranium"].verts.mean(axis=0), sums)
    except BaseException:
        _settle(early)
        raise
    if flipped:
        redo = np.flatnonzero((turned != scan_tris).any(axis=1))
        fc[redo], sums, early = geometry.face_cross(sv, turned[redo]), None, _settle(early)
    scan_tris = turned
    notes = handedness_notes(handed, flipped)
    info = {**info, **({"scan_triangles_turned": mixed} if mixed else {}), "scan_pieces_turned": flipped, "handedness": {**handed, "notes": notes}, "unused_fdps": unused}
    scan = ScanSide(sv, scan_tris, options, fc, sums, early, border)
    threshold = float(np.ptp(tpl.skin.verts[:, 0])) / 10.0     # the paper's width / 10
    return Fit(tpl, scan, options, threshold), tpl_fdps, q_fdp, sim, info


def _settle(future) -> None:
    """Wait for a worker's result that will not be used (None: nothing to wait for), so that no worker
    outlives the call: Blender crashed (2 of about 230 runs of the real scans through the add-on) in
    the calibrate operator while the dropped tree of a scan whose pieces were turned was being built."""
    if future is not None:
        future.exception()


class Judge:
    """The errors of the fit so far (sec 5): E_d over the skin, E_m over held-out markers (the
    template's named markers, or FDPs the user clicked but held out), E = alpha E_d + beta E_m."""

    def __init__(self, fit, tpl, sim, markers, names):
        self.fit = fit
        known = {**tpl.fdp_points(), **tpl.marker_points()}
        use = [m for m in (markers or {}) if m in known and m not in names]
        self.marker_tpl = np.array([known[m] for m in use]) if use else None
        self.marker_scan = sim.apply(np.array([markers[m] for m in use])) if use else None

    def __call__(self, cur=None):
        """(skin (n,3), distance per vertex (nan: unmatched), (E_d, E_d RMS mm, E_m, E, coverage)) of
        the fit now, or of the skin `cur` given (the fit's, unfolded)."""
        fit, o = self.fit, self.fit.options
        cur = fit.current() if cur is None else cur
        de = fit.distance_error(cur)
        e_d = float(np.sum(de.w * (de.dist * MM) ** 2) / len(cur))
        rms = float(np.sqrt(np.sum(de.w * (de.dist * MM) ** 2) / max(np.sum(de.w), TINY)))
        cover = float(np.sum(de.w > 0) / max(np.sum(fit.vert_w > 0), 1))
        e_m = None if self.marker_tpl is None else metrics.marker_error(self.predicted() * MM, self.marker_scan * MM)
        e = metrics.combined_error(e_d, e_m, o.alpha, o.beta)
        return cur, np.where(de.matched, de.dist, np.nan), (e_d, rms, e_m, e, cover)

    def predicted(self, functions=None):
        """Where the level functions put the markers (template frame)."""
        return self.marker_tpl + self.fit.displacement(self.marker_tpl, functions)

    def marker_rms_mm(self, functions):
        """The markers' RMS error under the given level functions, mm (None without markers)."""
        if self.marker_tpl is None:
            return None
        return float(np.sqrt(np.mean(np.sum((self.predicted(functions) - self.marker_scan) ** 2, axis=1)))) * MM
