"""The adaptation's steps one by one (core/adapt/), on a scan made from the template itself under a
known smooth deformation: the template's visible skin, stretched, sheared and bumped. Every step must
move the template toward that known answer, and the clicks' checks must tell right from wrong."""
import numpy as np
import pytest

from headadapt_addon.core import adapt, mpeg4
from headadapt_addon.core.adapt import calibration
from headadapt_addon.core.adapt.clicks import check_clicks
from headadapt_addon.core.adapt.fit import Fit, Pairs
from headadapt_addon.core.adapt.level0 import (
    AffineMap,
    affine_scan_distance,
    feature_mesh,
    global_affine,
    global_rbf,
    level_zero,
)
from headadapt_addon.core.adapt.levels import csrbf_level, fit_level, solve_spd
from headadapt_addon.core.adapt.options import FACE_REGIONS
from headadapt_addon.core.adapt.pairs import curvature_pairs, feature_mesh_pairs, surface_pairs
from headadapt_addon.core.adapt.scan import ScanSide
from headadapt_addon.core.adapt.snap import snap_to_scan
from headadapt_addon.core.adapt.unfolding import Unfolding, blend_back, seen_rms_mm
from headadapt_addon.core.mesh import geometry

MM = 1000.0


def _deform(x):
    """A known smooth deformation of template-frame points: 8% deeper, 4% wider, a sheared jaw and a
    10 mm bump on the left cheek."""
    x = np.asarray(x, float)
    out = x * np.array([1.04, 1.08, 1.0])
    out[:, 1] += 0.05 * (x[:, 2] - 0.70)
    bump = np.exp(-np.sum((x - np.array([0.045, -0.09, 0.69])) ** 2, axis=1) / (2 * 0.015 ** 2))
    out[:, 0] += 0.010 * bump
    return out


@pytest.fixture(scope="module")
def case(tpl):
    """(scan verts, scan tris, true skin (n,3), clicks of CLICKS_11 on the scan, exact)."""
    hidden = tpl.hidden
    tris = tpl.skin.tris[~hidden[tpl.skin.tris].any(axis=1)]
    truth = _deform(tpl.skin.verts)
    fdps = tpl.fdp_points()
    clicks = {k: _deform(fdps[k][None])[0] for k in mpeg4.CLICKS_11}
    return truth, tris, truth, clicks


def _fit(tpl, case, **kw):
    scan_v, scan_t, _, clicks = case
    options = adapt.AdaptOptions(**kw)
    scan = ScanSide(scan_v, scan_t, options)
    fit = Fit(tpl, scan, options, float(np.ptp(tpl.skin.verts[:, 0])) / 10)
    names = list(clicks)
    P = np.array([tpl.fdp_points()[k] for k in names])
    Q = np.array([clicks[k] for k in names])
    return fit, names, P, Q


def _face(tpl):
    return tpl.region_mask(*FACE_REGIONS)


def _corr_mm(tpl, verts, truth):
    return float(np.sqrt(np.mean(np.sum((verts - truth)[_face(tpl)] ** 2, axis=1)))) * MM


def test_global_rbf_interpolates_the_clicks_and_keeps_an_affine_map(tpl):
    P = np.array(list(tpl.fdp_points().values()))[:20]
    A = np.array([[1.05, 0.02, 0.0], [0.0, 0.97, 0.03], [0.01, 0.0, 1.02]])
    Q = P @ A.T + np.array([0.01, -0.02, 0.005])
    f = global_rbf(P, Q)
    assert np.abs(P + f(P) - Q).max() < 1e-9                      # interpolates
    x = tpl.skin.verts[::50]
    assert np.abs(x + f(x) - (x @ A.T + np.array([0.01, -0.02, 0.005]))).max() < 1e-9   # affine exact


def test_global_affine_finds_the_depth_the_clicks_cannot_see(tpl, case):
    fit, names, P, Q = _fit(tpl, case)
    truth = case[2]
    before = _corr_mm(tpl, tpl.skin.verts, truth)
    f = global_affine(fit, Pairs(P, Q, np.full(len(P), 20.0)), fit.threshold, 8)
    after = _corr_mm(tpl, tpl.skin.verts + f(tpl.skin.verts), truth)
    assert after < 0.5 * before, (before, after)
    assert abs(f.matrix[1, 1] - 1.08) < 0.03                       # the depth stretch, found on the surface


