"""Scan and landmark files: OBJ/PLY/STL read the template skin back exactly; landmarks round-trip."""
import numpy as np
import pytest

from headadapt_addon.core import meshio
from headadapt_addon.core.exceptions import FileFormatError, LandmarkError
from headadapt_addon.core.template import load_template


@pytest.fixture(scope="module")
def skin():
    tpl = load_template()
    return tpl.skin.verts * 1000.0, tpl.skin.tris, tpl.fdp_points()


def _same_surface(v1, t1, v2, t2, tol):
    tri1 = np.sort(np.round(v1[t1] / tol).astype(np.int64).reshape(len(t1), -1), axis=0)
    tri2 = np.sort(np.round(v2[t2] / tol).astype(np.int64).reshape(len(t2), -1), axis=0)
    return len(t1) == len(t2) and np.array_equal(np.sort(tri1, axis=None), np.sort(tri2, axis=None))


def test_obj_round_trip(tmp_path, skin):
    v, t, _ = skin
    meshio.write_obj(tmp_path / "s.obj", v, t)
    v2, t2 = meshio.read_mesh(tmp_path / "s.obj")
    np.testing.assert_allclose(v2, v, rtol=1e-8)
    np.testing.assert_array_equal(t2, t)


def test_obj_polygons_slashes_and_negative_indices(tmp_path):
    (tmp_path / "q.obj").write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nf 1/1/1 2/1/1 3/1/1 4/1/1\nf -4 -2 -1\n")
    v, t = meshio.read_mesh(tmp_path / "q.obj")
    np.testing.assert_array_equal(t, [[0, 1, 2], [0, 2, 3], [0, 2, 3]])


@pytest.mark.parametrize("fmt", ["binary_little_endian", "binary_big_endian", "ascii"])
def test_ply_reads_binary_and_ascii(tmp_path, skin, fmt):
    v, t, _ = skin
    order = {"binary_little_endian": "<", "binary_big_endian": ">"}.get(fmt)
    header = (f"ply\nformat {fmt} 1.0\ncomment test\nelement vertex {len(v)}\nproperty float x\n"
              f"property float y\nproperty float z\nproperty uchar red\nelement face {len(t)}\n"
              "property list uchar int vertex_indices\nend_header\n").encode()
    if order:
        vt = np.zeros(len(v), dtype=[("p", order + "f4", 3), ("r", "u1")])
        vt["p"] = v
        ft = np.zeros(len(t), dtype=[("n", "u1"), ("i", order + "i4", 3)])
        ft["n"], ft["i"] = 3, t
        body = vt.tobytes() + ft.tobytes()
    else:
        body = ("".join(f"{a:.7g} {b:.7g} {c:.7g} 7\n" for a, b, c in v.astype(np.float32))
                + "".join(f"3 {a} {b} {c}\n" for a, b, c in t)).encode()
    (tmp_path / "s.ply").write_bytes(header + body)
    v2, t2 = meshio.read_mesh(tmp_path / "s.ply")
    np.testing.assert_allclose(v2, v.astype(np.float32), rtol=1e-6)
    np.testing.assert_array_equal(t2, t)


def test_stl_binary_and_ascii_weld_to_the_same_surface(tmp_path, skin):
    v, t, _ = skin
    v32 = v.astype(np.float32).astype(np.float64)
    rec = np.zeros(len(t), dtype=[("n", "<f4", 3), ("v", "<f4", (3, 3)), ("a", "<u2")])
    rec["v"] = v32[t]
    (tmp_path / "b.stl").write_bytes(b"\0" * 80 + np.uint32(len(t)).tobytes() + rec.tobytes())
    facets = "".join("facet normal 0 0 0\nouter loop\n" + "".join(f"vertex {x!r} {y!r} {z!r}\n" for x, y, z in tri)
                     + "endloop\nendfacet\n" for tri in v32[t].tolist())
    (tmp_path / "a.stl").write_text(f"solid s\n{facets}endsolid s\n")
    for name in ("b.stl", "a.stl"):
        v2, t2 = meshio.read_mesh(tmp_path / name)
        assert len(v2) == len(np.unique(v32, axis=0))
        assert _same_surface(v32, t, v2, t2, 1e-4), name


def test_bad_scan_files_name_the_file_and_problem(tmp_path):
    with pytest.raises(FileFormatError, match="no such file"):
        meshio.read_mesh(tmp_path / "missing.obj")
    (tmp_path / "x.fbx").write_text("")
    with pytest.raises(FileFormatError, match="unsupported scan format"):
        meshio.read_mesh(tmp_path / "x.fbx")
    (tmp_path / "pts.obj").write_text("v 0 0 0\nv 1 0 0\n")
    with pytest.raises(FileFormatError, match="pts.obj.*no faces"):
        meshio.read_mesh(tmp_path / "pts.obj")
    (tmp_path / "bad.ply").write_bytes(b"not a ply at all")
    with pytest.raises(FileFormatError, match="bad.ply"):
        meshio.read_mesh(tmp_path / "bad.ply")
    (tmp_path / "oob.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n")
    with pytest.raises(FileFormatError, match="does not exist"):
        meshio.read_mesh(tmp_path / "oob.obj")


@pytest.mark.parametrize("suffix", [".json", ".pp"])
def test_landmarks_round_trip_exactly(tmp_path, skin, suffix):
    _, _, fdps = skin
    points = {k: p * 1000.0 + np.pi for k, p in fdps.items()}
    meshio.write_landmarks(tmp_path / f"l{suffix}", points)
    back = meshio.read_landmarks(tmp_path / f"l{suffix}")
    assert list(back) == list(points)
    for k in points:
        assert np.array_equal(back[k], points[k]), k


def test_bad_landmark_files_are_named(tmp_path):
    (tmp_path / "u.json").write_text('{"points": {"3.15": [0, 0, 0]}}')
    with pytest.raises(LandmarkError, match="3.15"):
        meshio.read_landmarks(tmp_path / "u.json")
    (tmp_path / "s.json").write_text('{"points": {"3.7": [0, 0]}}')
    with pytest.raises(LandmarkError, match="3.7"):
        meshio.read_landmarks(tmp_path / "s.json")
    (tmp_path / "b.json").write_text('{"points": ')
    with pytest.raises(FileFormatError, match="b.json"):
        meshio.read_landmarks(tmp_path / "b.json")


def test_atomic_write_leaves_no_partial_file(tmp_path):
    target = tmp_path / "out" / "a.obj"
    meshio.write_atomic(target, "x")
    assert target.read_text() == "x" and [p.name for p in target.parent.iterdir()] == ["a.obj"]
    blocked = tmp_path / "file"
    blocked.write_text("")
    with pytest.raises(FileFormatError, match="cannot write"):
        meshio.write_atomic(blocked / "sub" / "a.obj", "x")
