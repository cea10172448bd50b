"""A dense scan clustered once (core/mesh/simplify.py) before it is fitted, and the template's side of
the fit begun on a worker (adapt/fit.py prefetch)."""

from concurrent.futures import Future

import numpy as np
import pytest
from test_core_numerics import _sphere as sphere

from headadapt_addon.core.adapt import adapt, fit
from headadapt_addon.core.adapt.options import AdaptOptions
from headadapt_addon.core.mesh import geometry, simplify, spatial


def _sphere(radius=0.1, n=20000):
    """A closed sphere of n points wound outward (head-sized by default, metres)."""
    return sphere(radius, n)


def test_odd_edges_are_the_border_of_a_manifold_mesh():
    p, t = _sphere()
    assert len(geometry.odd_edges(t)) == 0
    cut = t[p[t].mean(axis=1)[:, 2] < 0.07]
    assert np.array_equal(geometry.odd_edges(cut), geometry.boundary_edges(cut))


def test_a_cell_s_rank_is_np_unique_s_inverse():
    rng = np.random.default_rng(3)
    # keys in runs, as a scan's vertex order gives them, with repeats and a negative one
    key = np.concatenate([np.sort(rng.integers(-5, 400, 300)), rng.integers(0, 50, 200), [7, 7, 7]])
    count, rank = simplify.unique_inverse(key)
    values, inverse = np.unique(key, return_inverse=True)
    assert count == len(values) and np.array_equal(rank, inverse)
    assert simplify.unique_inverse(np.zeros(0, np.int64))[0] == 0


def test_clustering_keeps_the_surface_the_winding_and_the_border():
    radius = 0.1
    p, t = _sphere(radius)
    t = t[p[t].mean(axis=1)[:, 2] < 0.07]                   # a hole: its border is a circle at z = 0.07
    edge = simplify.median_edge(p, t)
    cell = 3 * edge
    v, tris, border = simplify.cluster(p, t, cell)
    assert len(v) < len(p) / 5
    # the clusters' means lie on the sphere, a little inside (about cell^2 / (8 r))
    assert np.abs(np.linalg.norm(v, axis=1) - radius).max() < cell ** 2 / radius
    # each triangle once, none degenerate, wound outward but for a few slivers clustering folds over
    # (0.7% of them, 0.2% of the area)
    s = np.sort(tris, axis=1)
    assert len(np.unique(s, axis=0)) == len(tris)
    assert ((s[:, 0] != s[:, 1]) & (s[:, 1] != s[:, 2])).all()
    fc = geometry.face_cross(v, tris)
    out = np.einsum("ij,ij->i", fc, v[tris].mean(axis=1)) > 0
    area = np.linalg.norm(fc, axis=1)
    assert out.mean() > 0.98 and area[out].sum() > 0.995 * area.sum()
    # the border is the hole's, carried over; the triangles alone would show edges used once inside
    # the surface too, where clustering collapsed a fan
    on = np.unique(border)
    assert len(on) > 20 and np.abs(v[on, 2] - 0.07).max() < 2 * cell
    naive = np.unique(geometry.boundary_edges(tris))
    assert np.abs(v[naive, 2] - 0.07).max() > 5 * cell
    # the hole keeps its size: the border's points ring round it at the cut's radius
    ring = np.hypot(v[on, 0], v[on, 1])
    assert abs(np.median(ring) - np.sqrt(radius ** 2 - 0.07 ** 2)) < cell


def test_clustering_ignores_unused_vertices():
    p, t = _sphere()
    cell = 3 * simplify.median_edge(p, t)
    v, tris, border = simplify.cluster(p, t, cell)
    extra = np.vstack([[[5.0, 5.0, 5.0]], p, [[-5.0, 0.0, 0.0]]])
    v2, tris2, border2 = simplify.cluster(extra, t + 1, cell)
    assert np.array_equal(v, v2) and np.array_equal(tris, tris2) and np.array_equal(border, border2)


def test_a_piece_kilometres_away_is_clustered_as_one_nearby():
    """A stray triangle 50 km off (the grid's packed key holds 2^21 cells an axis: 17 km at this cell) gives
    the head the clusters a stray triangle 1 m off gives it (both below it, so the grid's origin is
    the same); before, clustering refused the scan with a ValueError (exit 1 in the batch)."""
    p, t = _sphere()
    cell = 3 * simplify.median_edge(p, t)

    def with_stray(x):
        stray = np.array([[x, 0.0, -1.0], [x + 0.01, 0.0, -1.0], [x, 0.01, -1.0]])
        return simplify.cluster(np.vstack([p, stray]), np.vstack([t, len(p) + np.arange(3)[None]]), cell)

    near, far = with_stray(1.0), with_stray(50000.0)
    assert np.array_equal(near[1], far[1]) and np.array_equal(near[2], far[2])
    head = np.ones(len(near[0]), bool)
    head[near[1][-1]] = False                                # the stray triangle's own clusters
    assert np.array_equal(near[0][head], far[0][head]) and len(np.unique(near[1][-1])) == 3


