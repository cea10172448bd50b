"""Core numerics on exact data: calibration, RBF/CSRBF, mean curvature, spatial queries, E_d."""
import numpy as np
import pytest
from scipy.spatial import ConvexHull
from scipy.spatial.transform import Rotation

from headadapt_addon.core import mpeg4
from headadapt_addon.core.adapt import calibration, clicks, metrics, rbf
from headadapt_addon.core.adapt.options import AdaptOptions
from headadapt_addon.core.adapt.scan import ScanSide
from headadapt_addon.core.exceptions import LandmarkError, MeshError
from headadapt_addon.core.mesh import curvature, geometry, spatial


@pytest.mark.parametrize("method", ["paper", "umeyama", "auto"])
@pytest.mark.parametrize("angles,scale", [((150, -40, 70), 1000.0), ((-10, 5, 3), 1.0), ((90, 90, 0), 25.4)])
def test_calibration_recovers_a_known_similarity(tpl, method, angles, scale):
    fdp = tpl.fdp_points()
    truth = calibration.Similarity(scale, Rotation.from_euler("zyx", angles, degrees=True).as_matrix(),
                                   np.array([10.0, -300.0, 5.0]))
    scan = {k: truth.apply(p) for k, p in fdp.items()}
    sim, info = calibration.calibrate(scan, fdp, method)
    assert np.abs(sim.compose(truth).matrix4() - np.eye(4)).max() < 1e-6
    assert info["rms"] < 1e-9
    back = sim.inverse().apply(sim.apply(scan["3.7"]))
    np.testing.assert_allclose(back, scan["3.7"], rtol=1e-9)


def test_calibration_reports_its_residuals_in_mm_too(tpl):
    """report.json's calibration rms and residuals were the template's metres, unlabelled, where the
    rest of the report is mm (0.00593 read as 5.93 mm)."""
    fdp = tpl.fdp_points()
    scan = {k: p + (np.array([0.0, 0.0, 0.003]) if k == "9.3" else 0.0) for k, p in fdp.items()}   # nose tip 3 mm off
    sim, info = calibration.calibrate(scan, fdp, "auto")
    assert info["residuals_mm"]["9.3"] == pytest.approx(info["residuals"]["9.3"] * 1000.0) and 2.5 < info["residuals_mm"]["9.3"] < 3.0
    assert info["rms_mm"] == pytest.approx(info["rms"] * 1000.0) and "mm" in info["units"]
    assert set(info["rms_by_method_mm"]) == {"paper", "umeyama"}
    partial = calibration.calibrate({k: scan[k] for k in list(scan)[:10] if k not in ("3.7",)}, fdp, "auto")[1]
    assert partial["rms_by_method"]["paper"] is None and partial["rms_by_method_mm"]["paper"] is None


def test_calibration_leans_on_the_face_and_reports_every_click(tpl):
    """A click far from the face that disagrees with the template (the top of the skull 30 mm off, as
    a head taller than the template's puts it) leaned the least-squares similarity away from the face.
    Fitted to the face's clicks (adapt's lean_on: clicks.calibrated_on), the similarity is the face's,
    and the far click is still reported with its residual."""
    fdp = tpl.fdp_points()
    truth = calibration.Similarity(1000.0, Rotation.from_euler("zyx", (20, -5, 3), degrees=True).as_matrix(),
                                   np.array([5.0, -20.0, 300.0]))
    names = list(mpeg4.CLICKS_11) + ["11.4"]
    scan = {k: truth.apply(fdp[k] + (np.array([0.0, 0.0, 0.03]) if k == "11.4" else 0.0)) for k in names}
    lean = clicks.calibrated_on(names)
    assert "11.4" not in lean and set(lean) == set(mpeg4.CLICKS_11)
    sim, info = calibration.calibrate(scan, fdp, "auto", lean_on=lean)
    assert np.abs(sim.compose(truth).matrix4() - np.eye(4)).max() < 1e-9
    assert info["not_leaned_on"] == ["11.4"] and info["residuals_mm"]["11.4"] == pytest.approx(30.0, abs=1e-6)
    leaned, _ = calibration.calibrate(scan, fdp, "auto")                       # every click: pulled off
    assert np.abs(leaned.compose(truth).matrix4() - np.eye(4))[:3].max() > 1e-3
    few, info = calibration.calibrate(scan, fdp, "auto", lean_on=["3.7", "3.12", "11.4"])   # under 4: all
    assert np.allclose(few.matrix4(), leaned.matrix4()) and "not_leaned_on" not in info
    firm = {k: scan[k] for k in mpeg4.CLICKS_11}                                 # the panel's: all firm
    same, info = calibration.calibrate(firm, fdp, "auto", lean_on=clicks.calibrated_on(firm))
    assert np.array_equal(same.matrix4(), calibration.calibrate(firm, fdp, "auto")[0].matrix4())
    assert "not_leaned_on" not in info


