"""Scan and landmark files: OBJ/PLY/STL read the template skin back exactly; landmarks round-trip;
malformed files end in one FileFormatError naming the file; writes are atomic."""
import errno
import os
import subprocess
import sys

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


def test_a_textured_binary_ply_reads_its_triangles_in_one_step(tmp_path, skin, monkeypatch):
    """A scanner's textured PLY carries each face's texture coordinates as a list beside its corners
    (two numbers a corner): read in one memory-mapped step like an untextured one, not row by row (the
    65k-triangle sample: 0.9 s against 0.01; a 2M-triangle scan, tens of seconds)."""
    import plyfile

    v, t, _ = skin
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(v)}\nproperty float x\n"
              f"property float y\nproperty float z\nelement face {len(t)}\n"
              "property list uchar int vertex_indices\nproperty list uchar float texcoord\nend_header\n").encode()
    ft = np.zeros(len(t), dtype=[("n", "u1"), ("i", "<i4", 3), ("m", "u1"), ("uv", "<f4", 6)])
    ft["n"], ft["i"], ft["m"], ft["uv"] = 3, t, 6, 0.5
    (tmp_path / "s.ply").write_bytes(header + v.astype("<f4").tobytes() + ft.tobytes())
    reads = []
    real = plyfile.PlyData.read
    monkeypatch.setattr(plyfile.PlyData, "read", staticmethod(lambda *a, **k: reads.append(k) or real(*a, **k)))
    v2, t2 = meshio.read_mesh(tmp_path / "s.ply")
    np.testing.assert_array_equal(t2, t)
    np.testing.assert_allclose(v2, v.astype(np.float32), rtol=1e-6)
    assert len(reads) == 1 and "known_list_len" in reads[0]


def test_obj_polygons_slashes_and_negative_indices(tmp_path):
    (tmp_path / "q.obj").write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nf 1/1/1 2/1/1 3/1/1 4/1/1\nf -4 -2 -1\n")
    v, t = meshio.read_mesh(tmp_path / "q.obj")
    # the quad as two triangles (either diagonal), the negative indices counted from the end; winding kept
    rolled = np.array([np.roll(tri, -int(np.argmin(tri))) for tri in t])
    assert {tuple(r) for r in rolled[:2]} in ({(0, 1, 2), (0, 2, 3)}, {(0, 1, 3), (1, 2, 3)})
    np.testing.assert_array_equal(rolled[2], [0, 2, 3])


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
    # a scanner's point-cloud PLY, with no face element or one of none: "cannot reshape array" before
    head = b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
    for name, faces in (("cloud.ply", b""), ("cloud0.ply", b"element face 0\nproperty list uchar int vertex_indices\n")):
        (tmp_path / name).write_bytes(head + faces + b"end_header\n0 0 0\n1 0 0\n0 1 0\n")
        with pytest.raises(FileFormatError, match=f"{name}: the file has no faces \\(a point cloud is not a scan"):
            meshio.read_mesh(tmp_path / name)
    (tmp_path / "bad.ply").write_bytes(b"not a ply at all")
    with pytest.raises(FileFormatError, match="bad.ply"):
        meshio.read_mesh(tmp_path / "bad.ply")
    (tmp_path / "oob.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n")
    with pytest.raises(FileFormatError, match="does not exist"):
        meshio.read_mesh(tmp_path / "oob.obj")


TRI_PLY = ("ply\nformat {fmt} 1.0\nelement vertex {nv}\nproperty float x\nproperty float y\nproperty float z\n"
           "element face {nf}\nproperty list uchar int vertex_indices\nend_header\n")


@pytest.mark.parametrize("name, content, where", [
    # errors raised inside the libraries (plyfile, trimesh, numpy), not by HeadAdapt's own checks
    ("short.ply", TRI_PLY.format(fmt="binary_little_endian", nv=3, nf=1).encode() + b"\0" * 40,
     "cannot read as PLY"),
    ("word.ply", (TRI_PLY.format(fmt="ascii", nv=3, nf=1) + "0 0 0\n1 0 0\n0 1 zero\n3 0 1 2\n").encode(),
     "cannot read as PLY"),
    ("facesonly.obj", b"f 1 2 3\n", "cannot read as OBJ"),
    ("twocoords.obj", b"v 0 0\nv 1 0\nv 0 1\nf 1 2 3\n", "does not exist"),
    ("badfacet.stl", b"solid s\nfacet normal 0 0 0\nouter loop\nvertex 0 0 0\nvertex 1 0 0\nendloop\n"
                     b"endfacet\nendsolid s\n", "cannot read as STL"),
    # HeadAdapt's own checks, before and after the library
    ("huge.ply", TRI_PLY.format(fmt="ascii", nv=10 ** 12, nf=1).encode() + b"0 0 0\n", "over the limit"),
    ("counts.ply", TRI_PLY.format(fmt="binary_little_endian", nv=1000, nf=1000).encode() + b"\0" * 100,
     "the file holds only 100 bytes"),
    ("negative.ply", TRI_PLY.format(fmt="ascii", nv=-3, nf=1).encode(), "declares -3"),
    ("nan.obj", b"v 0 0 nan\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", "vertex 1 is not finite"),
    ("zero.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n", "line 4: face index 0"),
    ("zero2.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nf 1/1 -0/1 2/1\n", "line 5: face index 0"),
    ("empty.stl", b"", "empty"),
    ("garbage.stl", b"\x00" * 90, "not an STL file"),
])
def test_malformed_scans_end_in_one_error_naming_the_file(tmp_path, name, content, where):
    (tmp_path / name).write_bytes(content)
    with pytest.raises(FileFormatError) as err:
        meshio.read_mesh(tmp_path / name)
    assert type(err.value) is FileFormatError                    # not a library's exception passing through
    assert str(err.value).startswith(str(tmp_path / name)) and where in str(err.value), str(err.value)
    assert "\n" not in str(err.value)