def test_a_skull_sloping_back_does_not_tilt_the_face_s_affine_map(tpl):
    # a head 4% wider and 8% deeper whose forehead and skull, from 2 cm above the eyes, slope back
    # (a shape no affine map follows): fitted to the whole skin by closest points, the affine map
    # squashed the face 4% and sheared it; fitted without the scalp and forehead, along the template's
    # normals (AdaptOptions.affine_weights, affine_along_normal), it keeps the face's map
    fdps = tpl.fdp_points()

    def deform(x):
        out = x * np.array([1.04, 1.08, 1.0])
        above = np.maximum(x[:, 2] - fdps["3.7"][2] - 0.02, 0.0)
        out[:, 1] += 0.6 * above ** 2 / 0.05
        return out

    truth = deform(tpl.skin.verts)
    tris = tpl.skin.tris[~tpl.hidden[tpl.skin.tris].any(axis=1)]
    clicks = {k: deform(fdps[k][None])[0] for k in mpeg4.CLICKS_8}
    face = tpl.region_mask(*(r for r in FACE_REGIONS if r != "forehead"))
    errors = {}
    for name, kw in (("face", {}), ("whole skin", {"affine_weights": (), "affine_along_normal": False})):
        fit, names, P, Q = _fit(tpl, (truth, tris, truth, clicks), **kw)
        f = global_affine(fit, Pairs(P, Q, np.full(len(P), 20.0)), fit.threshold, 8)
        errors[name] = float(np.sqrt(np.mean(np.sum((tpl.skin.verts + f(tpl.skin.verts) - truth)[face] ** 2,
                                                    axis=1)))) * MM
        if name == "face":
            assert abs(f.matrix[2, 2] - 1.0) < 0.01 and abs(f.matrix[1, 2]) < 0.01, f.matrix
    assert errors["face"] < 1.0 and errors["whole skin"] > 1.5, errors


def test_affine_scan_distance_is_how_far_the_mapped_skin_lies_from_the_scan(tpl, case):
    fit, names, P, Q = _fit(tpl, case)
    fitted = global_affine(fit, Pairs(P, Q, np.full(len(P), 20.0)), fit.threshold, 8)
    before = affine_scan_distance(fit, AffineMap(np.eye(3), np.zeros(3)), 0.005)
    after = affine_scan_distance(fit, fitted, 0.005)
    assert after < 0.5 * before and after < 0.002, (before, after)        # the fitted map lies on the scan
    far = AffineMap(np.eye(3), np.array([0.0, 0.0, 0.5]))                  # half a metre up: all a miss
    assert affine_scan_distance(fit, far, 0.005) == pytest.approx(0.005)


@pytest.mark.parametrize("seed", [20, 35])
def test_level_zero_keeps_the_pairing_whose_skin_lies_nearer_the_scan(tpl, testheads, seed):
    # two tuning heads whose cheeks the map paired along the normals put 1 to 1.5 mm off along the skin
    # (against nricp_amberg's 5.48 and 7.92 mm, 8 clicks): fitted both ways, the map whose skin lies
    # nearer the scan is the one paired at the closest points, and the whole fit gains from it
    head = testheads.make_head(seed, style="scan")
    seen = testheads.face_mask(tpl) & head.true_on_scan
    corr, level0 = {}, {}
    for both in (True, False):
        res = adapt.adapt(tpl, head.scan_verts, head.scan_tris, head.clicks_8,
                          adapt.AdaptOptions(affine_both_pairings=both))
        corr[both] = float(np.sqrt(np.mean(np.sum((res.verts_scan - head.true_template)[seen] ** 2, axis=1)))
                           / head.similarity[0] * MM)
        level0[both] = res.functions[0]
    assert corr[True] < corr[False] - 0.5, corr
    assert not np.allclose(level0[True].matrix, level0[False].matrix)