@pytest.mark.parametrize("case,needle", [("nan", "3.7"), ("unknown", "3.15"), ("duplicate", "3.12"),
                                         ("coplanar", "plane"), ("missing", "10.9"), ("few", "at least 4")])
def test_bad_landmarks_are_named(tpl, case, needle):
    pts = {k: p.copy() for k, p in tpl.fdp_points().items()}
    need = ()
    if case == "nan":
        pts["3.7"][1] = np.nan
    elif case == "unknown":
        pts["3.15"] = pts["3.7"]
    elif case == "duplicate":
        pts["3.12"] = pts["3.7"].copy()
    elif case == "coplanar":
        pts = {k: pts[k] * [1, 0, 1] for k in ("2.1", "11.1", "3.7", "3.12", "8.3", "8.4")}
    elif case == "missing":
        del pts["10.9"]
        need = calibration.mpeg4.CALIBRATION_FDPS
    elif case == "few":
        pts = {k: pts[k] for k in ("3.7", "3.12", "9.3")}
    with pytest.raises(LandmarkError, match=needle):
        calibration.validate_landmarks(pts, need=need)


def test_rbf_interpolates_with_rho_0_and_smooths_with_rho(tpl):
    rng = np.random.default_rng(3)
    p = np.array(list(tpl.fdp_points().values()))
    smooth = 0.01 * np.sin(20 * p)                     # a smooth field, metres
    noisy = smooth + rng.normal(0, 0.002, smooth.shape)
    f = rbf.fit_rbf(p, noisy)
    assert np.abs(f(p) - noisy).max() < 1e-6 * np.abs(noisy).max()
    g = rbf.fit_rbf(p, noisy, rho=0.05)
    assert np.abs(g(p) - noisy).max() > 1e-4                      # no longer interpolates
    # smoothing pulls the fit toward the underlying smooth field
    assert np.linalg.norm(g(p) - smooth) < np.linalg.norm(f(p) - smooth)


def test_csrbf_is_sparse_interpolates_and_vanishes_outside_its_support(tpl):
    rng = np.random.default_rng(4)
    v = tpl.skin.verts
    centres = v[rng.choice(len(v), 1500, replace=False)]
    values = rng.normal(0, 0.001, (1500, 3))
    sigma = 0.02
    f = rbf.fit_csrbf(centres, values, sigma)
    assert f.matrix.nnz < 0.1 * 1500 ** 2
    np.testing.assert_allclose(f(centres), values, atol=1e-9)
    far = v + rng.normal(size=v.shape)
    far = far[np.min(np.linalg.norm(far[:, None] - centres[None], axis=2), axis=1) > sigma]
    assert len(far) > 100 and np.all(f(far) == 0.0)


def _sphere(radius, n=12000):
    i = np.arange(n) + 0.5
    phi, theta = np.arccos(1 - 2 * i / n), np.pi * (1 + 5 ** 0.5) * i
    p = radius * np.c_[np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)]
    t = ConvexHull(p).simplices
    flip = np.einsum("ij,ij->i", geometry.face_normals(p, t), p[t].mean(axis=1)) < 0
    t[flip] = t[flip][:, ::-1]
    return p, t