def test_blender_binary_ply_of_quads_and_triangles_reads(tmp_path, clean_scene):
    """Blender 5.0's own binary PLY export of a mixed quad/triangle mesh (a UV sphere: quads, and
    triangle fans at the poles) reads with every polygon fanned into triangles."""
    import bpy

    bpy.ops.mesh.primitive_uv_sphere_add(segments=16, ring_count=8)
    mesh = bpy.context.active_object.data
    sizes = sorted({len(p.vertices) for p in mesh.polygons})
    assert sizes == [3, 4]
    n_tris = sum(len(p.vertices) - 2 for p in mesh.polygons)
    for ascii_format in (False, True):
        path = tmp_path / f"sphere_{ascii_format}.ply"
        bpy.ops.wm.ply_export(filepath=str(path), ascii_format=ascii_format, export_uv=False, export_normals=False)
        assert path.read_bytes().startswith(b"ply\nformat " + (b"ascii" if ascii_format else b"binary_little_endian"))
        v, t = meshio.read_mesh(path)
        assert len(v) == len(mesh.vertices) and len(t) == n_tris
        np.testing.assert_allclose(np.linalg.norm(v, axis=1), 1.0, atol=1e-5)     # all on the unit sphere
        area = 0.5 * np.linalg.norm(np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]]), axis=1)
        assert area.min() > 0 and 0.9 * 4 * np.pi < area.sum() < 4 * np.pi
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


@pytest.mark.parametrize("text, suffix", [
    ('{"points": {"3.7": [0, 0, 0], "3.8": [1, 0, 0], "3.7": [2, 0, 0]}}', ".json"),
    ('{"points": {"3.7": [0, 0, 0], "3.7 ": [2, 0, 0]}}', ".json"),
    ('<PickedPoints><point name="3.7" x="0" y="0" z="0"/><point name="3.7" x="2" y="0" z="0"/></PickedPoints>', ".pp"),
])
def test_an_fdp_given_twice_is_named_not_dropped(tmp_path, text, suffix):
    """Two points labelled 3.7 (one of them meant 3.8): JSON and the dict of a .pp kept the last and
    dropped the other silently."""
    (tmp_path / f"t{suffix}").write_text(text)
    with pytest.raises(LandmarkError, match=r"FDP 3\.7 is given twice"):
        meshio.read_landmarks(tmp_path / f"t{suffix}")


def test_a_mesh_given_as_the_landmarks_is_named_as_one(tmp_path):
    """--scan and --landmarks swapped: the scan's PLY read as landmarks said only that 1.2 MB is over
    the landmark file's limit (a small one: that it is not JSON)."""
    (tmp_path / "scan.ply").write_bytes(b"ply\nformat ascii 1.0\nend_header\n")
    with pytest.raises(FileFormatError, match=r"scan\.ply: a mesh, not a landmark file .* swapped\?"):
        meshio.read_landmarks(tmp_path / "scan.ply")


def test_names_read_without_the_spaces_typed_round_them(tmp_path):
    (tmp_path / "l.pp").write_text('<PickedPoints><point name="3.7 " x="0" y="0" z="1"/></PickedPoints>')
    assert list(meshio.read_landmarks(tmp_path / "l.pp")) == ["3.7"]


BOMB = ('<?xml version="1.0"?>\n<!DOCTYPE PickedPoints [\n <!ENTITY a "aaaaaaaaaa">\n'
        + "".join(f' <!ENTITY {c} "{("&" + p + ";") * 10}">\n' for p, c in zip("abcdefgh", "bcdefghi"))
        + ']>\n<PickedPoints><point name="&i;" x="0" y="0" z="0"/></PickedPoints>\n')