def test_surface_pairs_lie_on_the_scan_and_respect_reach(tpl, case):
    fit, names, P, Q = _fit(tpl, case)
    level_zero(fit, Pairs(P, Q, np.ones(len(P))))
    for along in (False, True):
        pairs = surface_pairs(fit, 0.004, along_normal=along)
        assert len(pairs) > 1000
        d = fit.scan.query.closest_points(pairs.q)[2]
        assert np.percentile(d, 95) < (2e-4 if not along else 1e-6)   # targets on the scan
        assert np.linalg.norm(fit.at(pairs) - pairs.q, axis=1).max() <= 0.004 + 1e-12
        assert np.all(pairs.vertex >= 0) and np.allclose(pairs.p, tpl.skin.verts[pairs.vertex])


def test_surface_pairs_weigh_the_ears_fully_while_e_d_keeps_the_paper_s_weights(tpl, case):
    # AdaptOptions.pair_weights: the ears hold the side of the face in place, so their pairs weigh as
    # much as the face's; the distance error E_d keeps the paper's region weights (ears 0.2, sec 5.1)
    fits = {name: _fit(tpl, case, **kw)[0] for name, kw in (("default", {}), ("paper", {"pair_weights": ()}))}
    pairs = {name: surface_pairs(fit, 0.02, along_normal=True) for name, fit in fits.items()}
    assert np.array_equal(pairs["default"].vertex, pairs["paper"].vertex)
    ear = tpl.region_mask("ear_l", "ear_r")[pairs["default"].vertex]
    assert ear.sum() > 100
    ratio = pairs["default"].w / pairs["paper"].w
    assert np.allclose(ratio[ear], 1.0 / 0.2) and np.allclose(ratio[~ear], 1.0)
    assert np.array_equal(fits["default"].vert_w, fits["paper"].vert_w)
    assert np.isclose(fits["default"].vert_w[tpl.region_mask("ear_l")].max(), 0.2)


def test_feature_mesh_pairs_split_triangles_and_pair_both_surfaces(tpl, case):
    # the case's head is an affine map of the template's whole skin (and a cheek bump): level 0 fits
    # all of it alike, scalp, forehead and neck included (AdaptOptions.affine_weights)
    fit, names, P, Q = _fit(tpl, case, affine_weights=())
    level_zero(fit, Pairs(P, Q, np.ones(len(P))))
    mesh = {"q": Q.copy(), "t": feature_mesh(P, tpl.skin.verts.mean(axis=0)), "dead": None}
    mesh["dead"] = np.zeros(len(mesh["t"]), bool)
    n_tri = len(mesh["t"])
    pairs = feature_mesh_pairs(fit, mesh, fit.threshold)
    assert len(pairs) >= 0.5 * n_tri > 0
    assert len(mesh["t"]) == n_tri + 2 * len(pairs) and len(mesh["q"]) == len(P) + len(pairs)
    assert fit.scan.query.closest_points(pairs.q)[2].max() < 1e-6            # on the scan
    assert np.linalg.norm(pairs.p - tpl.skin.verts[np.argmin(np.linalg.norm(
        tpl.skin.verts[None] - pairs.p[:, None], axis=2), axis=1)], axis=1).max() < 0.02   # on the template


def test_curvature_pairs_come_from_curved_places(tpl, case):
    fit, names, P, Q = _fit(tpl, case)
    level_zero(fit, Pairs(P, Q, np.ones(len(P))))
    box = np.ones(len(fit.scan.verts), bool)
    pairs = curvature_pairs(fit, box, 100, 0.004, 0.004)
    assert len(pairs) > 30
    H, valid = fit.scan.curvature(box)
    at = np.argmin(np.linalg.norm(fit.scan.verts[None] - pairs.q[:, None], axis=2), axis=1)
    assert np.median(np.abs(H[at])) > 3 * np.median(np.abs(H[valid]))


def test_csrbf_level_fits_and_its_stiffness_smooths(tpl, case):
    fit, names, P, Q = _fit(tpl, case)
    fit.functions = [AffineMap(np.eye(3), np.zeros(3))]
    truth = case[2]
    use = np.flatnonzero(_face(tpl))[::3]
    pairs = Pairs(tpl.skin.verts[use], truth[use], np.ones(len(use)), use)
    errs, bends = [], []
    for stiffness in (1e-4, 10.0):
        f = csrbf_level(fit, pairs, 0.024, stiffness)
        fit.warm.clear()
        off = f(tpl.skin.verts)
        errs.append(np.sqrt(np.mean(np.sum((tpl.skin.verts[use] + off[use] - truth[use]) ** 2, axis=1))) * MM)
        bends.append(np.linalg.norm(fit.laplacian @ off))
    assert errs[0] < 0.5 and errs[0] < errs[1], errs               # soft: fits; stiff: fits less ...
    assert bends[1] < bends[0], bends                              # ... and bends less


