"""Write an adaptation result as a .blend (batch job): scan, adapted template hierarchy, landmarks, report."""

import json
import os
import pathlib
import tempfile

import bpy
import numpy as np

from . import bridge, scene
from .core import calibration
from .core.exceptions import FileFormatError

RESULT_COLLECTION = "HeadAdapt result"


def adapted_parts(tpl, result):
    """{part: (n,3) verts} of every template mesh carried through the result (template frame, m).

    Skin: the adapted skin; skull and mandible: through the final map; eyes, teeth, tongue: the
    best similarity to their mapped vertices (they stay rigid).
    """
    out = {"skin": result.verts}
    for name, part in tpl.parts.items():
        if name == "skin":
            continue
        mapped = result.map_points(part.verts)
        if name in ("cranium", "mandible"):
            out[name] = mapped
        else:
            out[name] = calibration.umeyama(part.verts, mapped).apply(part.verts)
    return out


def build_result_objects(tpl, result, target_scene, scan_matrix=None):
    """Add the adapted template (all parts) to a new "HeadAdapt result" collection, placed on the scan.

    The hierarchy keeps template-frame coordinates; its root carries scan_matrix @ inverse
    calibration, so it overlays the scan object. The skin gets a "HeadAdapt distance" colour
    attribute (distance to the scan, blue 0 mm to red 3 mm). Returns the root.
    """
    import mathutils

    from .ops import heat_colours

    coll = bpy.data.collections.new(RESULT_COLLECTION)
    target_scene.collection.children.link(coll)
    parts = adapted_parts(tpl, result)
    root = scene.add_template(tpl, coll, name="HA Adapted head")
    objs = scene.template_objects(root)
    pivot = result.map_points(np.asarray(tpl.meta["jaw"]["pivot"])[None])[0]
    objs["jaw_pivot"].location = pivot
    for name, verts in parts.items():
        offset = pivot if name in ("mandible", "teeth_lower") else 0.0
        bridge.set_vertex_positions(objs[name].data, verts - offset)
    names = list(tpl.fdp_points())
    moved = result.map_points(np.array(list(tpl.fdp_points().values())))
    fdp_pts = dict(zip(names, moved))
    for o in root.children_recursive:
        if "headadapt_fdp" in o:
            o.location = fdp_pts[o["headadapt_fdp"]]
    dist_mm = result.distances * 1000.0
    bridge.set_point_colors(objs["skin"].data, "HeadAdapt distance", heat_colours(dist_mm))
    m = mathutils.Matrix(result.similarity.inverse().matrix4().tolist())
    root.matrix_world = (scan_matrix if scan_matrix is not None else mathutils.Matrix.Identity(4)) @ m
    root["headadapt_report"] = json.dumps(result.report(), default=float)
    root["headadapt_part"] = "result_root"
    bpy.context.view_layer.update()
    return root


def build_result_scene(tpl, result, scan_verts, scan_tris, landmarks, report, scan_name="scan"):
    """Add the scan (with its landmarks) and the adapted template to the current scene; return the root."""
    scan_obj = bpy.data.objects.new(scan_name, bridge.new_mesh(scan_name, scan_verts, scan_tris))
    bpy.context.scene.collection.objects.link(scan_obj)
    scan_obj["headadapt_landmarks"] = json.dumps({k: [float(c) for c in v] for k, v in landmarks.items()})
    root = build_result_objects(tpl, result, bpy.context.scene)
    text = bpy.data.texts.new("HeadAdapt report")
    text.write(json.dumps(report, indent=1, default=float))
    root["headadapt_report"] = json.dumps(report, default=float)
    return root


def write_blend(path, tpl, result, scan_verts, scan_tris, landmarks, report):
    """Write a fresh .blend with the scan and the adapted head, atomically (temp file, then rename)."""
    path = pathlib.Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=".blend", dir=path.parent)
        os.close(fd)
    except OSError as exc:
        raise FileFormatError(f"cannot write {path}: {exc.strerror or exc}") from exc
    try:
        bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
        build_result_scene(tpl, result, scan_verts, scan_tris, landmarks, report)
        bpy.ops.wm.save_as_mainfile(filepath=tmp, copy=True, compress=True)
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    finally:
        pathlib.Path(tmp).unlink(missing_ok=True)
    return path
