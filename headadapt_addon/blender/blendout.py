"""Write an adaptation result as a .blend (batch job): scan, adapted template hierarchy, landmarks, report."""

import json
import os
import pathlib
import tempfile

import bpy
import numpy as np

from ..core.anatomy import transfer
from ..core.exceptions import FileFormatError
from . import animation, bridge, scene

RESULT_COLLECTION = "HeadAdapt result"


def heat_colours(dist_mm, limit_mm=3.0):
    """RGBA (n,4): blue at 0 mm through green and yellow to red at limit_mm and beyond; grey where NaN (no scan)."""
    dist_mm = np.asarray(dist_mm, dtype=float)
    t = np.clip(np.nan_to_num(dist_mm, nan=0.0) / limit_mm, 0.0, 1.0)
    r = np.clip(2 * t, 0, 1)
    g = np.clip(2 - 2 * t, 0, 1) * np.clip(2 * t + 0.3, 0, 1)
    b = np.clip(1 - 2 * t, 0, 1)
    rgba = np.c_[r, g, b, np.ones_like(t)]
    rgba[np.isnan(dist_mm)] = (0.6, 0.6, 0.6, 1.0)
    return rgba


def build_result_objects(tpl, result, target_scene, scan_matrix=None, anatomy=None):
    """Add the adapted template (all parts) to a new "HeadAdapt result" collection, placed on the scan.

    The hierarchy keeps template-frame coordinates; its root carries scan_matrix @ inverse
    calibration, so it overlays the scan object. The skin gets a "HeadAdapt distance" colour
    attribute (distance to the scan, blue 0 mm to red 3 mm); the root keeps the anatomy (`anatomy`,
    else transferred here) for the bake. Returns the root.
    """
    import mathutils

    coll = bpy.data.collections.new(RESULT_COLLECTION)
    target_scene.collection.children.link(coll)
    ana = anatomy if anatomy is not None else transfer(tpl, result)
    parts = ana.parts
    root = scene.add_template(tpl, coll, name="HA Adapted head")
    objs = scene.template_objects(root)
    pivot = ana.jaw_pivot
    objs["jaw_pivot"].location = pivot
    for name, verts in parts.items():
        offset = pivot if name in ("mandible", "teeth_lower") else 0.0
        bridge.set_vertex_positions(objs[name].data, verts - offset)
    muscles = {m["name"]: m for m in ana.muscles}
    rings = {sph["name"]: sph for sph in ana.sphincters}
    angles = np.linspace(0, 2 * np.pi, 48, endpoint=False)[:, None]
    for o in root.children_recursive:
        if "headadapt_fdp" in o:
            o.location = ana.fdps[o["headadapt_fdp"]]
        name = o.get("headadapt_muscle")
        if name in muscles:
            pts = np.array([muscles[name]["attachment"], muscles[name]["insertion"]])
        elif name in rings:
            a, b = rings[name]["axes"]
            pts = rings[name]["centre"] + np.cos(angles) * a + np.sin(angles) * b
        else:
            continue
        co = np.hstack([pts, np.ones((len(pts), 1))]).astype(np.float32)
        o.data.splines[0].points.foreach_set("co", co.ravel())
    root["headadapt_fapus"] = json.dumps(ana.fapus)
    root["headadapt_anatomy"] = ana.to_plain()      # float64, exactly what the bake simulates on
    dist_mm = result.distances * 1000.0
    bridge.set_point_colors(objs["skin"].data, "HeadAdapt distance", heat_colours(dist_mm))
    m = mathutils.Matrix(result.similarity.inverse().matrix4().tolist())
    root.matrix_world = (scan_matrix if scan_matrix is not None else mathutils.Matrix.Identity(4)) @ m
    root["headadapt_report"] = json.dumps(result.report(), default=float)
    root["headadapt_part"] = "result_root"
    bpy.context.view_layer.update()
    return root


def bake_result(tpl, root, kinds=("expression", "viseme", "fap", "arkit"), preview=True, progress=None, anatomy=None):
    """Bake expressions/visemes/FAPs of a head hierarchy to shape keys (+ the preview action); timings.
    The anatomy simulated is `anatomy` (the batch passes the transfer's own), else the one stored on
    the root by build_result_objects, else (the template's hierarchy) the template's."""
    from ..core.skin import bake
    if anatomy is None:
        anatomy = animation.stored_anatomy(tpl, root)
    keys, timing = bake.bake(tpl, anatomy, kinds=kinds, progress=progress)
    animation.write_shape_keys(root, keys)
    if preview and "expression" in kinds:
        animation.preview_action(root)
    return {"keys": len(keys), "build_s": timing["build_s"], "per_key_s": timing["per_key_s"]}


def build_result_scene(tpl, result, scan_verts, scan_tris, landmarks, report, scan_name="scan", bake=True):
    """Add the scan (with its landmarks), the adapted template and (bake) its shape keys; return the root."""
    scan_obj = bpy.data.objects.new(scan_name, bridge.new_mesh(scan_name, scan_verts, scan_tris))
    bpy.context.scene.collection.objects.link(scan_obj)
    scan_obj["headadapt_landmarks"] = json.dumps({k: [float(c) for c in v] for k, v in landmarks.items()})
    ana = transfer(tpl, result)
    root = build_result_objects(tpl, result, bpy.context.scene, anatomy=ana)
    if bake:
        report = dict(report, bake=bake_result(tpl, root, anatomy=ana))
    text = bpy.data.texts.new("HeadAdapt report")
    text.write(json.dumps(report, indent=1, default=float))
    root["headadapt_report"] = json.dumps(report, default=float)
    return root


def write_blend(path, tpl, result, scan_verts, scan_tris, landmarks, report, bake=True):
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
        build_result_scene(tpl, result, scan_verts, scan_tris, landmarks, report, bake=bake)
        pathlib.Path(tmp).unlink()          # mkstemp only reserved the name: Blender would back up the empty file
        bpy.ops.wm.save_as_mainfile(filepath=tmp, copy=True, compress=True)
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    finally:
        pathlib.Path(tmp).unlink(missing_ok=True)
        pathlib.Path(tmp + "1").unlink(missing_ok=True)
    return path