@pytest.mark.parametrize("radius", [0.01, 0.1, 80.0])
def test_mean_curvature_of_a_sphere_is_one_over_r(radius):
    p, t = _sphere(radius)
    h, valid = curvature.mean_curvature(p, t)
    assert valid.all()
    assert abs(np.median(h) * radius - 1) < 0.02
    assert np.percentile(np.abs(h * radius - 1), 95) < 0.02


def test_curvature_excludes_the_boundary():
    p, t = _sphere(1.0)
    keep = p[t].mean(axis=1)[:, 2] > 0
    h, valid = curvature.mean_curvature(p, t[keep])
    border = geometry.boundary_vertices(t[keep], len(p))
    assert border.sum() > 50 and not valid[border].any()


def test_orient_outward_turns_each_inward_piece():
    p, t = _sphere(1.0, n=2000)
    q = p + [5.0, 0, 0]                                      # a second piece, wound inward
    v = np.vstack([p, q])
    tris = np.vstack([t, (t + len(p))[:, ::-1]])
    out, turned = geometry.orient_outward(v, tris, centre=np.array([2.5, 0, 0]))
    assert turned == 1
    # every face now points away from its own piece's centre
    n = geometry.face_normals(v, out)
    centres = np.where(np.arange(len(out))[:, None] < len(t), [0, 0, 0], [5.0, 0, 0])
    assert (np.einsum("ij,ij->i", n, v[out].mean(axis=1) - centres) > 0).all()
    assert geometry.orient_outward(v, out, centre=np.array([2.5, 0, 0]))[1] == 0


def test_mesh_checks_name_the_problem():
    with pytest.raises(MeshError, match="no vertices"):
        geometry.check_mesh(np.zeros((0, 3)), np.zeros((0, 3), int))
    with pytest.raises(MeshError, match="not a triangle mesh"):
        geometry.check_mesh(np.zeros((4, 3)), np.zeros((1, 4), int))
    with pytest.raises(MeshError, match="NaN"):
        geometry.check_mesh(np.array([[0, 0, 0], [1, 0, 0], [np.nan, 1, 0]]), np.array([[0, 1, 2]]))


