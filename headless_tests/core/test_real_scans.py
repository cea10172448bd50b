"""Real data: the template adapted onto a real head CT (skin and skull of one person) and onto a
real Cyberware range scan of a face (the kind of scan the paper adapts to).

The CT and its clicks: tools/realct.py; the clicks on the range scan and the two busts (stress
tests: statues, a crown, a beard): data/*_fdps.json. These tests skip when ../shared/scans is absent.
"""
import pathlib
import warnings

import numpy as np
import pytest

from headadapt_addon.core import adapt, anatomy, meshio
from headadapt_addon.core.mesh import geometry
from headadapt_addon.core.mesh.inside import winding_numbers
from headadapt_addon.core.mesh.spatial import MeshQuery
from headadapt_addon.core.template import load_template
from tools import realct

# every test here stands on generated or real heads adapted and transferred (10-20 s)
pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def ct(shared_scans):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        case = realct.run(load_template(), shared_scans)
    case.warnings = [str(w.message) for w in caught if issubclass(w.category, RuntimeWarning)]
    return case


def test_adapts_onto_the_real_ct_skin(ct):
    res = ct.result
    # the CT's marching-cubes skin has zero-area triangles: no overflow or NaN on the way
    assert not ct.warnings, ct.warnings
    assert not res.flagged and ct.mm == pytest.approx(1000, rel=0.2)    # the CT is in mm, head-sized
    tpl = ct.tpl
    lids = np.isin(tpl.region, [tpl.region_names.index(r) for r in ("eyelid_l", "eyelid_r")])
    d = res.distances * ct.mm
    # the CT covers the face from the brows to the chin and the ears: most of the visible face
    assert np.isfinite(d).sum() > 2500
    visible = ~tpl.hidden
    away = d[np.isfinite(d) & visible & ~lids]   # the lids are closed on the CT, open on the template
    # p95 is 1.90 mm under numpy 1.26 and 2.01 under numpy 2.5; rounding alone moves it that much: the
    # CT's coordinates scaled by 1 +- 1e-13 give 1.90 to 1.95 (numpy 1.26) and 1.87 to 2.01 (numpy 2.5)
    assert np.median(away) < 0.2 and np.percentile(away, 95) < 2.1, (np.median(away), np.percentile(away, 95))


def test_no_folds_where_the_scan_has_closed_eyes(ct, fran):
    # both real scans have the eyes closed or smoothed over: the template's open lids would fold
    # onto them; the levels leave those places to their smoothness, the rest is relaxed
    for tpl, res in ((ct.tpl, ct.result), fran):
        assert res.unfolded["folded_left"] == 0 and res.outcome["folds_left"] == 0 and res.outcome["ok"]
        assert len(geometry.folded(tpl.skin.verts, res.verts, tpl.skin.tris)) == 0


def test_transferred_skull_lies_on_the_persons_own_skull(ct):
    d = ct.bone_distance_mm(ct.transferred_bone())
    # the template skull is the table's mean person: on this real CT it lands within a few mm
    assert len(d) > 1500
    assert np.median(d) < 3.0 and np.percentile(d, 75) < 5.0, (np.median(d), np.percentile(d, 75))


def test_tissue_depths_on_the_ct_are_those_of_the_transferred_skull(ct):
    rows = [r for r in realct.tissue_depths(ct) if np.isfinite(r[2]) and np.isfinite(r[3])]
    assert len(rows) >= 20
    err = np.array([abs(ours - real) for _, _, real, ours in rows])
    # the transferred skull's depth against this person's real depth at each landmark, mean of 25 (3.93
    # mm with level 0 fitted to the whole skin, 3.91 fitted without the scalp and forehead). Each
    # landmark's "real" depth is measured from where the adapted skin puts it. The median used to be
    # asserted (3.25 mm since the unfold's harmonic fallback lets the pressed bone settle, 4.2 before;
    # 3.58 after the levels' rounds were fixed, 3.62 with the lip seam's band narrowed), but the sorted
    # errors have a gap at the middle (2.6 to 3.9 mm), so the median jumped 3.2 to 4.1 between level-0
    # variants whose mean moved by 0.1
    assert np.mean(err) < 4.2, [(n, round(real, 1), round(ours, 1)) for n, _, real, ours in rows]


