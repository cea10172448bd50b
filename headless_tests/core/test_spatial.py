"""The spatial queries (core/mesh/spatial.py, core/mesh/bvh.py) against brute force over every triangle:
the numpy tree's walks, its shells, chunks and tie rule, the bvh backend's float64 refinement, and the
embree backend's rays (core/mesh/embree.py: Embree's face, measured in float64)."""
import numpy as np
import pytest

from headadapt_addon.core.mesh import bvh, geometry, spatial, triangles
from headadapt_addon.core.template import load_template


@pytest.fixture(scope="module")
def skin():
    tpl = load_template()
    return tpl.skin.verts, tpl.skin.tris


def uneven_mesh(seed=0):
    """A bumpy sphere with triangles of very different sizes (a coarse cap, a fine band), a few
    slivers, a zero-area triangle and vertices no triangle uses."""
    rng = np.random.default_rng(seed)
    from scipy.spatial import ConvexHull
    pts = rng.normal(size=(600, 3))
    pts /= np.linalg.norm(pts, axis=1, keepdims=True)
    band = rng.normal(size=(1500, 3)) * [1, 1, 0.05]
    band /= np.linalg.norm(band, axis=1, keepdims=True)
    pts = np.vstack([pts[pts[:, 2] < 0.3], pts[pts[:, 2] > 0.9][:5], band])
    tris = ConvexHull(pts).simplices
    verts = pts * (0.1 + 0.003 * np.sin(7 * pts[:, :1]))
    verts = np.vstack([verts, rng.normal(size=(5, 3))])                 # unused vertices
    tris = np.vstack([tris, [[tris[0, 0], tris[0, 0], tris[0, 1]]]])   # a zero-area triangle
    return verts, tris


def brute_closest(verts, tris, p):
    """Closest (point, face, distance) measured on every triangle, chosen by the module's rule."""
    _, q, f, dist = triangles.closest_choice(p[None], np.zeros(len(tris), np.int64), np.arange(len(tris)), verts, tris)
    return q[0], int(f[0]), dist[0]


def brute_ray(verts, tris, o, d, lo, hi):
    """Nearest hit (t or None, face) measured on every triangle, chosen by the module's rule."""
    who, t, f, _ = triangles.ray_choice(o[None], d[None], np.array([lo]), np.array([hi]), np.zeros(len(tris), np.int64),
                                        np.arange(len(tris)), verts, tris)
    return (t[0], int(f[0])) if len(who) else (None, None)


def test_the_rule_at_a_tie():
    """pick: least first key exactly, then second, then the lowest face. closest_choice at a shared
    vertex: the face the point lies most squarely in front of; on the surface (no offset), the lowest."""
    owner = np.array([0, 0, 0, 1, 1, 2])
    who, idx = triangles.pick(owner, np.array([1.0, 1.0, 1.0, 2.0, 1.0, 5.0]), np.array([0.5, 0.2, 0.2, 0, 0, 0]),
                              np.array([9, 7, 8, 1, 2, 3]))
    assert list(who) == [0, 1, 2] and list(idx) == [1, 4, 5]
    # a pyramid: apex over the middle of a square, four faces; a point above the apex, leaning to +x
    verts = np.array([[0.0, 0, 2.0], [1, 1, 0], [-1, 1, 0], [-1, -1, 0], [1, -1, 0]])
    tris = np.array([[0, 1, 2], [0, 2, 3], [0, 3, 4], [0, 4, 1]])           # faces towards +y, -x, -y, +x
    n = geometry.face_normals(verts, tris)
    p = np.array([[0.3, 0.05, 3.0], [0.0, 0.0, 2.0]])
    _, q, f, _ = triangles.closest_choice(p, np.repeat([0, 1], 4), np.tile(np.arange(4), 2), verts, tris)
    np.testing.assert_array_equal(q, verts[[0, 0]])                        # both nearest the apex
    off = (p[0] - verts[0]) / np.linalg.norm(p[0] - verts[0])
    assert f[0] == np.argmax(np.abs(n @ off)) == 3 and f[1] == 0


