"""Scan and landmark files: OBJ, PLY (ascii/binary), STL (ascii/binary); landmark JSON and MeshLab .pp.

Everything is read as given (the file's own frame and unit); errors name the file and the problem.
Readers check the file's size before reading it (core/limits.py); scans are read by plyfile and
trimesh (core/readers.py). Writers are atomic: they write a temporary file beside the target and
rename it; any failure (a full disk, a folder that cannot be written) is a FileFormatError naming it.
"""

import json
import os
import pathlib
import re
import tempfile
import xml.etree.ElementTree as ET

import numpy as np

from . import limits, mpeg4, readers
from .exceptions import FileFormatError, LandmarkError


# ---------------------------------------------------------------------------------------------
# atomic writes
# ---------------------------------------------------------------------------------------------
def write_atomic(path: str | os.PathLike, data: str | bytes) -> None:
    """Write bytes or str to path atomically: a temporary file in the same folder, flushed to disk, then
    renamed over path, so path holds either its old content or all of data. FileFormatError names path
    when the folder cannot be made or written or the disk is full; no temporary file is left."""
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
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except OSError as exc:
        pathlib.Path(tmp).unlink(missing_ok=True)
        raise FileFormatError(f"cannot write {path}: {exc.strerror or exc}") from exc
    except BaseException:
        pathlib.Path(tmp).unlink(missing_ok=True)
        raise
    return path