@pytest.mark.parametrize("name, content, where", [
    ("nan.json", b'{"points": {"3.12": [0, 1, 0], "3.7": [NaN, 0, 0]}}', "FDP 3.7 must be three finite numbers [x, y, z], got [nan, 0, 0]"),
    ("minf.json", b'{"points": {"3.7": [0, -Infinity, 0]}}', "FDP 3.7 must be three finite numbers [x, y, z], got [0, -inf, 0]"),
    ("inf.json", b'{"points": {"3.7": [1e999, 0, 0]}}', "FDP 3.7 must be three finite numbers"),
    ("bigint.json", b'{"points": {"3.7": [1' + b"0" * 400 + b', 0, 0]}}', "FDP 3.7 must be three finite"),
    ("longint.json", b'{"points": {"3.7": [1' + b"0" * 5000 + b', 0, 0]}}', "cannot read landmarks"),
    ("bool.json", b'{"points": {"3.7": [true, 0, 0]}}', "FDP 3.7 must be three finite numbers"),
    ("deep.json", b"[" * 100_000 + b"]" * 100_000, "nested too deep"),
    ("list.json", b"[1, 2, 3]", "expected a JSON object"),
    ("markers.json", b'{"points": {"3.7": [0, 0, 0]}, "markers": {"m": [0, "x", 0]}}', "marker m must be three"),
    ("latin1.json", '{"points": {"3.7": [0, 0, 0]}, "who": "Ren\u00e9"}'.encode("latin-1"), "not UTF-8"),
    ("empty.json", b"", "empty"),
    ("bomb.pp", BOMB.encode(), "entity declarations are not allowed"),
    ("nan.pp", b'<PickedPoints><point name="3.7" x="nan" y="0" z="0"/></PickedPoints>', "FDP 3.7 must be three"),
    ("noxyz.pp", b'<PickedPoints><point name="3.7" x="1"/></PickedPoints>', "needs numbers x, y and z"),
    ("broken.pp", b"<PickedPoints><point", "cannot read landmarks"),
])
def test_malformed_landmark_files_end_in_one_error_naming_the_file(tmp_path, name, content, where):
    (tmp_path / name).write_bytes(content)
    with pytest.raises((FileFormatError, LandmarkError)) as err:
        meshio.read_landmarks(tmp_path / name)
    assert str(err.value).startswith(str(tmp_path / name)) and where in str(err.value), str(err.value)


def test_atomic_write_keeps_the_old_file_when_the_rename_fails(tmp_path, monkeypatch):
    target = tmp_path / "out" / "a.obj"
    meshio.write_atomic(target, "old")
    assert target.read_text() == "old" and [p.name for p in target.parent.iterdir()] == ["a.obj"]

    def no_space(src, dst):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(meshio.os, "replace", no_space)
    with pytest.raises(FileFormatError, match=f"cannot write {target}: No space left on device"):
        meshio.write_atomic(target, "new " * 1000)
    # the write went to a temporary file: the target is untouched and the temporary file removed
    assert target.read_text() == "old" and [p.name for p in target.parent.iterdir()] == ["a.obj"]


def test_atomic_write_on_a_full_disk_names_the_file_and_leaves_nothing(tmp_path):
    """A file-size limit stands in for a full disk: the write itself fails, in a child process."""
    target = tmp_path / "a.obj"
    target.write_text("old")
    code = ("import resource, signal, sys\n"
            "from headadapt_addon.core import meshio\n"
            "from headadapt_addon.core.exceptions import FileFormatError\n"
            "signal.signal(signal.SIGXFSZ, signal.SIG_IGN)\n"
            "resource.setrlimit(resource.RLIMIT_FSIZE, (4096, resource.RLIM_INFINITY))\n"
            "try:\n"
            f"    meshio.write_atomic({str(target)!r}, 'x' * 100_000)\n"
            "except FileFormatError as exc:\n"
            "    print(exc)\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert proc.stdout.strip() == f"cannot write {target}: File too large", proc.stdout + proc.stderr
    assert target.read_text() == "old" and [p.name for p in tmp_path.iterdir()] == ["a.obj"]


def test_atomic_write_into_a_file_names_it(tmp_path):
    blocked = tmp_path / "file"
    blocked.write_text("")
    with pytest.raises(FileFormatError, match="cannot write"):
        meshio.write_atomic(blocked / "sub" / "a.obj", "x")


@pytest.mark.parametrize("module, name", [("plyfile", "scan.ply"), ("trimesh", "scan.obj")])
def test_a_missing_reader_library_is_one_error_saying_how_to_get_it(tmp_path, monkeypatch, module, name):
    """A Blender without the extension (which bundles plyfile and trimesh) running batch.py."""
    (tmp_path / name).write_bytes(b"ply\nformat ascii 1.0\nend_header\n" if name.endswith("ply") else b"v 0 0 0\n")
    for loaded in [m for m in sys.modules if m == module or m.startswith(module + ".")]:
        monkeypatch.delitem(sys.modules, loaded)
    monkeypatch.setitem(sys.modules, module, None)          # import fails
    with pytest.raises(FileFormatError, match=f"needs the Python package {module}, missing in this Python"):
        meshio.read_mesh(tmp_path / name)