@pytest.mark.parametrize("leaf_size", [1, 2, 4, 7])
def test_the_tree_holds_every_triangle_in_boxes_that_hold_it(leaf_size):
    verts, tris = uneven_mesh()
    tree = bvh.TriangleBVH(verts, tris, leaf_size=leaf_size)
    assert sorted(tree.face) == list(range(len(tris)))                   # each triangle in one slot
    assert np.all(np.diff(tree.leaf_start) >= 1) and np.all(np.diff(tree.leaf_start) <= max(leaf_size, 2))
    leaf_of_slot = np.repeat(np.arange(len(tree.leaf_start) - 1), np.diff(tree.leaf_start))
    corners = verts[tris[tree.face]]
    for level in range(tree.depth, -1, -1):
        lo, hi = np.stack(tree.boxes[level][:3], 1), np.stack(tree.boxes[level][3:], 1)
        node = leaf_of_slot >> (tree.depth - level)
        assert np.all(corners >= lo[node][:, None]) and np.all(corners <= hi[node][:, None])


@pytest.mark.parametrize("leaf_size", [2, 3, 4])
def test_the_walk_two_levels_a_step_keeps_the_leaves_the_walk_level_by_level_keeps(skin, leaf_size, monkeypatch):
    verts, tris = skin
    tree = bvh.TriangleBVH(verts, tris, leaf_size=leaf_size)
    rng = np.random.default_rng(leaf_size)
    o = verts[rng.choice(len(verts), 300)] + rng.normal(0, 0.003, (300, 3))
    d = rng.normal(size=(300, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    reach = rng.uniform(0.001, 0.05, 300)
    walk = bvh.TriangleBVH._walk
    got = tree.ray_candidates(o, d, -reach, reach), tree.closest(o)
    monkeypatch.setattr(bvh.TriangleBVH, "_walk", lambda self, count, keep_fn: walk(self, count, keep_fn, stride=1))
    want = tree.ray_candidates(o, d, -reach, reach), tree.closest(o)
    assert tree.depth >= 3 and all(np.array_equal(a, b) for a, b in zip(got[0], want[0]))
    assert len(got[0][0]) > 3 * len(o)
    assert all(np.array_equal(a, b) for a, b in zip(got[1], want[1]))


@pytest.mark.parametrize("mesh", ["skin", "uneven"])
def test_closest_points_are_the_brute_force_ones(skin, mesh):
    verts, tris = skin if mesh == "skin" else uneven_mesh()
    scale = np.linalg.norm(np.ptp(verts[tris.ravel()], axis=0))
    rng = np.random.default_rng(3)
    used = np.unique(tris)
    pts = np.vstack([
        verts[rng.choice(used, 40)] + rng.normal(0, 0.002 * scale, (40, 3)),   # near the surface
        verts[rng.choice(used, 20)] * 1.6,                                       # far outside
        verts[rng.choice(used, 10)] * 0.3,                                       # deep inside
        verts[rng.choice(used, 10)],                                             # on a vertex: faces tie at 0
        0.5 * (verts[tris[:10, 0]] + verts[tris[:10, 1]]),                       # on an edge
        verts[rng.choice(used, 10)] * 1.02,                                      # off a vertex: faces tie
    ])
    q, f, d = spatial.MeshQuery(verts, tris).closest_points(pts)
    for k, p in enumerate(pts):
        bq, bf, bd = brute_closest(verts, tris, p)
        assert d[k] == bd and f[k] == bf and np.array_equal(q[k], bq), (k, d[k], bd, f[k], bf)


@pytest.mark.parametrize("mesh", ["skin", "uneven"])
@pytest.mark.parametrize("both_ways", [True, False])
@pytest.mark.parametrize("backend", ["numpy", "embree"])
def test_ray_hits_are_the_brute_force_ones(skin, mesh, both_ways, backend):
    verts, tris = skin if mesh == "skin" else uneven_mesh()
    scale = np.linalg.norm(np.ptp(verts[tris.ravel()], axis=0))
    rng = np.random.default_rng(4)
    used = np.unique(tris)
    n = 90
    o = verts[rng.choice(used, n)] + rng.normal(0, 0.01 * scale, (n, 3))
    d = rng.normal(size=(n, 3))
    d[:10] = np.eye(3)[rng.integers(0, 3, 10)] * rng.choice([-1, 1], (10, 1))   # along an axis: zero slopes
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    # reaches from a tenth of an edge to past the whole mesh: every shell of the search is used
    reach = scale * np.exp(rng.uniform(np.log(1e-3), np.log(2.0), n))
    hits = spatial.MeshQuery(verts, tris, backend=backend).ray_cast(o, d, reach, both_ways=both_ways)
    d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)     # to the bit as ray_cast has it
    shells = np.abs(hits.t[hits.hit]) / bvh.TriangleBVH(verts, tris).median_edge()
    assert (shells < 4).any() and (shells > 4).any()
    for k in range(n):
        t, f = brute_ray(verts, tris, o[k], d[k], -reach[k] if both_ways else 0.0, reach[k])
        assert hits.hit[k] == (t is not None), k
        if t is not None:
            assert hits.t[k] == t and hits.face[k] == f, (k, hits.t[k], t, hits.face[k], f)
            np.testing.assert_allclose(hits.bary[k] @ verts[tris[f]], hits.point[k], atol=1e-12 * scale)
        else:
            assert np.isnan(hits.t[k]) and np.all(np.isnan(hits.point[k]))


def test_a_far_hit_met_in_a_near_shell_waits_for_the_nearer_ones():
    """Shells: a large tilted triangle whose box holds the ray's start is met in the first shell, but
    its hit is far (t = 10); the nearest hit is a small triangle at t = -5, beyond the first shell and
    in another leaf (small triangles round it, off the ray, fill its leaf)."""
    rng = np.random.default_rng(9)
    bits = rng.uniform(-0.05, 0.05, (40, 3, 3)) + np.repeat(rng.uniform(0.3, 1, (40, 1, 3)) * [1, 1, 0], 3, 1)
    bits[20:] += [0, 0, -5]                                              # 20 near the start, 20 round z = -5
    big = np.array([[[-20.0, -20, -10], [20, -20, -10], [0, 20, 30]]])   # crosses the z axis at z = 10
    near = np.array([[[-0.05, -0.05, -5], [0.1, -0.05, -5], [-0.05, 0.1, -5]]])
    corners = np.vstack([bits, big, near])
    verts, tris = corners.reshape(-1, 3), np.arange(3 * len(corners)).reshape(-1, 3)
    tree = bvh.TriangleBVH(verts, tris)
    shell = 4 * tree.median_edge()
    _, slot = tree.ray_candidates(np.zeros((1, 3)), np.array([[0.0, 0, 1]]), np.array([-shell]), np.array([shell]))
    assert 40 in tree.face[slot] and 41 not in tree.face[slot]          # the far hit's face only
    h = spatial.MeshQuery(verts, tris).ray_cast([[0.0, 0, 0]], [[0.0, 0, 1]], 20.0)
    assert h.hit[0] and h.t[0] == pytest.approx(-5.0) and h.face[0] == 41


def test_rays_through_shared_edges_and_vertices(skin):
    """Rays through a shared vertex or edge: numpy answers as brute force with the rule (to the bit);
    Blender's BVH hits there too, at the same t up to float32, on one of the faces that tie; Embree
    too, at the same t up to float64 rounding (measured on its own face)."""
    verts, tris = skin
    normals = geometry.vertex_normals(verts, tris)
    rng = np.random.default_rng(6)
    k = rng.choice(len(tris), 30)
    at_vertex = verts[tris[k, 0]]
    at_edge = 0.5 * (verts[tris[k, 0]] + verts[tris[k, 1]])
    target = np.vstack([at_vertex, at_edge])
    d = np.vstack([normals[tris[k, 0]], normals[tris[k, 0]]])
    o = target + 0.003 * d
    unit = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)  # to the bit as ray_cast has it
    a, b, c = (verts[tris[:, j]] for j in range(3))
    numpy_hits = spatial.MeshQuery(verts, tris).ray_cast(o, d, 0.01)
    bvh_hits = spatial.MeshQuery(verts, tris, backend="bvh").ray_cast(o, d, 0.01)
    embree_hits = spatial.MeshQuery(verts, tris, backend="embree").ray_cast(o, d, 0.01)
    for j in range(len(o)):
        t, f = brute_ray(verts, tris, o[j], unit[j], -0.01, 0.01)
        assert numpy_hits.hit[j] and numpy_hits.t[j] == t and numpy_hits.face[j] == f, (j, numpy_hits.face[j], f)
        hit, tt, _, _ = spatial.ray_triangles(np.repeat(o[j][None], len(tris), 0), np.repeat(unit[j][None], len(tris), 0),
                                              a, b, c)
        tied = np.flatnonzero(hit & (np.abs(np.abs(tt) - abs(t)) < 1e-7))
        assert len(tied) >= 2 or j >= 30                 # through a vertex: several faces at once
        assert bvh_hits.hit[j] and abs(bvh_hits.t[j] - t) < 1e-6 and bvh_hits.face[j] in tied, (j, bvh_hits.face[j], tied)
        assert embree_hits.hit[j] and abs(embree_hits.t[j] - t) < 1e-15 and embree_hits.face[j] in tied