@pytest.mark.parametrize("backend", ["numpy", "bvh", "embree"])
def test_queries_match_brute_force(tpl, backend):
    v, t = tpl.skin.verts, tpl.skin.tris
    q = spatial.MeshQuery(v, t, backend=backend)
    assert q.backend == backend
    rng = np.random.default_rng(5)
    pts = v[rng.integers(0, len(v), 200)] + rng.normal(0, 0.01, (200, 3))
    _, _, d = q.closest_points(pts)
    a, b, c = v[t[:, 0]], v[t[:, 1]], v[t[:, 2]]
    for p, dp in zip(pts[:60], d[:60]):
        cq, _ = spatial.closest_on_triangles(np.repeat(p[None], len(t), 0), a, b, c)
        assert abs(np.linalg.norm(cq - p, axis=1).min() - dp) < (1e-6 if backend == "bvh" else 1e-12)
    dirs = rng.normal(size=(200, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    hits = q.ray_cast(pts, dirs, 0.02)
    for k in range(60):
        hit, tt, _, _ = spatial.ray_triangles(np.repeat(pts[k][None], len(t), 0), np.repeat(dirs[k][None], len(t), 0), a, b, c)
        ok = hit & (np.abs(tt) <= 0.02)
        assert ok.any() == hits.hit[k]
        if ok.any():
            assert abs(tt[ok][np.argmin(np.abs(tt[ok]))] - hits.t[k]) < (1e-6 if backend == "bvh" else 1e-12)
            np.testing.assert_allclose(hits.bary[k] @ v[t[hits.face[k]]], hits.point[k], atol=1e-6)


def test_distance_error_is_zero_on_itself_and_ignores_holes(tpl):
    v, t = tpl.skin.verts, tpl.skin.tris
    vn = geometry.vertex_normals(v, t)
    w = tpl.region_weights[tpl.region]
    s = ScanSide(v, t, AdaptOptions())
    de = metrics.distance_error(v, vn, s.query, s.normal_at, w, 0.016)
    assert de.E_d < 1e-12 and de.matched.mean() > 0.99   # 0 up to float32 BVH rounding; folds may pick a face turned away
    # cut a hole in the forehead: the vertices over it get w = 0, E_d stays finite and small
    fore = tpl.region_mask("forehead")
    fi = np.flatnonzero(fore)
    centre = v[fi[np.argmin(np.linalg.norm(v[fi] - v[fi].mean(axis=0), axis=1))]]   # a forehead vertex
    cut = np.linalg.norm(v[t].mean(axis=1) - centre, axis=1) < 0.015
    holed = t[~cut]
    sh = ScanSide(v, holed, AdaptOptions())
    de = metrics.distance_error(v, vn, sh.query, sh.normal_at, w, 0.016, sh.on_border)
    inside = np.linalg.norm(v - centre, axis=1) < 0.010
    assert inside.sum() > 5 and np.all(de.w[inside] == 0)
    assert np.isfinite(de.E_d) and de.E_d < 1e-8
    # flipped normals never match
    de = metrics.distance_error(v, -vn, s.query, s.normal_at, w, 0.016)
    assert de.matched.mean() < 0.01


def test_unfold_falls_back_to_a_harmonic_patch_where_relaxing_stalls():
    """A 5x5 block of a flat grid pushed 6 edges sideways folds 10 triangles; one Jacobi step cannot
    undo it (34 folds were left before the fallback). The harmonic patch leaves none and touches
    nothing outside the vertices it reports as moved."""
    n = 21
    u, v = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    rest = np.c_[u.ravel(), v.ravel(), np.zeros(n * n)] * 0.001
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    t = np.r_[np.c_[a, b, c], np.c_[a, c, d]]
    x = rest.copy()
    block = np.zeros((n, n), bool)
    block[8:13, 8:13] = True
    x[block.ravel(), 0] += 0.006
    assert len(geometry.folded(rest, x, t)) == 10
    y, moved, left = geometry.unfold(rest, x, t, rounds=1, steps=1)
    assert left == 0 and len(geometry.folded(rest, y, t)) == 0
    assert np.array_equal(y[~moved], x[~moved])
    # the repair goes back toward x as far as it can: the block keeps part of its push
    assert np.mean(y[block.ravel(), 0] - rest[block.ravel(), 0]) > 0.0005


def test_distance_error_does_not_depend_on_which_face_answers_a_tie(tpl):
    """Points off the skin whose closest point is a vertex or an edge several faces share (over a
    hole's rim, at a crease): the face that answers is the backend's tie-break (numpy: the face the
    point is most squarely in front of; Blender's BVH: the first its search meets); whether the
    point matches must not change."""
    v, t = tpl.skin.verts, tpl.skin.tris
    fore = tpl.region_mask("forehead")
    fi = np.flatnonzero(fore)
    centre = v[fi[np.argmin(np.linalg.norm(v[fi] - v[fi].mean(axis=0), axis=1))]]
    holed = t[np.linalg.norm(v[t].mean(axis=1) - centre, axis=1) >= 0.015]
    vn = geometry.vertex_normals(v, holed)
    rng = np.random.default_rng(3)
    # every vertex of the scan, pushed off along a direction tilted from its normal: nearest the vertex
    # itself (a tie among its faces) wherever the vertex is convex enough
    used = np.unique(holed)
    tilt = vn[used] + 0.8 * rng.normal(size=(len(used), 3))
    pts = v[used] + 0.002 * tilt / np.linalg.norm(tilt, axis=1, keepdims=True)
    normals = vn[used] + 0.5 * rng.normal(size=(len(used), 3))
    w = np.ones(len(pts))
    a, b = ScanSide(v, holed, AdaptOptions(backend="numpy")), ScanSide(v, holed, AdaptOptions(backend="bvh"))
    fa, fb = a.query.closest_points(pts)[1], b.query.closest_points(pts)[1]
    assert (fa != fb).sum() > 100                                      # ties answered by other faces
    da = metrics.distance_error(pts, normals, a.query, a.normal_at, w, 0.016, a.on_border)
    db = metrics.distance_error(pts, normals, b.query, b.normal_at, w, 0.016, b.on_border)
    assert 0.2 < da.matched.mean() < 0.95
    np.testing.assert_array_equal(da.matched, db.matched)
