"""Scan readers: PLY through plyfile, OBJ and STL through trimesh, behind HeadAdapt's limits and checks.

Why these libraries: plyfile reads every PLY variant (ascii, both binary byte orders, any property
types, face lists of mixed length such as Blender's own binary export of quads and triangles);
trimesh's binary PLY reader cannot read mixed-length lists, but its OBJ and STL readers are vectorised
(its OBJ reader takes a face index 0 as the last vertex: such files are refused before it runs). Both
are pure Python on numpy and ship as wheels in the extension. Blender's importers would put bpy into
every batch worker and cannot be bounded per file.

Each file goes through the same steps: its size against the limit before it is read; the counts a
header declares against the bytes that follow before the parser sizes an array from them; the
library's parse; then HeadAdapt's own checks (finite coordinates, faces present, every index naming
a vertex, counts within limits). Every failure is one FileFormatError that names the file.
"""

from __future__ import annotations

import importlib
import io
import os
import pathlib
import re
import types

import numpy as np

from . import limits
from .exceptions import FileFormatError
from .mesh import geometry

# A PLY header longer than this is not a header (plyfile reads it one character at a time).
_PLY_HEADER_MAX_BYTES = 64 * 1024
# An OBJ face corner whose vertex index is 0 (OBJ counts from 1; trimesh would take it as the last vertex).
_OBJ_ZERO_INDEX = re.compile(r"^f[ \t](?:.*?[ \t])?[-+]?0+(?:[/ \t\r]|$)", re.M)
_OBJ_VERTEX_LINE = re.compile(r"^v[ \t]", re.M)


def read_scan(path: os.PathLike | str) -> tuple[np.ndarray, np.ndarray]:
    """(verts (n,3) float64, tris (k,3) int64) of an OBJ, PLY or STL scan, the file's own frame and unit;
    polygons are fanned into triangles. FileFormatError names the file and what is wrong."""
    path = pathlib.Path(path)
    readers = {".obj": _read_obj, ".ply": _read_ply, ".stl": _read_stl}
    suffix = path.suffix.lower()
    if suffix not in readers:
        raise FileFormatError(f"{path}: unsupported scan format {suffix!r} (use OBJ, PLY or STL)")
    verts, tris, weld = readers[suffix](path)
    return _checked(path, verts, tris, weld)


def _library(module: str, path: pathlib.Path) -> types.ModuleType:
    """The reader library's module; FileFormatError saying how to get it where this Python lacks it
    (a Blender without the extension running batch.py)."""
    try:
        return importlib.import_module(module)
    except ImportError:
        name = module.split(".")[0]
        raise FileFormatError(f"{path}: reading this scan needs the Python package {name}, missing in this Python "
                              f"(the HeadAdapt extension bundles it; else pip install {name}, see requirements.txt)"
                              ) from None


# ---------------------------------------------------------------------------------------------
# PLY (plyfile)
# ---------------------------------------------------------------------------------------------
def _open_ply(path: pathlib.Path) -> limits.CappedFile:
    return limits.open_capped(path, limits.SCAN_MAX_BYTES, "scan")


def _ply_header(path: pathlib.Path, fh: limits.CappedFile):
    """plyfile's parse of the header alone (the body is not touched), its counts checked against the
    bytes after it: each row needs at least one byte per value (ascii) or its fixed-size values and
    list lengths (binary)."""
    plyfile = _library("plyfile", path)

    if b"end_header" not in fh.read(_PLY_HEADER_MAX_BYTES):
        raise FileFormatError(f"{path}: not a PLY file (no 'end_header' in its first "
                              f"{_PLY_HEADER_MAX_BYTES // 1024} kB)")
    fh.seek(0)
    try:
        header = plyfile.PlyData._parse_header(fh)      # the first step of PlyData.read (plyfile 1.1.3)
    except (plyfile.PlyParseError, UnicodeDecodeError, ValueError) as exc:
        raise FileFormatError(f"{path}: not a PLY file ({exc})") from None
    room = fh.size - fh.tell()
    for el in header.elements:
        if header.text:
            row = len(el.properties)
        else:
            row = sum(np.dtype(p.list_dtype()[0] if isinstance(p, plyfile.PlyListProperty) else p.dtype()).itemsize
                      for p in el.properties)
        limit = limits.SCAN_MAX_VERTICES if el.name == "vertex" else limits.SCAN_MAX_FACES
        room -= limits.check_count(path, f"'{el.name}' elements", el.count, limit, room, max(row, 1)) * max(row, 1)
    return header


