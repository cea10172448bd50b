"""Scan and landmark files: OBJ, PLY (ascii/binary), STL (ascii/binary); landmark JSON and MeshLab .pp.

Everything is read as given (the file's own frame and unit); errors name the file and the problem.
Writers are atomic: they write a temporary file beside the target and rename it.
"""

import io
import json
import os
import pathlib
import re
import tempfile
import xml.etree.ElementTree as ET

import numpy as np

from .exceptions import FileFormatError, LandmarkError
from . import mpeg4


# ---------------------------------------------------------------------------------------------
# atomic writes
# ---------------------------------------------------------------------------------------------
def write_atomic(path, data):
    """Write bytes or str to path atomically (temp file in the same folder, then rename)."""
    path = pathlib.Path(path)
    if isinstance(data, str):
        data = data.encode()
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    except OSError as exc:
        raise FileFormatError(f"cannot write {path}: {exc.strerror or exc}") from exc
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        pathlib.Path(tmp).unlink(missing_ok=True)
        raise
    return path


# ---------------------------------------------------------------------------------------------
# meshes
# ---------------------------------------------------------------------------------------------
def _fan(polys):
    """Triangles (k,3) from a list of polygons (index lists), fan-triangulated, vectorised per size."""
    out = []
    by_size = {}
    for p in polys:
        by_size.setdefault(len(p), []).append(p)
    for size, group in by_size.items():
        if size < 3:
            continue
        arr = np.asarray(group, dtype=np.int64)
        for k in range(1, size - 1):
            out.append(arr[:, [0, k, k + 1]])
    return np.concatenate(out) if out else np.zeros((0, 3), np.int64)


def _read_obj(path):
    text = path.read_text(errors="replace")
    v_lines = re.findall(r"^v[ \t]+(.+)$", text, flags=re.M)
    f_lines = re.findall(r"^f[ \t]+(.+)$", text, flags=re.M)
    try:
        rows = [line.split()[:3] for line in v_lines]
        verts = np.asarray(rows, dtype=np.float64).reshape(-1, 3)
    except ValueError as exc:
        raise FileFormatError(f"{path}: a vertex line is not three numbers ({exc})") from exc
    n = len(verts)
    polys = []
    try:
        for line in f_lines:
            idx = [int(tok.split("/")[0]) for tok in line.split()]
            polys.append([i - 1 if i > 0 else n + i for i in idx])
    except ValueError as exc:
        raise FileFormatError(f"{path}: a face line has a non-integer index ({exc})") from exc
    return verts, _fan(polys)


_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}