def test_a_triangle_soup_is_welded_and_fits_as_the_mesh_it_came_from(tpl):
    """The sample written with every triangle's own corners (some exporters do): before, every edge
    was a hole's border, the fit kept 7 seen vertices and ended at level 0, 'not trustworthy'."""
    from headadapt_addon.batch import SAMPLE_DIR
    from headadapt_addon.core import meshio

    v, t = meshio.read_mesh(SAMPLE_DIR / "scan.ply")
    clicks = meshio.read_landmarks(SAMPLE_DIR / "landmarks.json")
    soup_v, soup_t = v[t].reshape(-1, 3), np.arange(3 * len(t)).reshape(-1, 3)
    welded_v, welded_t = simplify.weld_if_split(soup_v, soup_t)
    assert len(welded_v) == len(np.unique(v[np.unique(t)], axis=0)) and len(welded_t) == len(t)
    assert simplify.weld_if_split(v, t) is None                          # a mesh is left as it is
    options = AdaptOptions(max_levels=2)
    soup, mesh = adapt(tpl, soup_v, soup_t, clicks, options), adapt(tpl, v, t, clicks, options)
    assert soup.calibration_info["scan_welded"] == {"vertices": len(soup_v), "kept": len(welded_v)}
    assert soup.outcome["ok"] and soup.best_level == mesh.best_level
    assert abs(soup.outcome["seen_vertices"] - mesh.outcome["seen_vertices"]) < 0.01 * mesh.outcome["seen_vertices"]
    assert abs(soup.outcome["seen_rms_mm"] - mesh.outcome["seen_rms_mm"]) < 0.02


def test_split_vertices_are_welded_within_a_100000th_of_the_scan_s_size(tpl):
    """Exporters split vertices at texture seams or write some triangles with their own corners; before,
    only a whole soup (1.5 vertices a triangle) was welded: a head with a third of its triangles split
    (1.4 a triangle) fitted at level 0, 'not trustworthy'. Corners 1e-4 mm apart (an exporter's
    rounding) are one point too."""
    from headadapt_addon.batch import SAMPLE_DIR
    from headadapt_addon.core import meshio

    v, t = meshio.read_mesh(SAMPLE_DIR / "scan.ply")
    clicks = meshio.read_landmarks(SAMPLE_DIR / "landmarks.json")
    rng = np.random.default_rng(0)
    split = rng.random(len(t)) < 0.3                                     # their own corners, jittered
    own = v[t[split]].reshape(-1, 3) + rng.normal(0.0, 1e-4, (3 * split.sum(), 3))
    sv = np.vstack([v, own])
    st = t.copy()
    st[split] = len(v) + np.arange(3 * split.sum()).reshape(-1, 3)
    assert 0.6 < len(sv) / len(st) < 1.5                                 # not a soup
    welded_v, welded_t = simplify.weld_if_split(sv, st)
    assert len(welded_v) == len(v) and np.array_equal(welded_t, t)
    options = AdaptOptions(max_levels=2)
    fit, mesh = adapt(tpl, sv, st, clicks, options), adapt(tpl, v, t, clicks, options)
    assert fit.calibration_info["scan_welded"] == {"vertices": len(sv), "kept": len(v)}
    assert fit.outcome["ok"] and fit.best_level == mesh.best_level
    assert np.abs(fit.verts_scan - mesh.verts_scan).max() < 1e-3          # mm: the same fit


@pytest.mark.slow
def test_a_dense_scan_is_clustered_and_fits_as_well(tpl, testheads):
    """A scan-like head remeshed finer (196k vertices, 0.96 mm median edge in the template frame) is
    clustered to the 1 mm grid of AdaptOptions.scan_cell, and its fit is as close to the scan (all of
    it, not the clusters), to the truth and to the markers as the fit of the whole scan."""
    head = testheads.make_head(3, style="scan", subdiv=3, decimate=0.95)
    clicks = {k: head.fdp_clicks[k] for k in ("3.7", "3.8", "3.11", "3.12", "8.3", "8.4", "9.3", "2.10")}
    seen = testheads.face_mask(tpl) & head.true_on_scan
    query = spatial.MeshQuery(head.scan_verts, head.scan_tris)
    figures = {}
    for cell in (0.001, 0.0):
        res = adapt(tpl, head.scan_verts, head.scan_tris, clicks, AdaptOptions(scan_cell=cell),
                          markers=head.markers)
        s = head.similarity[0] / 1000                         # scan units per mm of the true head
        surf = query.closest_points(res.verts_scan[seen])[2] / s
        corr = np.linalg.norm(res.verts_scan[seen] - head.true_template[seen], axis=1) / s
        figures[cell] = (np.sqrt(np.mean(surf ** 2)), np.sqrt(np.mean(corr ** 2)), res)
    clustered, whole = figures[0.001], figures[0.0]
    info = clustered[2].calibration_info["scan_clustered"]
    assert info["vertices"] == len(head.scan_verts) and info["kept"] < 0.7 * info["vertices"]
    assert "scan_clustered" not in whole[2].calibration_info
    assert clustered[0] < whole[0] * 1.05 + 0.01, (clustered[0], whole[0])      # surface, mm
    assert clustered[1] < whole[1] * 1.02, (clustered[1], whole[1])             # correspondence, mm
    assert clustered[2].outcome["ok"]