def test_fit_level_converges_onto_the_scan(tpl, case):
    fit, names, P, Q = _fit(tpl, case)
    clicks = Pairs(P, Q, np.ones(len(P)))
    level_zero(fit, clicks)
    before = np.median(fit.scan.query.closest_points(fit.current()[_face(tpl)])[2])
    for k in (1, 2, 3):
        fit_level(fit, clicks, k)
    after = np.median(fit.scan.query.closest_points(fit.current()[_face(tpl)])[2])
    assert after < 0.2 * before and after * MM < 0.1, (before * MM, after * MM)


def test_a_level_s_icp_rounds_converge(tpl, case):
    """Each round's CSRBF replaces the last one's and is fitted to what the levels below leave: a second
    and third round refine the first (fitted on top of the last round they alternated between the
    whole offset and a small correction, and the second round fell back toward the level's start)."""
    fit, names, P, Q = _fit(tpl, case)
    clicks = Pairs(P, Q, np.ones(len(P)))
    level_zero(fit, clicks)
    start = [list(fit.functions), fit.current()]
    gap, moved = [], []          # median distance to the scan, RMS move from level 0, mm
    for rounds in (1, 2, 3):
        fit.functions, fit.warm = list(start[0]), {}
        fit_level(fit, clicks, 1, rounds=rounds)
        now = fit.current()
        gap.append(float(np.median(fit.scan.query.closest_points(now[_face(tpl)])[2])) * MM)
        moved.append(float(np.sqrt(np.mean(np.sum((now - start[1]) ** 2, axis=1)))) * MM)
    # each round keeps the level's whole offset and still fits the scan (was: 0.95, 0.13, 0.91 mm moved)
    assert min(moved[1], moved[2]) > 0.9 * moved[0], moved
    assert max(gap) < 0.15, gap


@pytest.mark.slow
def test_unfolding_relaxes_a_level_s_folds_as_it_will_be_delivered(tpl, case):
    fit, *_ = _fit(tpl, case)
    truth = case[2]
    unfold = Unfolding(fit)
    same, report = unfold(truth)            # nothing folded: the skin as it is
    assert same is truth and report == {"folded_triangles": 0, "vertices_relaxed": 0, "folded_left": 0,
                                        "repair": None}
    # a nose-tip vertex pushed 8 mm into the head turns its triangles over
    folded = truth.copy()
    tip = int(np.argmax(tpl.skin.verts[:, 1] * -1.0 * _face(tpl)))
    folded[tip] += 0.008 * geometry.vertex_normals(truth, tpl.skin.tris)[tip] * -1.0
    n = len(geometry.folded(fit.V, folded, fit.tris))
    assert n > 0
    first = Unfolding(fit)                  # level 0: no level below, so the folds are relaxed
    out, report = first(folded)
    assert report["folded_triangles"] == n and report["folded_left"] == 0 and report["vertices_relaxed"] > 0
    assert report["repair"] == "relaxed"
    assert len(geometry.folded(fit.V, out, fit.tris)) == 0 and first.seconds >= first.last > 0
    # after a level that folded nothing (the truth), the next level's folds go back to it round the tip,
    # which lies on the scan: nearer it than the relaxation, and over a few vertices only
    back, report = unfold(folded)
    assert report["repair"] == "level below" and report["folded_left"] == 0
    assert 0 < report["vertices_relaxed"] < 40
    assert len(geometry.folded(fit.V, back, fit.tris)) == 0
    assert seen_rms_mm(fit, back) < seen_rms_mm(fit, out)
    assert np.array_equal(back[tip], truth[tip])