def _read_ply(path):
    raw = path.read_bytes()
    end = raw.find(b"end_header")
    if not raw.startswith(b"ply") or end < 0:
        raise FileFormatError(f"{path}: not a PLY file (no 'ply' magic or no end_header)")
    header = raw[:end].decode("ascii", errors="replace").splitlines()
    body_start = raw.index(b"\n", end) + 1
    fmt, elements = None, []
    for line in header:
        tok = line.split()
        if not tok:
            continue
        if tok[0] == "format":
            fmt = tok[1]
        elif tok[0] == "element":
            elements.append({"name": tok[1], "count": int(tok[2]), "props": []})
        elif tok[0] == "property" and elements:
            if tok[1] == "list":
                elements[-1]["props"].append((tok[4], "list", _PLY_TYPES[tok[2]], _PLY_TYPES[tok[3]]))
            else:
                elements[-1]["props"].append((tok[2], _PLY_TYPES[tok[1]], None, None))
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise FileFormatError(f"{path}: unknown PLY format {fmt!r}")
    verts, tris = None, np.zeros((0, 3), np.int64)
    if fmt == "ascii":
        tokens = raw[body_start:].split()
        pos = 0
        for el in elements:
            if all(p[1] != "list" for p in el["props"]):
                k = len(el["props"]) * el["count"]
                table = np.asarray(tokens[pos:pos + k], dtype=np.float64).reshape(el["count"], -1)
                pos += k
                if el["name"] == "vertex":
                    names = [p[0] for p in el["props"]]
                    verts = table[:, [names.index(c) for c in "xyz"]]
            else:
                polys = []
                for _ in range(el["count"]):
                    row = []
                    for name, kind, _c, _i in el["props"]:
                        if kind == "list":
                            m = int(tokens[pos]); vals = [int(t) for t in tokens[pos + 1:pos + 1 + m]]
                            pos += 1 + m
                            if name in ("vertex_indices", "vertex_index"):
                                row = vals
                        else:
                            pos += 1
                    polys.append(row)
                if el["name"] == "face":
                    tris = _fan(polys)
        return verts, tris
    order = "<" if fmt == "binary_little_endian" else ">"
    offset = body_start
    for el in elements:
        if all(p[1] != "list" for p in el["props"]):
            dt = np.dtype([(p[0], order + p[1]) for p in el["props"]])
            table = np.frombuffer(raw, dtype=dt, count=el["count"], offset=offset)
            offset += dt.itemsize * el["count"]
            if el["name"] == "vertex":
                verts = np.stack([table[c].astype(np.float64) for c in "xyz"], axis=1)
            continue
        props = el["props"]
        simple = (len(props) == 1 and props[0][1] == "list")
        if simple:
            ct, it = np.dtype(order + props[0][2]), np.dtype(order + props[0][3])
            first = np.frombuffer(raw, ct, 1, offset)[0] if el["count"] else 3
            row = np.dtype([("n", ct), ("i", it, (int(first),))])
            table = np.frombuffer(raw, row, count=el["count"], offset=offset) if el["count"] else None
            if table is not None and np.all(table["n"] == first):   # constant polygon size: vectorised
                offset += row.itemsize * el["count"]
                if el["name"] == "face":
                    tris = _fan([]) if first < 3 else np.concatenate(
                        [table["i"][:, [0, k, k + 1]] for k in range(1, int(first) - 1)]).astype(np.int64)
                continue
        polys = []
        for _ in range(el["count"]):
            row = []
            for name, kind, ct, it in props:
                if kind == "list":
                    ctd, itd = np.dtype(order + ct), np.dtype(order + it)
                    m = int(np.frombuffer(raw, ctd, 1, offset)[0]); offset += ctd.itemsize
                    vals = np.frombuffer(raw, itd, m, offset).tolist(); offset += itd.itemsize * m
                    if name in ("vertex_indices", "vertex_index"):
                        row = vals
                else:
                    offset += np.dtype(kind).itemsize
            polys.append(row)
        if el["name"] == "face":
            tris = _fan(polys)
    return verts, tris


def _read_stl(path):
    raw = path.read_bytes()
    if len(raw) >= 84:
        n = int(np.frombuffer(raw, "<u4", 1, 80)[0])
        if 84 + 50 * n == len(raw):
            dt = np.dtype([("n", "<f4", 3), ("v", "<f4", (3, 3)), ("a", "<u2")])
            corners = np.frombuffer(raw, dt, n, 84)["v"].reshape(-1, 3).astype(np.float64)
            return _weld(corners)
    text = raw.decode("ascii", errors="replace")
    if not text.lstrip().startswith("solid"):
        raise FileFormatError(f"{path}: neither binary nor ascii STL")
    nums = re.findall(r"vertex\s+(\S+)\s+(\S+)\s+(\S+)", text)
    return _weld(np.asarray(nums, dtype=np.float64).reshape(-1, 3))


def _weld(corners):
    verts, inverse = np.unique(corners, axis=0, return_inverse=True)
    return verts, inverse.reshape(-1, 3).astype(np.int64)


def read_mesh(path):
    """Read a scan (OBJ, PLY or STL) as (verts (n,3) float64, tris (k,3) int64), the file's frame and unit."""
    path = pathlib.Path(path)
    suffix = path.suffix.lower()
    readers = {".obj": _read_obj, ".ply": _read_ply, ".stl": _read_stl}
    if suffix not in readers:
        raise FileFormatError(f"{path}: unsupported scan format {suffix!r} (use OBJ, PLY or STL)")
    if not path.is_file():
        raise FileFormatError(f"{path}: no such file")
    try:
        verts, tris = readers[suffix](path)
    except FileFormatError:
        raise
    except (ValueError, IndexError, KeyError, UnicodeDecodeError, OSError) as exc:
        raise FileFormatError(f"{path}: cannot read as {suffix[1:].upper()} ({exc})") from exc
    if verts is None or len(verts) == 0:
        raise FileFormatError(f"{path}: the file has no vertices")
    if len(tris) == 0:
        raise FileFormatError(f"{path}: the file has no faces (a point cloud is not a scan surface)")
    if tris.min() < 0 or tris.max() >= len(verts):
        raise FileFormatError(f"{path}: a face refers to a vertex that does not exist")
    return verts, tris