def test_closest_points_at_a_tie_follow_the_rule_on_numpy_and_are_a_tied_face_on_bvh(skin):
    """Points nearest a shared vertex or edge (a third of the points off a head's surface): numpy answers
    the rule's face (not whichever face a search meets first); Blender's BVH answers one of the tied
    faces, at the same distance up to float32."""
    verts, tris = skin
    normals = geometry.vertex_normals(verts, tris)
    rng = np.random.default_rng(7)
    v = rng.choice(np.unique(tris), 300)
    pts = verts[v] + 0.004 * normals[v] + rng.normal(0, 0.002, (300, 3))
    qn, fn, dn = spatial.MeshQuery(verts, tris).closest_points(pts)
    _, fb, db = spatial.MeshQuery(verts, tris, backend="bvh").closest_points(pts)
    _, bary = spatial.closest_on_triangles(pts, *(verts[tris[fn, k]] for k in range(3)))
    ties = (bary == 0).any(axis=1)
    assert ties.sum() > 30
    for k in np.flatnonzero(ties):
        bq, bf, bd = brute_closest(verts, tris, pts[k])
        assert fn[k] == bf and dn[k] == bd and np.array_equal(qn[k], bq)
    np.testing.assert_allclose(db, dn, atol=1e-7)                      # float32 inside
    on_bvh_face, _ = spatial.closest_on_triangles(pts, *(verts[tris[fb, k]] for k in range(3)))
    np.testing.assert_allclose(np.linalg.norm(on_bvh_face - pts, axis=1), dn, atol=1e-7)   # a tied face
    assert (fb != fn).sum() > 5                                        # Blender's choice at a tie is its own


