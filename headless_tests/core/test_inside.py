"""Inside tests: FastWinding (core/winding.py) against the brute-force winding number (core/inside.py).

FastWinding closes a mesh with caps over its border loops, counts ray crossings of the closed
surface (an integer) and subtracts the caps' winding number; it claims the brute force's values
up to rounding. Each test here fails if the acceleration is wrong: a crossing missed or counted
twice (the ray through an edge or a vertex), a cap turned the wrong way or missing, a grid cell
that loses a triangle, a grid kept after the mesh moved out of its slack.
"""
import time

import numpy as np
import pytest
from scipy.spatial import ConvexHull

from headadapt_addon.core import anatomy
from headadapt_addon.core.mesh.caps import border_edges, border_loops, cap_triangles
from headadapt_addon.core.mesh.inside import winding_numbers
from headadapt_addon.core.mesh.spatial import MeshQuery
from headadapt_addon.core.mesh.winding import ROTATION, FastWinding

ATOL = 1e-9          # values: the brute force's up to rounding (1e-13 seen); this is the test's margin


def sphere(n=400, radius=1.0, centre=(0.0, 0.0, 0.0), seed=0):
    """A closed, outward-turned triangle mesh of a sphere (convex hull of Fibonacci points)."""
    i = np.arange(n) + 0.5
    phi, theta = np.arccos(1 - 2 * i / n), np.pi * (1 + 5 ** 0.5) * i
    v = np.c_[np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)]
    t = ConvexHull(v).simplices.copy()
    c = v[t]
    inward = np.einsum("ij,ij->i", np.cross(c[:, 1] - c[:, 0], c[:, 2] - c[:, 0]), c.mean(axis=1)) < 0
    t[inward] = t[inward][:, ::-1]
    return radius * v + np.asarray(centre), t


def torus(n=40, m=20, big=1.0, small=0.35):
    """A closed, outward-turned torus (genus 1) on an n x m grid."""
    u, w = np.meshgrid(np.arange(n) * 2 * np.pi / n, np.arange(m) * 2 * np.pi / m, indexing="ij")
    v = np.c_[((big + small * np.cos(w)) * np.cos(u)).ravel(), ((big + small * np.cos(w)) * np.sin(u)).ravel(),
              (small * np.sin(w)).ravel()]
    idx = np.arange(n * m).reshape(n, m)
    a, b = idx, np.roll(idx, -1, axis=0)
    c, d = np.roll(idx, -1, axis=1), np.roll(np.roll(idx, -1, axis=0), -1, axis=1)
    t = np.r_[np.c_[a.ravel(), b.ravel(), d.ravel()], np.c_[a.ravel(), d.ravel(), c.ravel()]]
    return v, t