def test_blend_back_takes_the_level_below_on_the_folds_and_the_level_beyond_its_rings(tpl, case):
    """blend_back: the skin below on the folded triangles' corners, the level's own skin from `width`
    rings out, the narrowest width that folds nothing; None when no width does."""
    fit, *_ = _fit(tpl, case)
    truth = case[2]
    folded = truth.copy()
    tip = int(np.argmax(tpl.skin.verts[:, 1] * -1.0 * _face(tpl)))
    folded[tip] -= 0.008 * geometry.vertex_normals(truth, tpl.skin.tris)[tip]
    corners = np.unique(fit.tris[fit.folds(folded)])
    y, changed = blend_back(truth, folded, fit, (1, 2, 4))
    assert np.array_equal(y[corners], truth[corners]) and len(fit.folds(y)) == 0
    far = np.linalg.norm(tpl.skin.verts - tpl.skin.verts[tip], axis=1) > 0.03
    assert np.array_equal(y[far], folded[far]) and changed >= len(corners)
    # a level below that is itself folded there repairs nothing
    assert blend_back(folded, folded, fit, (1, 2, 4)) == (None, 0)
    # folds on kept vertices (the lids: Unfolding relaxes them after) are left as they are
    lids = tpl.region_mask("eyelid_l")
    lid = int(np.flatnonzero(lids & _face(tpl))[0])
    both = folded.copy()
    both[lid] -= 0.008 * geometry.vertex_normals(truth, tpl.skin.tris)[lid]
    lid_folds = [f for f in fit.folds(both) if lid in fit.tris[f]]
    assert lid_folds
    y, _ = blend_back(truth, both, fit, (1, 2, 4), keep=lids)
    assert np.array_equal(y[corners], truth[corners]) and np.array_equal(y[lid], both[lid])
    assert set(fit.folds(y)) <= set(lid_folds)


def test_a_fold_the_relaxation_leaves_goes_back_to_the_level_below_lids_and_all(tpl, case, monkeypatch):
    """The lids' folds are relaxed, not taken back (stop 58), but where the relaxation leaves a fold
    the level below goes back round them, lids and all: a scan-like head with every FDP clicked folded
    8 lid triangles at level 3, the relaxation left one, moved 906 vertices and took the level from 0.47
    to 1.18 mm RMS from the scan (and the head's delivered skin 1.31 mm); the level below round them:
    0.47, no fold."""
    from headadapt_addon.core.adapt import unfolding

    fit, *_ = _fit(tpl, case)
    truth = case[2]
    lid = int(np.flatnonzero(tpl.region_mask("eyelid_l") & _face(tpl))[0])
    folded = truth.copy()
    folded[lid] -= 0.008 * geometry.vertex_normals(truth, tpl.skin.tris)[lid]
    assert len(fit.folds(folded))
    relax = unfolding.geometry.unfold

    def stuck(V, cur, tris, **kw):          # a relaxation that leaves one fold, as on that head
        out, moved, _ = relax(V, cur, tris, **kw)
        return out, moved, 1

    monkeypatch.setattr(unfolding.geometry, "unfold", stuck)
    unfold = Unfolding(fit)
    unfold(truth)                           # the level below: folded nowhere
    back, report = unfold(folded)
    assert report["repair"] == "level below" and report["folded_left"] == 0, report
    assert len(fit.folds(back)) == 0 and np.array_equal(back[lid], truth[lid])