@pytest.mark.parametrize("backend", ["numpy", "embree"])
def test_small_and_empty_inputs(backend):
    verts = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [5, 5, 5]])
    q = spatial.MeshQuery(verts, [[0, 1, 2]], backend=backend)
    p, f, d = q.closest_points([[0.2, 0.2, 1.0], [2.0, 0.0, 0.0]])
    np.testing.assert_allclose(p, [[0.2, 0.2, 0], [1, 0, 0]], atol=1e-15)
    assert list(f) == [0, 0] and np.allclose(d, [1.0, 1.0])
    h = q.ray_cast([[0.2, 0.2, 1.0], [0.2, 0.2, 1.0]], [[0, 0, -1], [0, 0, 1]], [2.0, 0.5], both_ways=False)
    assert list(h.hit) == [True, False] and h.t[0] == pytest.approx(1.0)
    h = q.ray_cast([[0.2, 0.2, 1.0]], [[0, 0, 1]], 2.0)                   # behind: t < 0 both ways
    assert h.hit[0] and h.t[0] == pytest.approx(-1.0)
    p, f, d = q.closest_points(np.zeros((0, 3)))
    assert p.shape == (0, 3) and len(f) == 0 and len(d) == 0
    assert len(q.ray_cast(np.zeros((0, 3)), np.zeros((0, 3)), 1.0).hit) == 0
    # a mesh with no triangles: nothing near, nothing hit (the tree was not built: a max of nothing)
    q = spatial.MeshQuery(verts, np.zeros((0, 3), int), backend=backend)
    p, f, d = q.closest_points([[0.2, 0.2, 1.0]])
    assert np.isnan(p).all() and np.isinf(d).all()
    assert not q.ray_cast([[0.2, 0.2, 1.0]], [[0, 0, -1]], 2.0).hit.any()


def test_a_hit_the_exact_test_takes_just_off_an_edge_is_found():
    """The ray test accepts barycentrics down to -RAY_TOL (no leak between faces); the tree's boxes
    are that much wider, so a ray 5e-10 off an edge of a 1 m triangle, on the side of its box, hits."""
    verts = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    o, d = np.array([[0.5, -5e-10, 1.0], [0.5, -5e-9, 1.0]]), np.array([[0.0, 0, -1]] * 2)
    hit, _, _, _ = spatial.ray_triangles(o, d, *(verts[[k, k]] for k in range(3)))
    assert list(hit) == [True, False]
    h = spatial.MeshQuery(verts, [[0, 1, 2]]).ray_cast(o, d, 2.0)     # (Blender's BVH has its own slack)
    assert list(h.hit) == [True, False]
    assert h.t[0] == pytest.approx(1.0)