def cube_grid(k=4):
    """A closed, outward-turned unit cube, each face a k x k grid: vertices on a lattice, so that
    rays and points line up with its edges and vertices as often as can be."""
    g = np.linspace(0.0, 1.0, k + 1)
    verts, tris = [], []
    for axis in range(3):
        for side in (0.0, 1.0):
            a, b = [x for x in range(3) if x != axis]
            uu, vv = np.meshgrid(g, g, indexing="ij")
            p = np.zeros(((k + 1) ** 2, 3))
            p[:, axis], p[:, a], p[:, b] = side, uu.ravel(), vv.ravel()
            base = len(verts) and sum(len(x) for x in verts)
            idx = base + np.arange((k + 1) ** 2).reshape(k + 1, k + 1)
            q = np.r_[np.c_[idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()],
                      np.c_[idx[:-1, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()]]
            n = np.cross(p[q[:, 1] - base] - p[q[:, 0] - base], p[q[:, 2] - base] - p[q[:, 0] - base])
            if (n[0, axis] > 0) != (side > 0.5):
                q = q[:, ::-1]
            verts.append(p)
            tris.append(q)
    v, t = np.vstack(verts), np.vstack(tris)
    # weld the shared edge vertices
    uniq, inv = np.unique(np.round(v, 9), axis=0, return_inverse=True)
    return uniq, inv.ravel()[t]


def probe_points(v, t, rng, n=1500):
    """Points all about a mesh: in its box and beyond, near its surface (both sides, down to 1e-6 of
    its size), at its vertices and edges pushed off the surface along the ray, and near its border."""
    lo, hi = v.min(axis=0), v.max(axis=0)
    size = float(np.linalg.norm(hi - lo))
    box = rng.uniform(lo - 0.2 * (hi - lo), hi + 0.2 * (hi - lo), (n, 3))
    c = v[t]
    normal = np.cross(c[:, 1] - c[:, 0], c[:, 2] - c[:, 0])
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-300)
    f = rng.integers(0, len(t), n)
    bary = rng.dirichlet(np.ones(3), n)
    offset = size * 10.0 ** rng.uniform(-6, -1, n) * rng.choice([-1.0, 1.0], n)
    near = np.einsum("ij,ijk->ik", bary, c[f]) + offset[:, None] * normal[f]
    ray = ROTATION[2]                       # points below a vertex or an edge, along the ray
    k = rng.integers(0, len(v), n // 3)
    below_vertex = v[k] - size * rng.uniform(0.01, 0.5, len(k))[:, None] * ray
    e = rng.integers(0, len(t), n // 3)
    mid = 0.5 * (v[t[e, 0]] + v[t[e, 1]])
    below_edge = mid - size * rng.uniform(0.01, 0.5, len(e))[:, None] * ray
    border = border_edges(t)
    if len(border):
        b = border[rng.integers(0, len(border), n // 3)]
        rim = 0.5 * (v[b[:, 0]] + v[b[:, 1]]) + size * 1e-3 * rng.normal(size=(len(b), 3))
    else:
        rim = np.zeros((0, 3))
    return np.vstack([box, near, below_vertex, below_edge, rim])


def assert_same(v, t, points, fw=None):
    fw = fw or FastWinding(v, t)
    fast, brute = fw(points), winding_numbers(points, v, t)
    assert np.isfinite(fast).all()
    np.testing.assert_allclose(fast, brute, rtol=0, atol=ATOL)
    clear = np.abs(brute - 0.5) > ATOL
    assert np.array_equal((fast > 0.5)[clear], (brute > 0.5)[clear])
    return fast


def test_closed_meshes_wind_once_inside_and_equal_the_brute_force():
    rng = np.random.default_rng(1)
    for v, t in (sphere(), torus(), cube_grid()):
        assert len(border_edges(t)) == 0
        w = assert_same(v, t, probe_points(v, t, rng))
        assert set(np.round(w[np.abs(w - np.round(w)) < 1e-6]).astype(int)) <= {0, 1}


def test_a_ray_along_the_lattice_of_a_cube_counts_each_crossing_once():
    # points on the cube's own lattice, off its surface: their rays meet edges and vertices
    v, t = cube_grid(4)
    g = np.linspace(-0.5, 1.5, 17)
    x, y, z = np.meshgrid(g, g, g, indexing="ij")
    p = np.c_[x.ravel(), y.ravel(), z.ravel()]
    on_surface = (np.abs(p - 0.0) < 1e-12) | (np.abs(p - 1.0) < 1e-12)
    inside_box = ((p >= 0) & (p <= 1)).all(axis=1)
    p = p[~(on_surface.any(axis=1) & inside_box)]
    w = assert_same(v, t, p)
    inside = ((p > 0) & (p < 1)).all(axis=1)
    np.testing.assert_allclose(w, inside.astype(float), atol=ATOL)
    # and the same points turned so that the rays run along the cube's axes
    assert_same(v @ ROTATION, t, p @ ROTATION)


def test_open_meshes_caps_and_soups_equal_the_brute_force():
    rng = np.random.default_rng(2)
    v, t = sphere(600)
    holes = [t[v[t].mean(axis=1)[:, 2] < 0.6],                     # a sphere with its top cut off
             t[np.abs(v[t].mean(axis=1)[:, 0]) > 0.3],            # two holes
             t[v[t].mean(axis=1)[:, 2] > 0.0]]                    # a hemisphere (a bowl)
    tv, tt = torus()
    keep = rng.random(len(tt)) > 0.1                               # a torus with 10% of it missing
    cases = [(v, h) for h in holes] + [(tv, tt[keep])]
    # two overlapping spheres as one soup: winding number 2 where they overlap
    v2, t2 = sphere(300, centre=(0.5, 0.1, 0.0))
    cases.append((np.vstack([v, v2]), np.vstack([t, t2 + len(v)])))
    # a bowtie: two fans that meet at one vertex (two border loops through it)
    fan = np.array([[0, 1, 2], [0, 2, 3], [0, 3, 4], [0, 5, 6], [0, 6, 7], [0, 7, 8]])
    pts = np.array([[0, 0, 0], [1, 0, 0.2], [1, 1, 0.1], [0.2, 1, 0], [-0.3, 0.8, 0.3],
                    [-1, 0, 0.2], [-1, -1, -0.1], [0, -1, 0.1], [0.5, -0.8, 0.4]], dtype=float)
    cases.append((pts, fan))
    for verts, tris in cases:
        assert len(border_edges(np.vstack([tris, cap_triangles(border_loops(border_edges(tris)))]))) == 0
        assert_same(verts, tris, probe_points(verts, tris, rng, 800))


def test_the_template_parts_equal_the_brute_force(tpl):
    rng = np.random.default_rng(3)
    skull_v = np.vstack([tpl.parts["cranium"].verts, tpl.parts["mandible"].verts])
    meshes = [(p.verts, p.tris) for p in tpl.parts.values()] + [(skull_v, tpl.skull_tris)]
    for v, t in meshes:
        assert_same(v, t, probe_points(v, t, rng, 600))
    # the transfer's own questions: bone points in the skin, skin points in the skull
    skin = tpl.skin
    assert_same(skin.verts, skin.tris, skull_v[::2] + rng.normal(0, 0.002, skull_v[::2].shape))
    assert_same(skull_v, tpl.skull_tris, skin.verts[::2] + rng.normal(0, 0.001, skin.verts[::2].shape))


def test_points_on_the_surface_fall_back_to_the_brute_force(tpl):
    v, t = tpl.skin.verts, tpl.skin.tris
    on = np.vstack([v[:300], 0.5 * (v[t[:300, 0]] + v[t[:300, 1]]), v[t[:300]].mean(axis=1)])
    np.testing.assert_allclose(FastWinding(v, t)(on), winding_numbers(on, v, t), atol=ATOL)


def test_a_moving_mesh_refits_its_grid(tpl):
    rng = np.random.default_rng(4)
    v0 = np.vstack([tpl.parts["cranium"].verts, tpl.parts["mandible"].verts])
    t = tpl.skull_tris
    points = tpl.skin.verts[::3] + rng.normal(0, 0.001, tpl.skin.verts[::3].shape)
    fw = FastWinding(v0, t, slack=0.001)
    for k, amplitude in enumerate((0.0005, 0.003, 0.01, 0.0)):   # within the slack, beyond, far beyond, back
        v = v0 + amplitude * np.sin(40 * v0[:, [1, 2, 0]] + k)
        assert_same(v, t, points, fw.refit(v))
    with pytest.raises(ValueError):
        fw.refit(v0[:-1])


def test_kept_cap_terms_give_the_fresh_sums_to_the_bit(tpl, monkeypatch):
    """FastWinding(remember=True), as the transfer asks the skull: the same points asked again while
    the bone moves in places sum the kept terms of the caps that did not move. Its values are those
    of a FastWinding that sums every cap afresh, to the bit, through moved caps, moved points, a
    query of another size in between and a point that is not a number; and it computes only what
    moved."""
    from headadapt_addon.core.mesh import winding

    v0 = np.vstack([tpl.parts["cranium"].verts, tpl.parts["mandible"].verts])
    t = tpl.skull_tris
    rng = np.random.default_rng(11)
    points = tpl.skin.verts[::2] + rng.normal(0, 0.001, tpl.skin.verts[::2].shape)
    kept, fresh = FastWinding(v0, t, slack=0.001, remember=True), FastWinding(v0, t, slack=0.001)
    rims = np.unique(kept.cap)
    terms = []
    real = winding.solid_angles
    monkeypatch.setattr(winding, "solid_angles", lambda p, c, **k: terms.append(len(p) * len(c)) or real(p, c, **k))
    v, p = v0.copy(), points.copy()
    steps = []
    for k in range(6):
        if k == 1:          # a few rim vertices (cap corners) and other bone vertices move
            v[rng.choice(rims, 12, replace=False)] += 0.002
            v[rng.choice(len(v), 100, replace=False)] -= 0.001
        if k == 2:          # some points move
            p[rng.choice(len(p), 40, replace=False)] += 0.003
        if k == 3:          # another query in between, then the big one with its points unmoved
            small = p[:50] + 0.0005
            assert np.array_equal(kept.refit(v)(small), fresh.refit(v)(small))
        if k == 4:
            p[7] = np.nan
        if k == 5:          # everything moves
            v += 0.001
        terms.clear()
        got, want = kept.refit(v)(p), fresh.refit(v)(p)
        assert np.array_equal(got, want, equal_nan=True), k
        steps.append(sum(terms))
        ok = np.isfinite(p).all(axis=1)
        np.testing.assert_allclose(got[ok], winding_numbers(p[ok], v, t), atol=ATOL)
    full = len(p) * len(kept.cap)
    assert steps[0] == full and steps[5] == full
    assert 0 < steps[1] < 0.2 * full and 0 < steps[2] < 0.05 * full and steps[3] == 0, (steps, full)


def test_a_triangle_collapsed_to_a_point_sends_no_point_to_the_brute_force():
    """A triangle whose corners coincide (the transfer presses some bone triangles so) has no area;
    the points round it are counted by the crossings, not summed by brute force, and right."""
    v, t = sphere(200)
    spot = v[t[0]].mean(axis=0) * 0.9                                       # just inside the surface
    v2 = np.vstack([v, spot, spot, spot])
    t2 = np.vstack([t, [len(v), len(v) + 1, len(v) + 2]])
    rng = np.random.default_rng(8)
    points = spot + rng.normal(0, 0.01, (300, 3))                            # within the grid's slack
    fw = FastWinding(v2, t2, slack=0.05)
    assert not fw.crossings(points)[1].any()
    np.testing.assert_allclose(fw(points), winding_numbers(points, v2, t2), atol=ATOL)


def test_empty_and_degenerate_inputs():
    v, t = sphere(50)
    fw = FastWinding(v, t)
    assert fw(np.zeros((0, 3))).shape == (0,)
    assert np.isnan(fw(np.array([[np.nan, 0.0, 0.0]]))).all()
    assert FastWinding(v, np.zeros((0, 3), int))(v[:4]).tolist() == [0.0] * 4
    far = np.array([[100.0, 0, 0], [0, -100.0, 3], [0, 0, 1e6]])
    np.testing.assert_allclose(fw(far), winding_numbers(far, v, t), atol=ATOL)


def test_fast_winding_is_much_faster_than_the_brute_force(tpl):
    # the point of it: on the skin and 1,000 bone points, tens of times faster (at least 5x here)
    v, t = tpl.skin.verts, tpl.skin.tris
    points = tpl.parts["cranium"].verts[::2][:1000]
    fw = FastWinding(v, t)
    fw(points[:10])                                  # build the grid
    fast, brute = [], []
    for _ in range(3):
        t0 = time.perf_counter()
        fw(points)
        fast.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        winding_numbers(points, v, t)
        brute.append(time.perf_counter() - t0)
    assert min(brute) > 5 * min(fast), (min(brute), min(fast))


def test_within_selects_what_the_closest_point_selects(tpl):
    # clear_visible_skin's skin vertices near the bone: _within against MeshQuery for every vertex
    bone = np.vstack([tpl.parts["cranium"].verts, tpl.parts["mandible"].verts])
    skin = tpl.skin.verts + np.random.default_rng(5).normal(0, 0.002, tpl.skin.verts.shape)
    d = MeshQuery(bone, tpl.skull_tris, backend="numpy").closest_points(skin)[2]
    for reach in (0.002, 0.006, 0.02):
        near = anatomy.bone._within(skin, bone, tpl.skull_tris, reach)
        assert np.array_equal(near, d < reach), reach
        assert 0 < near.sum() < len(skin)


class BruteWinding:
    """The old inside test behind FastWinding's interface: every triangle summed at every point."""

    def __init__(self, verts, tris, slack=None, remember=None):
        self.verts, self.tris = verts, tris

    def refit(self, verts):
        self.verts = verts
        return self

    def __call__(self, points):
        return winding_numbers(points, self.verts, self.tris)


@pytest.mark.slow
def test_the_transferred_anatomy_is_the_brute_force_one(tpl, legacy_heads, monkeypatch):
    # a whole transfer on a head with thin lids on the orbit's rim (the skull cleared, unrelaxed and
    # cleared again), with FastWinding and _within, and with the brute force in their place
    from headadapt_addon.core.mesh import winding

    _, res, _ = legacy_heads(7)
    fast = anatomy.transfer(tpl, res)
    monkeypatch.setattr(winding, "FastWinding", BruteWinding)
    monkeypatch.setattr(anatomy.bone, "_within", lambda points, verts, tris, reach: MeshQuery(
        verts, tris, backend="numpy").closest_points(points)[2] < reach)
    brute = anatomy.transfer(tpl, res)
    for part in brute.parts:
        np.testing.assert_allclose(fast.parts[part], brute.parts[part], rtol=0, atol=1e-12, err_msg=part)
    for a, b in zip(fast.muscles, brute.muscles):
        np.testing.assert_allclose(a["attachment"], b["attachment"], rtol=0, atol=1e-12)