def test_the_snap_lays_the_skin_onto_the_scan_and_follows_neighbours_over_a_hole(tpl, case):
    """snap.py, the last step: a skin 1 mm in front of the scan (the truth moved forward: folded nowhere,
    as a fit the levels leave; 1 mm along the normals already turns 42 of the template's smallest lid
    and lip triangles over) is laid onto the scan, moved no farther than snap_reach and folded nowhere,
    the lids' margins kept where they were; where the scan has a hole (the left cheek's triangles cut out) the skin has no pair and follows its
    neighbours."""
    scan_v, scan_t, truth, _ = case
    cheek = tpl.region_mask("cheek_l")
    holed = scan_t[~cheek[scan_t].any(axis=1)]
    options = adapt.AdaptOptions()
    fit = Fit(tpl, ScanSide(scan_v, holed, options), options, float(np.ptp(tpl.skin.verts[:, 0])) / 10)
    off = truth + np.array([0.0, -0.001, 0.0])          # the face looks toward -y
    lids = tpl.region_mask(*options.snap_keep)          # the lids' margins stay (the blink is made on them)
    for _ in range(options.snap_keep_rings):
        lids |= (fit.ring @ lids) > 0
    face = _face(tpl) & ~cheek & ~lids
    before = fit.scan.query.closest_points(off[face])[2]
    assert np.median(before) * MM > 0.6
    out, info = snap_to_scan(fit, off)
    after = fit.scan.query.closest_points(out[face])[2]
    rms = [float(np.sqrt(np.mean(d ** 2))) * MM for d in (before, after)]
    assert np.median(after) * MM < 0.05 and rms[1] < 0.4 * rms[0], rms
    assert _corr_mm(tpl, out, truth) < 0.8 * _corr_mm(tpl, off, truth)     # its part along the normals
    assert np.linalg.norm(out - off, axis=1).max() <= options.snap_reach + 1e-9
    assert len(fit.folds(out)) == 0 and info["snapped"] and info["paired"] > 1000
    held = np.linalg.norm(out - off, axis=1)[lids] * MM      # held by weights: a little pulled along
    assert lids.sum() > 200 and np.percentile(held, 90) < 0.1, np.percentile(held, [50, 90, 100])
    # over the hole: no pair, yet the skin came in with the face round it (by the membrane)
    edges = (fit.ring != 0).astype(float)
    inner = cheek & ((edges @ (edges @ (~cheek).astype(float))) == 0)      # two rings in from its border
    inward = (out - off)[inner, 1] * MM
    assert inner.sum() > 50 and np.median(inward) > 0.3, np.percentile(inward, [5, 50, 95])
    # off: the pipeline leaves the skin as the levels left it
    skip = adapt.adapt(tpl, scan_v, scan_t, case[3], adapt.AdaptOptions(snap_reach=0.0, max_levels=1))
    assert skip.snapped is None and skip.report()["snapped"] is None and skip.stages["snap"] < 1e-3

def test_adapt_recovers_the_known_deformation(tpl, case):
    scan_v, scan_t, truth, clicks = case
    res = adapt.adapt(tpl, scan_v, scan_t, clicks)
    assert _corr_mm(tpl, res.verts_scan, truth) < 1.5
    assert res.outcome["ok"] and res.outcome["folds_left"] == 0 and res.outcome["seen_rms_mm"] < 0.3


def test_right_clicks_are_kept_a_wrong_one_is_dropped(tpl, case):
    fit, names, P, Q = _fit(tpl, case)
    assert check_clicks(fit, names, P, Q, np.ones(len(P))) == {}
    i = names.index("8.3")
    wrong = Q.copy()
    q, _, _ = fit.scan.query.closest_points((Q[i] + np.array([0.0, 0.0, 0.02]))[None])   # 2 cm up the cheek
    wrong[i] = q[0]
    assert set(check_clicks(fit, names, P, wrong, np.ones(len(P)))) == {"8.3"}


@pytest.mark.slow
def test_the_nose_tip_is_kept_with_eight_clicks(tpl, case):
    scan_v, scan_t, truth, clicks = case
    eight = {k: clicks[k] for k in mpeg4.CLICKS_8}
    res = adapt.adapt(tpl, scan_v, scan_t, eight)
    assert res.dropped == [] and res.flagged == {}


def test_drops_never_go_below_what_calibration_needs(tpl, case):
    fit, names, P, Q = _fit(tpl, case)
    rng = np.random.default_rng(3)
    wild = Q + rng.normal(0, 0.03, Q.shape)                         # every click 5 cm off
    dropped = check_clicks(fit, names, P, wild, np.ones(len(P)))
    assert len(names) - len(dropped) >= calibration.MIN_FDPS