def write_obj(path, verts, tris, header="HeadAdapt"):
    """Write a triangle mesh as OBJ (atomic); coordinates as given."""
    buf = io.StringIO()
    buf.write(f"# {header}\n# {len(verts)} vertices, {len(tris)} triangles\n")
    np.savetxt(buf, np.asarray(verts, dtype=np.float64), fmt="v %.9g %.9g %.9g")
    np.savetxt(buf, np.asarray(tris, dtype=np.int64) + 1, fmt="f %d %d %d")
    return write_atomic(path, buf.getvalue())


# ---------------------------------------------------------------------------------------------
# landmarks
# ---------------------------------------------------------------------------------------------
def read_landmarks(path):
    """Read FDP landmarks {id: (3,) float} from JSON {"points": {...}} or a MeshLab .pp file (file's frame).

    Unknown names raise LandmarkError naming them; a "template" field (JSON) is returned as
    ``read_landmarks.last_template`` for checks against the template in use.
    """
    path = pathlib.Path(path)
    if not path.is_file():
        raise FileFormatError(f"{path}: no such landmark file")
    try:
        if path.suffix.lower() == ".pp":
            root = ET.fromstring(path.read_text())
            points = {}
            for el in root.iter("point"):
                if el.get("active", "1") in ("0", "false"):
                    continue
                points[el.get("name")] = [float(el.get(c)) for c in "xyz"]
            meta = {}
        else:
            data = json.loads(path.read_text())
            if not isinstance(data, dict) or not isinstance(data.get("points"), dict):
                raise FileFormatError(f'{path}: expected a JSON object {{"points": {{"3.7": [x, y, z], ...}}}}')
            points, meta = data["points"], {k: v for k, v in data.items() if k != "points"}
    except (ET.ParseError, json.JSONDecodeError, TypeError, ValueError) as exc:
        if isinstance(exc, FileFormatError):
            raise
        raise FileFormatError(f"{path}: cannot read landmarks ({exc})") from exc
    out = {}
    for name, xyz in points.items():
        try:
            mpeg4.check_fdp_name(str(name))
        except LandmarkError as exc:
            raise LandmarkError(f"{path}: {exc}") from None
        arr = np.asarray(xyz, dtype=np.float64) if isinstance(xyz, (list, tuple)) else None
        if arr is None or arr.shape != (3,):
            raise LandmarkError(f"{path}: FDP {name} must be three numbers [x, y, z], got {xyz!r}")
        out[str(name)] = arr
    read_landmarks.last_meta = meta
    return dict(sorted(out.items(), key=lambda kv: mpeg4.fdp_sort_key(kv[0])))


read_landmarks.last_meta = {}


def landmarks_json(points, **meta):
    """JSON text of landmarks {"points": {id: [x, y, z]}, **meta}, FDPs in the standard's order."""
    ordered = {k: [float(c) for c in points[k]] for k in sorted(points, key=mpeg4.fdp_sort_key)}
    return json.dumps({"points": ordered, **meta}, indent=1)


def write_landmarks(path, points, **meta):
    """Write landmarks as JSON (.json) or MeshLab picked points (.pp), atomically."""
    path = pathlib.Path(path)
    if path.suffix.lower() == ".pp":
        root = ET.Element("PickedPoints")
        ET.SubElement(root, "DocumentData")
        for k in sorted(points, key=mpeg4.fdp_sort_key):
            x, y, z = (repr(float(c)) for c in points[k])
            ET.SubElement(root, "point", name=k, active="1", x=x, y=y, z=z)
        text = "<!DOCTYPE PickedPoints>\n" + ET.tostring(root, encoding="unicode") + "\n"
        return write_atomic(path, text)
    return write_atomic(path, landmarks_json(points, **meta))