def _read_ply(path: pathlib.Path) -> tuple[np.ndarray, np.ndarray, bool]:
    plyfile = _library("plyfile", path)

    with _open_ply(path) as fh:
        header = _ply_header(path, fh)
        if "vertex" not in header or not {"x", "y", "z"} <= {p.name for p in header["vertex"].properties}:
            raise FileFormatError(f"{path}: no 'vertex' element with x, y, z properties")
        # Triangles first: their lists memory-map in one step (a textured scan's per-face texcoord: two
        # numbers a corner); plyfile says so if a length differs (quads, Blender's mixed export), then
        # it reads the lists row by row (a 65k-triangle textured scan: 0.9 s instead of 0.05).
        triangles = {el.name: {p.name: 6 if "texcoord" in p.name.lower() else 3
                               for p in el.properties if isinstance(p, plyfile.PlyListProperty)}
                     for el in header.elements}
        try:
            try:
                fh.seek(0)
                data = plyfile.PlyData.read(fh, mmap="c", known_list_len=triangles)
            except plyfile.PlyElementParseError as exc:
                if exc.message != "unexpected list length":
                    raise
                fh.seek(0)
                data = plyfile.PlyData.read(fh, mmap="c")
            vertex = data["vertex"]
            verts = np.stack([np.asarray(vertex[c], dtype=np.float64) for c in "xyz"], axis=1)
            names = [p.name for p in data["face"].properties] if "face" in data else []
            key = next((n for n in ("vertex_indices", "vertex_index") if n in names), None)
            polys = data["face"][key] if key else np.zeros((0, 3), np.int64)
            if polys.dtype != object and polys.dtype.kind not in "iu":
                raise FileFormatError(f"{path}: face indices are of type {polys.dtype}, not integers")
            tris = fan_triangles(polys)
        except (FileFormatError, MemoryError):    # out of memory is no fault of the file (batch: exit 1)
            raise
        except Exception as exc:        # plyfile's own errors and whatever a malformed body makes numpy raise
            raise FileFormatError(f"{path}: cannot read as PLY ({exc})") from None
    return verts, tris, False


def fan_triangles(polys: np.ndarray) -> np.ndarray:
    """(k,3) int64 triangles fanning out each polygon of polys, an (n,m) index array or an object array
    of n index arrays of any lengths (polygons under 3 corners give none)."""
    if not len(polys):                  # a point cloud (no face element, or one of none)
        return np.zeros((0, 3), np.int64)
    if polys.dtype != object:
        polys = np.asarray(polys, dtype=np.int64).reshape(len(polys), -1)
        m = polys.shape[1]
        corners = np.stack([np.zeros(max(m - 2, 0), np.int64), np.arange(1, m - 1), np.arange(2, m)], axis=1)
        return polys[:, corners].reshape(-1, 3)
    sizes = np.fromiter(map(len, polys), np.int64, count=len(polys))
    if not sizes.sum():
        return np.zeros((0, 3), np.int64)
    flat = np.concatenate([np.asarray(p) for p in polys])
    if flat.dtype.kind not in "iu":
        raise ValueError(f"face indices are of type {flat.dtype}, not integers")
    flat = flat.astype(np.int64)
    fans = np.maximum(sizes - 2, 0)
    first = np.repeat(np.cumsum(sizes) - sizes, fans)                        # each triangle's polygon start
    k = np.arange(fans.sum()) - np.repeat(np.cumsum(fans) - fans, fans) + 1  # 1.. within its polygon
    return np.stack([flat[first], flat[first + k], flat[first + k + 1]], axis=1)


# ---------------------------------------------------------------------------------------------
# OBJ and STL (trimesh)
# ---------------------------------------------------------------------------------------------
def _trimesh_parts(loaded: dict) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and faces of a trimesh loader's result: one mesh, or several ("geometry") stacked."""
    parts = loaded["geometry"].values() if "geometry" in loaded else [loaded]
    verts, faces, offset = [], [], 0
    for part in parts:
        v = np.asarray(part.get("vertices", np.zeros((0, 3))), dtype=np.float64).reshape(-1, 3)
        f = part.get("faces")
        if f is not None and len(f):
            faces.append(fan_triangles(np.asarray(f)) + offset)
        verts.append(v)
        offset += len(v)
    return (np.concatenate(verts) if verts else np.zeros((0, 3)),
            np.concatenate(faces) if faces else np.zeros((0, 3), np.int64))