def test_embree_s_hit_is_measured_in_float64_and_the_tree_answers_where_that_disagrees(skin, monkeypatch):
    """The embree backend: a skin's rays onto a scan-like surface (the skin pushed out 1 mm) give the
    numpy tree's t, face, point and barycentrics to the bit; a hit Embree finds just past the range's
    end (float32; it looks a little farther) is left to the float64 range test, and the numpy tree then
    answers that ray (here: no hit), as it does for a face the float64 test rejects."""
    verts, tris = skin
    normals = geometry.vertex_normals(verts, tris)
    scan = verts + 0.001 * normals
    rng = np.random.default_rng(11)
    d = normals + rng.normal(0, 0.2, normals.shape)
    exact = spatial.MeshQuery(scan, tris).ray_cast(verts, d, 0.01)
    q = spatial.MeshQuery(scan, tris, backend="embree")
    asked = []
    monkeypatch.setattr(q.tree, "ray_nearest", lambda *a, f=q.tree.ray_nearest: asked.append(len(a[0])) or f(*a))
    fast = q.ray_cast(verts, d, 0.01)
    assert exact.hit.mean() > 0.95
    for name in ("hit", "face"):
        np.testing.assert_array_equal(getattr(fast, name), getattr(exact, name))
    for name in ("t", "point", "bary"):
        np.testing.assert_array_equal(getattr(fast, name), getattr(exact, name))
    # a triangle at t = 1 (a 1 m triangle): reach 1 - 1e-12 misses, 1 hits, both ways or one
    tri = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    q = spatial.MeshQuery(tri, [[0, 1, 2]], backend="embree")
    asked.clear()
    monkeypatch.setattr(q.tree, "ray_nearest", lambda *a, f=q.tree.ray_nearest: asked.append(len(a[0])) or f(*a))
    o, down = np.array([[0.2, 0.2, 1.0]] * 2), np.array([[0.0, 0, -1]] * 2)
    for both in (True, False):
        h = q.ray_cast(o, down, [1.0 - 1e-12, 1.0], both_ways=both)
        assert list(h.hit) == [False, True] and h.t[1] == 1.0
    assert asked == [1, 1]                      # the ray whose hit lay past its end, each time


def test_the_embree_backend_is_asked_for_and_refused_by_name(monkeypatch):
    """"embree" is the caller's choice; an unknown name is refused with the names there are."""
    with pytest.raises(ValueError, match="numpy, bvh or embree"):
        spatial.MeshQuery(np.eye(3), [[0, 1, 2]], backend="embre")
    q = spatial.MeshQuery(np.eye(3), [[0, 1, 2]], backend="embree")
    assert q.backend == "embree" and q.rays.scene is not None


def test_embree_is_not_used_inside_a_blender_executable(monkeypatch):
    """A Blender executable's own Embree takes embreex's calls (a segfault in Debian's Blender 3.4:
    test_blender_binary); the bpy module, which has no executable, keeps it."""
    import types

    from headadapt_addon import batch
    from headadapt_addon.core.mesh import embree

    pytest.importorskip("embreex")
    fake = types.SimpleNamespace(app=types.SimpleNamespace(binary_path="/usr/bin/blender"))
    monkeypatch.setitem(__import__("sys").modules, "bpy", fake)
    assert not embree.available() and batch.spatial_backend() == "numpy"
    with pytest.raises(RuntimeError, match="inside a Blender executable"):
        spatial.MeshQuery(np.eye(3), [[0, 1, 2]], backend="embree")
    fake.app.binary_path = ""                 # the bpy module
    assert embree.available() and batch.spatial_backend() == "embree"


def test_large_query_sets_are_walked_in_chunks(skin, monkeypatch):
    verts, tris = skin
    q = spatial.MeshQuery(verts, tris)
    rng = np.random.default_rng(8)
    pts = verts[rng.integers(0, len(verts), 500)] + rng.normal(0, 0.003, (500, 3))
    dirs = rng.normal(size=(500, 3))
    whole = q.closest_points(pts), q.ray_cast(pts, dirs, 0.01)
    monkeypatch.setattr(spatial, "CHUNK", 37)
    chunked = q.closest_points(pts), q.ray_cast(pts, dirs, 0.01)
    for a, b in zip(whole[0], chunked[0]):
        np.testing.assert_array_equal(a, b)
    for name in ("hit", "t", "face", "point", "bary"):
        np.testing.assert_array_equal(getattr(whole[1], name), getattr(chunked[1], name))