def _assert_keys_bake_cleanly(tpl, ana):
    """Every key baked on an adapted head: neutral reproduced, no folded triangle, no visible skin
    vertex that the key moved inside the (moved) skull (one already inside at rest is the transfer's
    test's: test_no_visible_skin_inside_the_transferred_skull)."""
    from headadapt_addon.core.skin import bake

    keys, timing = bake.bake(tpl, ana)
    model = timing["model"]
    rest = ana.parts["skin"]
    assert np.abs(model.equilibrium({}) - rest).max() < 1e-4
    tris = tpl.skull_tris
    visible = ~tpl.hidden
    visible &= winding_numbers(rest, np.vstack([ana.parts["cranium"], ana.parts["mandible"]]), tris) < 0.5
    for key in keys:
        skin = key.moved.get("skin")
        if skin is None:
            continue
        assert len(model.flipped(skin)) == 0, key.name
        bone = np.vstack([ana.parts["cranium"], key.moved.get("mandible", ana.parts["mandible"])])
        moved = visible & (np.linalg.norm(skin - rest, axis=1) > 1e-5)
        # into the bone: through its surface, where the winding number steps by 1 (by an opening of the
        # skull, the orbit's, it passes 0.5 smoothly: a closed lid in the opening, 0.49 at rest, 0.50
        # after a 0.03 mm pull, 0.7 mm from any bone, is not in it)
        w = winding_numbers(skin[moved], bone, tris)
        crossed = (w > 0.5) & (w - winding_numbers(rest[moved], bone, tris) > 0.5)
        assert crossed.sum() == 0, key.name


@pytest.mark.slow
def test_expressions_bake_cleanly_on_the_real_ct(ct):
    # every key on the CT's head (3 keys put a lid vertex in the bone before the skull's folds were
    # relaxed; joy folded 3 lip-corner triangles before the unfold relaxed only around the folds)
    _assert_keys_bake_cleanly(ct.tpl, ct.anatomy)


def test_eyes_do_not_stand_out_through_the_closed_lids(ct):
    # the map carries the eyes 1.2 to 1.4 mm out through this person's closed lids; they go back, and
    # their orbits with them, until the eye's front meets the scanned lid (the template's lids stay
    # open on it, so the closed lid between them is taken for the eye: seat_orbits)
    for eye in ("eye_l", "eye_r"):
        v = ct.anatomy.parts[eye]
        centre = v.mean(axis=0)
        gaze = ct.anatomy.rigid[eye].rotation @ np.asarray(ct.tpl.meta["eyes"][eye]["gaze"])
        out = anatomy.eye_protrusion(ct.result.scan.query, v, centre, gaze / np.linalg.norm(gaze)) * ct.mm
        assert out < 0.25, (eye, out)
    d = ct.bone_distance_mm(ct.transferred_bone())
    assert np.median(d) < 2.2 and np.percentile(d, 90) < 6.0, (np.median(d), np.percentile(d, 90))


def test_eyes_sit_in_the_real_orbits(ct):
    q = ct.bone_query()
    reach = 35.0 / ct.mm
    for eye in ("eye_l", "eye_r"):
        centre = ct.anatomy.parts[eye].mean(axis=0)
        # the CT's bone above, below, behind and on the nose side of the eye, within 35 mm
        medial = -1.0 if eye == "eye_l" else 1.0
        dirs = np.array([[0, 0, 1], [0, 0, -1], [0, 1, 0], [medial, 0, 0]], float)
        hits = q.ray_cast(np.repeat(centre[None], 4, axis=0), dirs, reach, both_ways=False)
        assert hits.hit.all(), (eye, hits.t * ct.mm)
        assert q.closest_points(centre[None])[2][0] * ct.mm > 4.0, eye       # not in the bone


def test_no_visible_skin_inside_the_transferred_skull(ct):
    # the skin delivered with the skull (the transfer's: its lids seated on the eyes, slivers lifted out
    # last) has none inside it
    tpl = ct.tpl
    visible = np.flatnonzero(~tpl.hidden)
    tris, bone = tpl.skull_tris, ct.transferred_bone()
    w = winding_numbers(ct.anatomy.parts["skin"][visible], bone, tris)
    assert (w > 0.5).sum() == 0, visible[w > 0.5]
    # and the adaptation's own skin at most a sliver (under lift_visible_skin's 0.5 mm): a lid vertex of
    # the CT's closed left eye ended 0.7 mm inside the orbit's rim while the coarse scan's closest-point
    # pairs took the normal and the border from whichever face answered a tie; with level 0 fitted
    # without the scalp and forehead one lid vertex (2394) is 0.31 mm inside under numpy 1.26
    inside = visible[winding_numbers(ct.result.verts[visible], bone, tris) > 0.5]
    depth = MeshQuery(bone, tris, backend="numpy").closest_points(ct.result.verts[inside])[2] * ct.mm
    assert np.all(depth < 0.5), (inside, depth)