def test_the_template_side_begun_on_a_worker_is_the_one_made_here():
    from headadapt_addon.core.template import load_template

    options = AdaptOptions()
    ahead, here = load_template(), load_template()
    fit.prefetch(ahead, options)
    assert any(isinstance(v, Future) for v in ahead.derived.values())
    for k in range(1, options.max_levels + 1):
        sigma = fit.level_sigma(options, k)
        key = ("basis", sigma, options.centre_density)
        got = fit.template_side(ahead, key, None)             # waits for the worker's
        side = fit.template_side(here, ("fit", options.seam_band), lambda: fit._skin_side(here, options.seam_band))
        made = fit._level_basis(here.skin.verts, side[4], sigma, options.centre_density)
        assert np.array_equal(got[0], made[0]) and (got[4] != made[4]).nnz == 0
    # one that failed on the worker is made on the caller's thread
    failed = Future()
    failed.set_exception(MemoryError())
    here.derived["x"] = failed
    assert fit.template_side(here, "x", lambda: 42) == 42 and here.derived["x"] == 42


def test_a_kept_calibration_fits_the_same_to_the_bit(tpl):
    """adapt(calibrated=...) on calibrate()'s answer (the panel's Calibrate, kept for Adapt): the scan
    it prepared (here clustered on a 2 mm grid) is the one fitted, as often as asked, and every fit is
    the fresh one to the bit."""
    from headadapt_addon.batch import SAMPLE_DIR
    from headadapt_addon.core import meshio
    from headadapt_addon.core.adapt import pipeline

    verts, tris = meshio.read_mesh(SAMPLE_DIR / "scan.ply")
    clicks = meshio.read_landmarks(SAMPLE_DIR / "landmarks.json")
    options = AdaptOptions(scan_cell=0.002, max_levels=2)
    fresh = adapt(tpl, verts, tris, clicks, options)
    kept = pipeline.calibrate(tpl, verts, tris, clicks, options)
    for _ in range(2):
        res = adapt(tpl, verts, tris, clicks, options, calibrated=kept)
        assert res.scan is kept[0].scan and res.calibration_info["scan_prepared_before"]
        assert res.calibration_info["scan_clustered"] == fresh.calibration_info["scan_clustered"]
        assert np.array_equal(res.verts, fresh.verts) and np.array_equal(res.verts_scan, fresh.verts_scan)
        assert [lv.E for lv in res.levels] == [lv.E for lv in fresh.levels]
    assert "scan_prepared_before" not in fresh.calibration_info


def test_suggestions_snap_to_the_prepared_scan_as_to_the_scan(tpl):
    """Suggest the Rest snaps its proposals to the scan as calibrate() prepared it (the panel's): on a
    scan fitted whole they are the scan's own closest points up to rounding; on a scan clustered to a
    2 mm grid (twice the sample's edge, the harshest case) within half a cell of the scan and at
    most a cell and a half from where the scan itself puts them (people's clicks spread 2 to 3 mm)."""
    from headadapt_addon.batch import SAMPLE_DIR
    from headadapt_addon.core import meshio, mpeg4
    from headadapt_addon.core.adapt import pipeline, suggest

    verts, tris = meshio.read_mesh(SAMPLE_DIR / "scan.ply")                     # mm
    clicks = {k: v for k, v in meshio.read_landmarks(SAMPLE_DIR / "landmarks.json").items() if k in mpeg4.CLICKS_8}
    plain = suggest.suggest_fdps(tpl, verts, tris, clicks)
    assert len(plain) > 50 and not set(plain) & set(clicks)
    query = spatial.MeshQuery(verts, tris)
    for cell, gap_mm, off_mm in ((0.0, 1e-9, 1e-9), (0.002, 1.0, 3.0)):
        fit_, _, _, sim, _ = pipeline.calibrate(tpl, verts, tris, clicks, AdaptOptions(scan_cell=cell))
        got = suggest.suggest_fdps(tpl, verts, tris, clicks, snap=suggest.snap_to_prepared(fit_.scan, sim))
        assert set(got) == set(plain)
        off = np.array([np.linalg.norm(got[k] - plain[k]) for k in plain])
        gap = query.closest_points(np.array(list(got.values())))[2]
        assert gap.max() < gap_mm and off.max() < off_mm, (cell, gap.max(), off.max())
        assert (gap.max() > 1e-6) == (cell > 0)             # the clusters' surface, not the scan's