@pytest.mark.slow
def test_swapped_labels_are_found_and_named(tpl, case):
    scan_v, scan_t, truth, clicks = case
    swapped = {(mpeg4.FDPS[k].mirror or k): v for k, v in clicks.items()}
    res = adapt.adapt(tpl, scan_v, scan_t, swapped)
    assert res.calibration_info["handedness"]["all"]
    assert any("viewer's side" in w for w in res.outcome["warnings"])
    assert _corr_mm(tpl, res.verts_scan, truth) < 1.5
    one = dict(clicks)
    one["3.7"], one["3.12"] = clicks["3.12"], clicks["3.7"]
    fixed, info = calibration.check_handedness(one, tpl.fdp_points())
    assert info["swapped"] == [["3.12", "3.7"]] and not info["all"]
    assert np.allclose(fixed["3.7"], clicks["3.7"])
    assert calibration.check_handedness(clicks, tpl.fdp_points())[1]["swapped"] == []
    # the panel's 8 clicks with both eyes' corners labelled from the viewer's side and the lips right
    # (a stranger's pipeline check: neither eye pair alone halves the residual, so nothing was found)
    eyes = {k: clicks[k] for k in mpeg4.CLICKS_8}
    for a, b in (("3.7", "3.12"), ("3.8", "3.11")):
        eyes[a], eyes[b] = clicks[b], clicks[a]
    fixed, info = calibration.check_handedness(eyes, tpl.fdp_points())
    assert sorted(info["swapped"]) == [["3.11", "3.8"], ["3.12", "3.7"]] and not info["all"]
    assert all(np.allclose(fixed[k], clicks[k]) for k in mpeg4.CLICKS_8)


@pytest.mark.slow
def test_a_mirrored_scan_is_named(tpl, case):
    scan_v, scan_t, truth, clicks = case
    flip = np.array([-1.0, 1.0, 1.0])
    res = adapt.adapt(tpl, scan_v * flip, scan_t, {k: v * flip for k, v in clicks.items()})
    assert any("mirrored" in w for w in res.outcome["warnings"])


@pytest.mark.slow
def test_clicks_are_evidence_not_law(tpl, case):
    """3 mm of disagreement between people costs at most 1 mm of correspondence, measured where it
    would show: on the face within 2 cm of a click."""
    scan_v, scan_t, truth, clicks = case
    fdps = tpl.fdp_points()
    near = np.min(np.linalg.norm(tpl.skin.verts[:, None] - np.array([fdps[k] for k in clicks])[None], axis=2), axis=1)
    near = _face(tpl) & (near < 0.02)

    def _corr_mm(tpl, verts, truth):
        return float(np.sqrt(np.mean(np.sum((verts - truth)[near] ** 2, axis=1)))) * MM

    exact = adapt.adapt(tpl, scan_v, scan_t, clicks)
    rng = np.random.default_rng(0)
    from headadapt_addon.core.mesh import spatial
    q = spatial.MeshQuery(scan_v, scan_t)
    costs = []
    for _ in range(3):
        moved = {k: q.closest_points((v + rng.normal(0, 0.003 / np.sqrt(3), 3))[None])[0][0] for k, v in clicks.items()}
        noisy = adapt.adapt(tpl, scan_v, scan_t, moved)
        costs.append(_corr_mm(tpl, noisy.verts_scan, truth) - _corr_mm(tpl, exact.verts_scan, truth))
    assert max(costs) < 1.0, costs


def test_a_closed_mouth_s_lip_corners_may_share_one_click(tpl, case):
    clicks = dict(case[3])
    fdps = tpl.fdp_points()
    clicks["8.4"] = _deform(fdps["8.4"][None])[0]
    clicks["2.5"] = clicks["8.4"].copy()             # inner and outer corner: one spot when closed
    assert set(calibration.validate_landmarks(clicks)) == set(clicks)
    clicks["3.12"] = clicks["3.7"].copy()            # two eye corners at one spot: a double click
    with pytest.raises(Exception, match="same spot"):
        calibration.validate_landmarks(clicks)


def test_a_level_s_solve_matches_a_direct_solve_warm_or_cold_and_by_its_factorisation():
    """solve_spd on a level-like system (a smoothness Gram matrix plus a ridge, three
    right-hand sides, one of them zero): diagonal-preconditioned CG, cold or warm; when CG is too
    slow, a sparse LU, which the next round's (slightly different) system uses as preconditioner."""
    from scipy import sparse
    from scipy.sparse.linalg import spsolve

    rng = np.random.default_rng(3)
    n = 400
    lap = sparse.diags([-np.ones(n - 1), 2.0 * np.ones(n), -np.ones(n - 1)], [-1, 0, 1])
    A = (lap.T @ lap + sparse.diags(rng.uniform(0.05, 1.0, n))).tocsr()
    b = np.c_[rng.standard_normal(n), np.zeros(n), rng.standard_normal(n)]

    def exact(M):
        return np.column_stack([spsolve(M.tocsc(), b[:, c]) for c in range(3)])

    want = exact(A)
    scale = np.abs(want).max()
    for x0 in (None, want + 0.01 * rng.standard_normal(want.shape)):
        x, factor = solve_spd(A, b, x0)
        assert factor is None and np.abs(x - want).max() < 1e-3 * scale
    x, factor = solve_spd(A, b, jacobi_steps=2)          # too few: the system is factorised
    assert factor is not None and np.abs(x - want).max() < 1e-9 * scale
    B = (A + sparse.diags(rng.uniform(0.0, 0.02, n))).tocsr()    # the next round: a little different
    x, again = solve_spd(B, b, x, factor)
    assert again is factor and np.abs(x - exact(B)).max() < 1e-3 * scale