@pytest.fixture(scope="module")
def fran(shared_scans):
    tpl = load_template()
    verts, tris = meshio.read_mesh(shared_scans / "fran_cyberware" / "fran_cut.obj")[:2]
    clicks = meshio.read_landmarks(realct.ROOT / "headless_tests" / "data" / "fran_fdps.json")
    return tpl, adapt.adapt(tpl, verts, tris, clicks)


def test_calibrating_a_scan_wound_inward_leaves_no_worker_running(shared_scans, monkeypatch):
    # the scan's tree is begun on a worker before the winding check; on a scan whose pieces are
    # turned that tree is dropped. Left running, it outlived the calibrate operator, and Blender
    # crashed while it was still being built (2 of about 230 runs through the add-on). The tree is made
    # slow here so that a worker still running when calibrate returns is seen.
    import time

    from headadapt_addon.core.adapt import AdaptOptions, pipeline
    from headadapt_addon.core.adapt import scan as scan_side

    made, build, start = [], scan_side._spatial_side, scan_side.start_spatial

    def slow_build(*args):
        time.sleep(0.5)
        return build(*args)

    def started(*args):
        made.append(start(*args))
        return made[-1]

    monkeypatch.setattr(scan_side, "_spatial_side", slow_build)
    monkeypatch.setattr(scan_side, "start_spatial", started)
    monkeypatch.setattr(pipeline, "start_spatial", started)
    verts, tris = meshio.read_mesh(shared_scans / "fran_cyberware" / "fran_cut.obj")[:2]
    clicks = meshio.read_landmarks(realct.ROOT / "headless_tests" / "data" / "fran_fdps.json")
    fit, *_, info = pipeline.calibrate(load_template(), verts, tris, clicks, AdaptOptions())
    assert info["scan_pieces_turned"] == 1 and len(made) == 2      # the early tree, and the scan's own
    assert made[0].done()
    assert fit.scan.query is not None                              # the scan's own, waited for by its user


def test_adapts_onto_a_real_range_scan_wound_inward(fran):
    # the Cyberware file winds its triangles so that its normals face into the head: turned round,
    # the levels find their pairs (before: 12 pairs at level 1, stuck at level 0, 5.6 mm median)
    tpl, res = fran
    assert res.calibration_info["scan_pieces_turned"] == 1
    assert res.best_level >= 3 and not res.flagged
    visible = ~tpl.hidden
    lids = np.isin(tpl.region, [tpl.region_names.index(r) for r in ("eyelid_l", "eyelid_r")])
    d = res.distances * 1000 / res.similarity.scale          # the scan's mm
    assert (np.isfinite(d) & visible).sum() > 1200   # the face mask: brows to chin, ear to ear
    away = d[np.isfinite(d) & visible & ~lids]
    assert np.median(away) < 0.2 and np.percentile(away, 95) < 1.5, (np.median(away), np.percentile(away, 95))
    # the scan's eyes are closed: the template's open lids, unfolded, stay within a few mm of them
    on_lids = d[np.isfinite(d) & lids]
    assert np.median(on_lids) < 3.0, np.median(on_lids)


def test_the_level_kept_is_the_best_as_delivered(fran, shared_scans):
    # a level is judged with its folds relaxed, as it will be delivered (pipeline.Unfolding): on Fran's
    # closed eyes level 4 folds 19 lid triangles (level 3: 8), and relaxed over 1290 vertices they left
    # the seen face 0.80 mm RMS from the scan, against 0.53 had the fit stopped at level 3
    tpl, res = fran
    verts, tris = meshio.read_mesh(shared_scans / "fran_cyberware" / "fran_cut.obj")[:2]
    clicks = meshio.read_landmarks(realct.ROOT / "headless_tests" / "data" / "fran_fdps.json")
    for stop in range(1, res.levels[-1].level):
        earlier = adapt.adapt(tpl, verts, tris, clicks, adapt.AdaptOptions(max_levels=stop))
        assert res.outcome["seen_rms_mm"] <= earlier.outcome["seen_rms_mm"] + 0.02, (stop, res.outcome, earlier.outcome)


def test_expressions_bake_cleanly_on_a_real_range_scan(fran):
    # every key on Fran's adapted head (before this round 8 keys kept a fold here: joy 5, the smile's
    # lip corner keys 1-2; and giving the lip corner's pull back toward rest put 2 vertices lying
    # 0.1 mm above the cranium 1 mm into it)
    tpl, res = fran
    _assert_keys_bake_cleanly(tpl, anatomy.transfer(tpl, res))