def _read_obj(path: pathlib.Path) -> tuple[np.ndarray, np.ndarray, bool]:
    load_obj = _library("trimesh.exchange.obj", path).load_obj

    # Not UTF-8 (a name or comment in another encoding) is no reason to refuse the geometry.
    text = limits.read_capped(path, limits.SCAN_MAX_BYTES, "scan").decode("utf-8", errors="replace")
    zero = _OBJ_ZERO_INDEX.search(text)
    if zero:
        raise FileFormatError(f"{path}, line {text.count(chr(10), 0, zero.start()) + 1}: "
                              "face index 0 (OBJ counts vertices from 1)")
    try:
        loaded = load_obj(io.StringIO(text), skip_materials=True)
        verts, tris = _trimesh_parts(loaded)
    except IndexError as exc:           # trimesh indexes the vertices with the faces as read
        raise FileFormatError(f"{path}: a face refers to a vertex that does not exist ({exc})") from None
    except MemoryError:                 # out of memory is no fault of the file (batch: exit 1)
        raise
    except Exception as exc:            # trimesh's own errors and whatever a malformed line makes numpy raise
        raise FileFormatError(f"{path}: cannot read as OBJ ({type(exc).__name__}: {exc})") from None
    # trimesh splits a vertex per texture coordinate or normal and a mesh per material: weld them back
    weld = "geometry" in loaded or len(verts) > len(_OBJ_VERTEX_LINE.findall(text))
    return verts, tris, weld


def _read_stl(path: pathlib.Path) -> tuple[np.ndarray, np.ndarray, bool]:
    stl = _library("trimesh.exchange.stl", path)

    raw = limits.read_capped(path, limits.SCAN_MAX_BYTES, "scan")
    declared = int.from_bytes(raw[80:84], "little") if len(raw) >= 84 else -1
    try:
        if len(raw) == 84 + 50 * declared:          # binary: the header's triangle count fits the size
            limits.check_count(path, "triangles", declared, limits.SCAN_MAX_FACES)
            loaded = stl.load_stl_binary(io.BytesIO(raw))
        else:
            text = raw.decode("ascii", errors="replace")
            if not text.lstrip().lower().startswith("solid"):
                why = (f"a binary STL of {declared:,} triangles would be {84 + 50 * declared:,} bytes, it has "
                       f"{len(raw):,}" if declared >= 0 else "too short for a binary STL")
                raise FileFormatError(f"{path}: not an STL file ({why}; an ASCII STL starts with 'solid')")
            loaded = stl.load_stl_ascii(io.StringIO(text))
        verts, tris = _trimesh_parts(loaded)
    except (FileFormatError, MemoryError):
        raise
    except Exception as exc:            # trimesh's own errors and whatever a malformed facet makes numpy raise
        raise FileFormatError(f"{path}: cannot read as STL ({type(exc).__name__}: {exc})") from None
    return verts, tris, True            # STL repeats each corner per triangle


# ---------------------------------------------------------------------------------------------
# HeadAdapt's checks
# ---------------------------------------------------------------------------------------------
def _checked(path: pathlib.Path, verts: np.ndarray, tris: np.ndarray, weld_corners: bool):
    n = len(verts)
    if n == 0:
        raise FileFormatError(f"{path}: the file has no vertices")
    limits.check_count(path, "vertices", n, limits.SCAN_MAX_VERTICES)
    limits.check_count(path, "triangles", len(tris), limits.SCAN_MAX_FACES)
    bad = np.flatnonzero(~np.isfinite(verts).all(axis=1))
    if len(bad):
        raise FileFormatError(f"{path}: vertex {bad[0] + 1} is not finite {verts[bad[0]].tolist()} "
                              f"({len(bad)} such vertices)")
    if len(tris) == 0:
        raise FileFormatError(f"{path}: the file has no faces (a point cloud is not a scan surface)")
    out = np.flatnonzero(((tris < 0) | (tris >= n)).any(axis=1))
    if len(out):
        raise FileFormatError(f"{path}: face {out[0] + 1} refers to a vertex that does not exist "
                              f"({tris[out[0]].tolist()}, the file has {n} vertices)")
    if weld_corners:
        verts, tris = geometry.weld(verts, tris)
    return np.ascontiguousarray(verts, dtype=np.float64), np.ascontiguousarray(tris, dtype=np.int64)