def test_a_level_s_conjugate_gradients_take_scipy_s_steps():
    """conjugate_gradients (a level's solve without scipy's wrappers) gives scipy's cg answers to the
    bit, cold and warm, with the diagonal or another preconditioner, and says when it ran out of
    steps; so the adapted heads are the same as with scipy's cg."""
    import inspect

    from scipy import sparse
    from scipy.sparse.linalg import LinearOperator, cg

    from headadapt_addon.core.adapt.levels import conjugate_gradients

    if "rtol" not in inspect.signature(cg).parameters:
        pytest.skip("scipy before 1.12: its cg was another implementation")
    rng = np.random.default_rng(5)
    n = 300
    lap = sparse.diags([-np.ones(n - 1), 2.0 * np.ones(n), -np.ones(n - 1)], [-1, 0, 1])
    A = (lap.T @ lap + sparse.diags(rng.uniform(0.05, 1.0, n))).tocsr()
    b = rng.standard_normal(n)
    inverse = 1.0 / A.diagonal()
    shifted = 1.0 / (A.diagonal() + 1.0)
    for x0 in (None, rng.standard_normal(n)):
        for pre, M in ((inverse, sparse.diags(inverse)),
                       (shifted, LinearOperator(A.shape, matvec=lambda v: shifted * v))):
            for steps in (500, 7):
                want, info = cg(A, b, x0=None if x0 is None else x0.copy(), rtol=1e-6, atol=0.0,
                                maxiter=steps, M=M)
                got, status = conjugate_gradients(A, b, x0, 1e-6, steps, lambda r, pre=pre: pre * r)
                assert np.array_equal(got, want) and status == info
                assert (status == 0) == (steps == 500)
    assert conjugate_gradients(A, np.zeros(n), None, 1e-6, 10, lambda r: r)[1] == 0


@pytest.mark.slow
def test_a_face_only_scan_runs_every_level_and_keeps_the_least_e(tpl, testheads):
    """A frontal scanner's scan (the front half of scan-like head 300, 11 clicks, its markers): level 1's
    E rose 0.2% over level 0's, the paper's stop at the first rise kept level 0, 1.6 mm RMS from the
    scan, 'not trustworthy'. Every level is run now and the least E kept: level 4, 0.33 mm."""
    from headadapt_addon.core.adapt.options import AdaptOptions

    h = testheads.make_head(300, style="scan")
    _, rot, _ = h.similarity
    front = rot @ np.array([0.0, -1.0, 0.0])
    keep = (h.scan_verts[h.scan_tris].mean(axis=1) - h.true_template.mean(axis=0)) @ front > 0
    used = np.unique(h.scan_tris[keep])
    index = np.full(len(h.scan_verts), -1)
    index[used] = np.arange(len(used))
    verts, tris = h.scan_verts[used], index[h.scan_tris[keep]]
    clicks = {k: h.fdp_clicks[k] for k in mpeg4.CLICKS_11 if k in h.fdp_clicks}
    every = adapt.adapt(tpl, verts, tris, clicks, AdaptOptions(), markers=h.markers)
    assert every.best_level == 4 and every.outcome["ok"] and every.outcome["seen_rms_mm"] < 0.5, every.outcome
    paper = adapt.adapt(tpl, verts, tris, clicks, AdaptOptions(stop_at_minimum=True), markers=h.markers)
    assert paper.best_level == 0 and len(paper.levels) == 2 and not paper.outcome["ok"]