@pytest.fixture(scope="module")
def nefertiti(shared_scans):
    tpl = load_template()
    verts, tris = meshio.read_mesh(shared_scans / "nefertiti" / "nefertiti-lowres.obj")[:2]
    clicks = meshio.read_landmarks(realct.ROOT / "headless_tests" / "data" / "nefertiti_fdps.json")
    res = adapt.adapt(tpl, verts, tris, clicks)
    return tpl, res, anatomy.transfer(tpl, res)


def test_adapts_onto_a_statue_with_a_crown(nefertiti):
    # a stress test: a limestone bust, a crown instead of hair, 35k vertices in about mm
    tpl, res, ana = nefertiti
    assert res.best_level >= 3 and not res.flagged and res.unfolded["folded_left"] == 0
    d = res.distances[_face(tpl)] / res.similarity.scale           # the scan's unit (about mm)
    d = d[np.isfinite(d)]
    assert len(d) > 1200
    assert np.median(d) < 0.2 and np.percentile(d, 95) < 3.0, (np.median(d), np.percentile(d, 95))


@pytest.fixture(scope="module")
def demosthenes(shared_scans):
    tpl = load_template()
    verts, tris = meshio.read_mesh(shared_scans / "demosthenes" / "demosthenes-low-res.obj")[:2]
    clicks = meshio.read_landmarks(realct.ROOT / "headless_tests" / "data" / "demosthenes_fdps.json")
    res = adapt.adapt(tpl, verts, tris, clicks)
    return tpl, res, anatomy.transfer(tpl, res)      # carved eyes: the lids lie in the orbit's opening


def test_adapts_onto_a_bearded_bust_in_its_own_units(demosthenes):
    # a stress test: a low-resolution photoscan of a bowed, bearded marble head, in units of ~15 cm
    tpl, res, ana = demosthenes
    assert 0.1 < res.similarity.scale < 0.2                     # found the unit from the clicks
    assert res.best_level >= 3 and not res.flagged and res.unfolded["folded_left"] == 0
    d = res.distances[_face(tpl)] * 1000                        # template mm
    d = d[np.isfinite(d)]
    assert len(d) > 1200
    assert np.median(d) < 0.2 and np.percentile(d, 95) < 4.0, (np.median(d), np.percentile(d, 95))


@pytest.mark.parametrize("bust", ["demosthenes", "nefertiti"])
def test_no_visible_skin_inside_a_bust_s_transferred_skull(bust, request):
    # a lid vertex of Demosthenes' right eye ended 0.016 mm inside the orbit's rim, where the bone by the
    # socket is frozen: the transfer's last step (lift.lift_visible_skin) lifts such slivers out
    tpl, res, ana = request.getfixturevalue(bust)
    visible = ~tpl.hidden
    bone = np.vstack([ana.parts["cranium"], ana.parts["mandible"]])
    assert (winding_numbers(ana.parts["skin"][visible], bone, tpl.skull_tris) > 0.5).sum() == 0


def _face(tpl):
    return np.isin(tpl.region, [tpl.region_names.index(r) for r in
                                ("forehead", "brow_l", "brow_r", "nose", "cheek_l", "cheek_r",
                                 "upper_lip", "lower_lip", "chin_jaw")])


@pytest.mark.parametrize("clicks_set", ["8", "11"])
@pytest.mark.parametrize("scan", ["demosthenes", "fran", "headsq_ct", "nefertiti"])
def test_real_scans_adapt_from_the_panel_s_click_sets(shared_scans, tpl, scan, clicks_set):
    """Issue 15: each real scan adapts from only the clicks the panel asks for (the 8, or the 11),
    as many of them as its landmark file has: no correct click dropped, no fold left, the face on
    the scan (the honest outcome ok). Before the unfold's harmonic fallback the CT's closed eyes
    kept 1-2 folded lid triangles and 1.5 mm RMS from 7 or 9 clicks (exit code 3)."""
    import json

    from headadapt_addon.core import mpeg4

    path = realct.ROOT / "headless_tests" / "data" / f"{scan}_fdps.json"
    meta = json.loads(path.read_text())
    mesh = shared_scans / pathlib.Path(meta["scan"]).relative_to("../shared/scans")
    verts, tris = meshio.read_mesh(mesh)[:2]
    given = meshio.read_landmarks(path)
    wanted = mpeg4.CLICKS_8 if clicks_set == "8" else mpeg4.CLICKS_11
    clicks = {k: given[k] for k in wanted if k in given}
    assert len(clicks) >= 7
    res = adapt.adapt(tpl, verts, tris, clicks)
    assert not res.dropped and not res.flagged, res.flagged
    assert res.unfolded["folded_left"] == 0
    assert res.outcome["ok"], res.outcome["warnings"]
    assert res.outcome["seen_rms_mm"] < 1.3, res.outcome["seen_rms_mm"]