# ---------------------------------------------------------------------------------------------
# meshes
# ---------------------------------------------------------------------------------------------
def read_mesh(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read a scan (OBJ, PLY or STL) as (verts (n,3) float64, tris (k,3) int64), the file's frame and unit.

    The one read path of the batch job and the add-on (core/readers.py: plyfile and trimesh behind
    HeadAdapt's limits and checks); FileFormatError names the file and the problem."""
    return readers.read_scan(path)


def write_obj(path: str | os.PathLike, verts: np.ndarray, tris: np.ndarray, header: str = "HeadAdapt") -> None:
    """Write a triangle mesh as OBJ (atomic); coordinates as given."""
    verts = np.asarray(verts, dtype=np.float64).reshape(-1, 3)
    tris = np.asarray(tris, dtype=np.int64).reshape(-1, 3) + 1
    # one %-format of all the numbers (np.savetxt's text to the byte, in a fifth of its time: it formats
    # row by row in Python)
    return write_atomic(path, f"# {header}\n# {len(verts)} vertices, {len(tris)} triangles\n"
                        + ("v %.9g %.9g %.9g\n" * len(verts)) % tuple(verts.ravel().tolist())
                        + ("f %d %d %d\n" * len(tris)) % tuple(tris.ravel().tolist()))


# ---------------------------------------------------------------------------------------------
# landmarks
# ---------------------------------------------------------------------------------------------
def read_landmarks(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """FDP landmarks {id: (3,) float} of a JSON or MeshLab .pp file (read_landmark_file's points)."""
    return read_landmark_file(path)[0]


def read_landmark_file(path: str | os.PathLike) -> tuple[dict[str, np.ndarray], dict]:
    """Read FDP landmarks ({id: (3,) float}, meta) from JSON {"points": {...}} or a MeshLab .pp file
    (file's frame).

    The file's size is checked before it is read; XML entity declarations are refused (no entity
    expansion). Unknown names and anything but three finite numbers raise LandmarkError naming the
    FDP; the other top-level JSON fields (a "template_sha256", held-out "markers", checked like the
    points) are returned as the meta dict.
    """
    path = pathlib.Path(path)
    if path.suffix.lower() in (".ply", ".obj", ".stl"):
        raise FileFormatError(f"{path}: a mesh, not a landmark file (JSON or MeshLab .pp): the scan and "
                              "the landmarks swapped?")
    raw = limits.read_capped(path, limits.LANDMARKS_MAX_BYTES, "landmark file")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise FileFormatError(f"{path}: not UTF-8 text (byte {exc.start})") from None
    points, meta = (_parse_pp if path.suffix.lower() == ".pp" else _parse_json)(path, text)
    limits.check_count(path, "points", len(points), limits.LANDMARKS_MAX_POINTS)
    out = {}
    for name, xyz in points.items():
        name = str(name).strip()            # (a MeshLab label typed as "3.7 ")
        try:
            mpeg4.check_fdp_name(name)
        except LandmarkError as exc:
            raise LandmarkError(f"{path}: {exc}") from None
        if name in out:
            raise _given_twice(path, name)
        out[name] = _xyz(path, f"FDP {name}", xyz)
    if "markers" in meta:
        markers = meta["markers"]
        if not isinstance(markers, dict):
            raise LandmarkError(f'{path}: "markers" must be an object {{"name": [x, y, z], ...}}')
        limits.check_count(path, "markers", len(markers), limits.LANDMARKS_MAX_POINTS)
        meta["markers"] = {str(k): _xyz(path, f"marker {k}", v).tolist() for k, v in markers.items()}
    return dict(sorted(out.items(), key=lambda kv: mpeg4.fdp_sort_key(kv[0]))), meta


def _xyz(path, what, value):
    """(3,) float64 of three finite numbers, else LandmarkError naming path and what."""
    arr = None
    if (isinstance(value, (list, tuple)) and len(value) == 3
            and all(isinstance(c, (int, float)) and not isinstance(c, bool) for c in value)):
        try:
            arr = np.array(value, dtype=np.float64)
        except OverflowError:            # an integer beyond any float
            arr = None
    if arr is None or not np.isfinite(arr).all():
        shown = repr(value) if len(repr(value)) <= 80 else repr(value)[:77] + "..."
        raise LandmarkError(f"{path}: {what} must be three finite numbers [x, y, z], got {shown}")
    return arr


class _Twice(Exception):
    """A name given twice in one JSON object (json.loads would keep the last silently)."""


def _unique_keys(pairs):
    out = {}
    for key, value in pairs:
        if key in out:
            raise _Twice(key)
        out[key] = value
    return out


def _given_twice(path, name):
    if str(name).strip() not in mpeg4.FDPS:            # a marker's or another field's name
        return FileFormatError(f"{path}: {name!r} is given twice in one object")
    return LandmarkError(f"{path}: FDP {name} is given twice: give each FDP once (one of them is probably "
                         "another FDP)")


def _parse_json(path, text):
    try:
        # NaN and Infinity (JSON's extension) read as floats: the check of the point they are in (_xyz)
        # then names its FDP
        data = json.loads(text, parse_constant=float, object_pairs_hook=_unique_keys)
    except _Twice as exc:
        raise _given_twice(path, exc.args[0]) from None
    except RecursionError:
        raise FileFormatError(f"{path}: cannot read landmarks (JSON nested too deep)") from None
    except ValueError as exc:        # JSONDecodeError, integers too long to convert
        raise FileFormatError(f"{path}: cannot read landmarks ({exc})") from None
    if not isinstance(data, dict) or not isinstance(data.get("points"), dict):
        raise FileFormatError(f'{path}: expected a JSON object {{"points": {{"3.7": [x, y, z], ...}}}}')
    return data["points"], {k: v for k, v in data.items() if k != "points"}


def _parse_pp(path, text):
    """{name: [x, y, z]} of the active points of a MeshLab .pp file (attributes still text)."""
    if re.search(r"<!ENTITY", text, re.I):
        raise FileFormatError(f"{path}: XML entity declarations are not allowed in a landmark file")
    try:
        root = ET.fromstring(text)
    except (ET.ParseError, ValueError) as exc:
        raise FileFormatError(f"{path}: cannot read landmarks ({exc})") from None
    points = {}
    for el in root.iter("point"):
        if el.get("active", "1") in ("0", "false"):
            continue
        if el.get("name") in points:
            raise _given_twice(path, el.get("name"))
        try:
            points[el.get("name")] = [float(el.get(c)) for c in "xyz"]
        except (TypeError, ValueError):
            raise LandmarkError(f"{path}: point {el.get('name')!r} needs numbers x, y and z, got "
                                f"{[el.get(c) for c in 'xyz']}") from None
    return points, {}


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
