"""Write an adaptation result as a .blend (batch job): scan, adapted template hierarchy, landmarks, report."""

import contextlib
import json
import os
import pathlib
import re
import sys
import tempfile
import time

import bpy
import numpy as np

from ..core.anatomy import transfer
from ..core.exceptions import FileFormatError
from ..core.interrupts import held_ctrl_c
from . import animation, bridge, scene, view
from .view import heat_colours  # noqa: F401  (blendout.heat_colours: the colours of the heat map)

RESULT_COLLECTION = "HeadAdapt result"


MESH_PARTS = ("skin", "cranium", "mandible", "teeth_lower", "eye_l", "eye_r", "teeth_upper", "tongue")


def build_result_objects(tpl, result, target_scene, scan_matrix=None, anatomy=None, name=None):
    """Add the adapted template (all parts) to a new "HeadAdapt result" collection, placed on the scan.

    The hierarchy keeps template-frame coordinates; its root carries scan_matrix @ inverse
    calibration, so it overlays the scan object. The skin gets a "HeadAdapt distance" colour
    attribute (distance to the scan, blue 0 mm to red 3 mm); the root keeps the anatomy (`anatomy`,
    else transferred here) for the bake. With a name (the scan's), the root is "NAME adapted" and the
    meshes "NAME skin", "NAME cranium", ... Returns the root.
    """
    import mathutils

    coll = bpy.data.collections.new(RESULT_COLLECTION)
    target_scene.collection.children.link(coll)
    ana = anatomy if anatomy is not None else transfer(tpl, result)
    parts = ana.parts
    root = scene.add_template(tpl, coll, name=f"{name} adapted" if name else "HA Adapted head")
    objs = scene.template_objects(root)
    if name:
        for part in MESH_PARTS:
            objs[part].name = objs[part].data.name = f"{name} {part}"
    head_pivot = result.map_points(np.asarray(tpl.meta["head_pivot"], dtype=float)[None])[0]
    root["headadapt_head_pivot"] = [float(c) for c in head_pivot]      # the adapted head turns about it
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
        if "headadapt_marker" in o:         # held-out markers: where the adapted skin puts them
            ref = tpl.meta["markers"][o["headadapt_marker"]]
            o.location = np.asarray(ref["bary"]) @ parts[ref["part"]][tpl.parts[ref["part"]].tris[ref["face"]]]
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
    bridge.set_point_colors(objs["skin"].data, view.HEAT_ATTRIBUTE, view.heat_colours(dist_mm))
    view.add_heat_legend(root, tpl, coll)
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
    return apply_bake(root, keys, timing, kinds, preview, animation.written_rest(tpl, anatomy))


def apply_bake(root, keys, timing, kinds, preview=True, rest=None):
    """Write baked keys (core.skin.bake.bake's) to root's shape keys (+ the preview action); timings.
    The bake itself is numpy only: the panels run it on a worker thread and this in the main thread.
    rest: animation.written_rest of the anatomy baked (keys follow a part the artist has moved)."""
    animation.write_shape_keys(root, keys, rest)
    if preview and "expression" in kinds:
        animation.preview_action(root)
    return {"keys": len(keys), "build_s": timing["build_s"], "per_key_s": timing["per_key_s"],
            "helper_keys": timing.get("helper_keys", 0)}


def add_camera_and_light(root, target_scene):
    """A camera looking at the head's face from the front and a sun from the front-left above, so a
    saved .blend renders (F12) without setup; both aimed at root's world bounding box."""
    import mathutils
    pts = [o.matrix_world @ mathutils.Vector(c) for o in root.children_recursive if o.type == "MESH"
           for c in o.bound_box]
    lo = mathutils.Vector([min(p[i] for p in pts) for i in range(3)])
    hi = mathutils.Vector([max(p[i] for p in pts) for i in range(3)])
    centre, size = (lo + hi) / 2, max((hi - lo).length, 1e-6)
    front = (root.matrix_world.to_3x3() @ mathutils.Vector((0.0, -1.0, 0.0))).normalized()  # template: face at -Y
    cam = bpy.data.objects.new("HeadAdapt camera", bpy.data.cameras.new("HeadAdapt camera"))
    cam.location = centre + front * 2.2 * size
    cam.rotation_euler = (centre - cam.location).to_track_quat("-Z", "Y").to_euler()
    cam.data.clip_end = 10 * size
    cam.data.clip_start = size / 100
    sun = bpy.data.objects.new("HeadAdapt light", bpy.data.lights.new("HeadAdapt light", "SUN"))
    sun.location = centre + front * size + mathutils.Vector((-size, 0.0, size))
    sun.rotation_euler = (centre - sun.location).to_track_quat("-Z", "Y").to_euler()
    sun.data.energy = 3.0
    for obj in (cam, sun):
        target_scene.collection.objects.link(obj)
    target_scene.camera = cam
    return cam, sun


SCAN_UNITS = (("MILLIMETERS", 0.001), ("CENTIMETERS", 0.01), ("INCHES", 0.0254), ("METERS", 1.0))


def set_scene_unit(scene, scale):
    """The scene's unit set to the scan's (the one of mm, cm, inch, m nearest the calibration's
    scale, metres of head per scan unit), so that a scan in mm opens as a head of some 250 mm, not
    250 m."""
    name, metres = min(SCAN_UNITS, key=lambda u: abs(np.log(u[1] / max(scale, 1e-30))))
    scene.unit_settings.system = "IMPERIAL" if name == "INCHES" else "METRIC"
    scene.unit_settings.scale_length = metres
    scene.unit_settings.length_unit = name


def build_result_scene(tpl, result, scan_verts, scan_tris, landmarks, report, scan_name="scan", bake=True,
                       progress=None, anatomy=None):
    """Add the scan (with its landmarks), the adapted template, a camera and a light, and (bake) its
    shape keys (progress(fraction, key name) per key); return the root. anatomy: the transfer's, if the
    caller made it. The seconds of the transfer (made here) and the bake go into report["stage_seconds"]
    (that dict itself)."""
    stages = report.setdefault("stage_seconds", {})
    set_scene_unit(bpy.context.scene, result.similarity.scale)
    scan_obj = bpy.data.objects.new(scan_name, bridge.new_mesh(scan_name, scan_verts, scan_tris))
    bpy.context.scene.collection.objects.link(scan_obj)
    scan_obj["headadapt_landmarks"] = json.dumps({k: [float(c) for c in v] for k, v in landmarks.items()})
    ana = anatomy
    if ana is None:
        t0 = time.perf_counter()
        ana = transfer(tpl, result)
        stages["transfer"] = time.perf_counter() - t0
    root = build_result_objects(tpl, result, bpy.context.scene, anatomy=ana)
    root["headadapt_scan"] = scan_obj                 # the add-on's panels show a scan's own result
    add_camera_and_light(root, bpy.context.scene)
    view.show_heat_map(bpy.data.screens)            # opened, the .blend shows the heat map and the legend
    view.show_scan_as_wire(scan_obj)
    if bake:
        t0 = time.perf_counter()
        report = dict(report, bake=bake_result(tpl, root, anatomy=ana, progress=progress))
        stages["bake"] = time.perf_counter() - t0
    text = bpy.data.texts.new("HeadAdapt report")
    text.write(json.dumps(report, indent=1, default=float))
    root["headadapt_report"] = json.dumps(report, default=float)
    return root


# Blender's own lines a batch log has no use for: each preview view's "Saved: '.../.preview.x/view00.png'"
# (Blender 4.2 on: "render | Saved: ..." after a time stamp; 3.x: the line alone, then " Time: 00:00.32
# (Saving: 00:00.04)" and a blank line), the .blend's "Info: Saved copy as ".head.x.blend"" (3.x: "Info:
# Saved ".head.x.blend"", after "Info: Total files 0 | Changed 0 | Failed 0"), both HeadAdapt's temporary
# files, renamed after; and a headless GPU's context probes ("EGL Error (0x3009): EGL_BAD_MATCH ...", three
# a run, the render fine; 3.x: "Managed to successfully fallback to surfaceless EGL rendering!")
CHATTER = re.compile(r"""(^|\| )Saved: '.*[/\\]\.[^/\\]+[/\\]view\d\d\.png'$|^ Time: [\d:.]+ \(Saving: [\d:.]+\)$|^\s*$"""
                     r"""|^Info: Saved (copy as )?"\.[^"]*\.blend"$|^Info: Total files \d+ \| Changed \d+ \| Failed \d+$"""
                     r"|^EGL Error \(0x[0-9A-Fa-f]+\): |^Managed to successfully fallback to surfaceless EGL rendering!$")


@contextlib.contextmanager
def without_chatter(drop=CHATTER):
    """Blender's lines written to the process's stdout and stderr during the block (its C code writes to
    the file descriptors) are held, and passed on after it to where they were going, but those matching
    drop; if the block raises, every line is passed on. Where the descriptors cannot be swapped (none
    open, Windows' C runtime) the block runs as it is."""
    try:
        import ctypes
        flush = ctypes.CDLL(None).fflush if os.name == "posix" else None
        saved = {fd: os.dup(fd) for fd in (1, 2)} if flush is not None else None
    except (OSError, AttributeError):
        saved = None
    if saved is None:
        yield
        return
    held = {fd: tempfile.TemporaryFile() for fd in saved}

    def swap(to):
        sys.stdout.flush()
        sys.stderr.flush()
        flush(None)                                     # C's own buffers, to where they were written
        for fd in saved:
            os.dup2(to[fd], fd)

    swap({fd: f.fileno() for fd, f in held.items()})
    ok = False
    try:
        yield
        ok = True
    finally:
        swap(saved)
        for fd, f in held.items():
            os.close(saved[fd])
            f.seek(0)
            lines = f.read().decode("utf-8", "replace").splitlines(keepends=True)
            f.close()
            kept = "".join(line for line in lines if not (ok and drop.search(line.rstrip("\r\n"))))
            if kept:
                os.write(fd, kept.encode("utf-8"))


def write_blend(path, tpl, result, scan_verts, scan_tris, landmarks, report, bake=True, progress=None, anatomy=None):
    """Write a fresh .blend with the scan, the adapted head, a camera and a light, atomically (temp
    file, then rename); progress(fraction, key name) while baking; anatomy: the transfer's, if made."""
    path = pathlib.Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=".blend", dir=path.parent)
        os.close(fd)
    except OSError as exc:
        raise FileFormatError(f"cannot write {path}: {exc.strerror or exc}") from exc
    try:
        with held_ctrl_c():
            bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
        build_result_scene(tpl, result, scan_verts, scan_tris, landmarks, report, bake=bake, progress=progress,
                           anatomy=anatomy)
        pathlib.Path(tmp).unlink()          # mkstemp only reserved the name: Blender would back up the empty file
        with held_ctrl_c(), without_chatter():
            bpy.ops.wm.save_as_mainfile(filepath=tmp, copy=True, compress=True)
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    finally:
        pathlib.Path(tmp).unlink(missing_ok=True)
        pathlib.Path(tmp + "1").unlink(missing_ok=True)
    return path


PREVIEW_VIEW_PX = 640           # each view of --preview is this many pixels square; front and side beside


def _aim(cam, root, direction, margin=1.15):
    """Point cam at the head's bounding box (the root's meshes and the legend's text, world) from
    `direction` (root frame), as near as it can while the box's corners stay in a square picture
    (margin: the box's half width or height across the view times this, whichever is larger)."""
    import math

    import mathutils
    pts = [o.matrix_world @ mathutils.Vector(c) for o in root.children_recursive if o.type in ("MESH", "FONT")
           for c in o.bound_box]
    lo = mathutils.Vector([min(p[i] for p in pts) for i in range(3)])
    hi = mathutils.Vector([max(p[i] for p in pts) for i in range(3)])
    centre, size = (lo + hi) / 2, max((hi - lo).length, 1e-6)
    way = (root.matrix_world.to_3x3() @ mathutils.Vector(direction)).normalized()
    up = (root.matrix_world.to_3x3() @ mathutils.Vector((0.0, 0.0, 1.0))).normalized()
    x = up.cross(way).normalized()                    # the camera looks down its -Z, its +Y up
    y = way.cross(x)
    across = max(max(abs((p - centre).dot(x)), abs((p - centre).dot(y))) for p in pts)
    deep = max((p - centre).dot(way) for p in pts)
    half_angle = math.atan(cam.data.sensor_width / 2 / cam.data.lens)
    cam.location = centre + way * (deep + margin * across / math.tan(half_angle))
    cam.rotation_euler = mathutils.Matrix((x, y, way)).transposed().to_euler()
    cam.data.clip_start, cam.data.clip_end = size / 100, 10 * size + (cam.location - centre).length
    return cam


def render_preview(path, root, scan_obj, px=PREVIEW_VIEW_PX):
    """Render the scan and the head with its heat map from the front and from the side (Workbench,
    Solid shading: the scan plain grey, the head by its colour attribute) and write them as one PNG
    (2 px x 2 px), atomically: a row per view, front on top, the scan on the left and the head on
    the right, so a likeness can be judged at a glance as well as read off the heat map."""
    path = pathlib.Path(path)
    sc = bpy.context.scene
    cams = []
    for name, direction in (("front", (0.0, -1.0, 0.0)), ("side", (-1.0, 0.0, 0.0))):   # template: face at -Y
        cam = bpy.data.objects.new(f"HeadAdapt preview {name}", bpy.data.cameras.new(f"HeadAdapt preview {name}"))
        sc.collection.objects.link(cam)
        cam.data.lens = 85.0
        cams.append(_aim(cam, root, direction))
    bpy.context.view_layer.update()
    shading = sc.display.shading
    # the scene's settings this changes, put back afterwards (the panel's Save Picture renders the
    # artist's own scene)
    kept = [(sc, "camera"), (sc.render, "engine"), (sc.render, "resolution_x"), (sc.render, "resolution_y"),
            (sc.render, "resolution_percentage"), (sc.render, "filepath"), (sc.render.image_settings, "file_format"),
            (sc.render.image_settings, "color_mode"), (shading, "light"), (shading, "color_type"),
            (shading, "single_color"), (scan_obj, "hide_render"), (scan_obj, "display_type")]
    # (a colour is read as a live view of the property: copied)
    before = [(owner, name, tuple(getattr(owner, name)) if name == "single_color" else getattr(owner, name))
              for owner, name in kept]
    head_objs = [o for o in root.children_recursive if o.type in ("MESH", "FONT")]
    hidden = {o.name: o.hide_render for o in head_objs}
    world = None
    if sc.world is None:
        sc.world = world = bpy.data.worlds.new("HeadAdapt preview")
    sc.render.engine = "BLENDER_WORKBENCH"
    shading.light = "STUDIO"
    shading.single_color = (0.8, 0.8, 0.8)
    sc.render.resolution_x = sc.render.resolution_y = px
    sc.render.resolution_percentage = 100
    sc.render.image_settings.file_format = "PNG"
    sc.render.image_settings.color_mode = "RGBA"
    columns = (("scan", "SINGLE"), ("head", "VERTEX"))      # what each column shows, in which colour
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp_dir = tempfile.mkdtemp(prefix=f".{path.stem}.", dir=path.parent)
    except OSError as exc:
        raise FileFormatError(f"cannot write the preview {path}: {exc.strerror or exc}") from None
    try:
        rows = []
        for i, cam in enumerate(cams):
            sc.camera = cam
            row = []
            for j, (what, colour) in enumerate(columns):
                for o in head_objs:     # the legend faces the front: from the side it is a stray line
                    o.hide_render = what != "head" or hidden[o.name] or (
                        i > 0 and str(o.get("headadapt_part", "")).startswith("legend"))
                scan_obj.hide_render, scan_obj.display_type = what != "scan", "SOLID"
                shading.color_type = colour
                sc.render.filepath = os.path.join(tmp_dir, f"view{i}{j}.png")
                with without_chatter():
                    bpy.ops.render.render(write_still=True)
                img = bpy.data.images.load(sc.render.filepath)
                pixels = np.empty(px * px * 4, dtype=np.float32)
                img.pixels.foreach_get(pixels)
                row.append(pixels.reshape(px, px, 4))
                bpy.data.images.remove(img)
            rows.append(np.concatenate(row, axis=1))
        grid = np.concatenate(rows[::-1], axis=0)         # front on top: Blender's pixels start at the bottom
        both = bpy.data.images.new("HeadAdapt preview", grid.shape[1], grid.shape[0], alpha=True)
        both.pixels.foreach_set(grid.ravel())
        both.filepath_raw = os.path.join(tmp_dir, "both.png")
        both.file_format = "PNG"
        both.save()
        bpy.data.images.remove(both)
        os.chmod(os.path.join(tmp_dir, "both.png"), 0o644)
        os.replace(os.path.join(tmp_dir, "both.png"), path)
    except (RuntimeError, OSError) as exc:
        raise FileFormatError(f"cannot write the preview {path}: {str(exc).strip()}") from None
    finally:
        for f in pathlib.Path(tmp_dir).glob("*"):
            f.unlink(missing_ok=True)
        os.rmdir(tmp_dir)
        for owner, name, value in before:
            setattr(owner, name, value)
        for o in head_objs:
            o.hide_render = hidden[o.name]
        if world is not None:
            sc.world = None
            bpy.data.worlds.remove(world)
        for cam in cams:
            data = cam.data
            bpy.data.objects.remove(cam)
            bpy.data.cameras.remove(data)
    return path


PREVIEW_SCAN_CELL = 0.001      # m, template frame: the picture's copy of a finer scan is clustered to this grid


def write_preview(path, tpl, result, scan_verts, scan_tris, landmarks, report, anatomy=None):
    """The batch's --preview: a fresh scene with the scan and the adapted head (not baked), rendered
    from the front and the side, the scan beside the head with its heat map, into one PNG
    (render_preview). A scan finer than PREVIEW_SCAN_CELL is drawn from its clusters on that grid
    (mesh/simplify.py; a view is 640 pixels across a head, about half a millimetre a pixel): a
    1M-vertex scan's side view took 6.5 s in software rendering, its clusters' 2.3 s. anatomy: the
    transfer's, if the caller made it (the batch's --blend); else one made here, its seconds part of
    the picture's (report's stage_seconds are left as they are: the caller times the preview whole)."""
    from ..core.mesh import simplify

    clustered = simplify.cluster_if_finer(scan_verts, scan_tris, PREVIEW_SCAN_CELL / result.similarity.scale)
    if clustered is not None:                                   # (the cell in the scan's unit)
        scan_verts, scan_tris, _ = clustered
    bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
    root = build_result_scene(tpl, result, scan_verts, scan_tris, landmarks, dict(report, stage_seconds={}),
                              bake=False, anatomy=anatomy)
    scan_obj = next(o for o in bpy.context.scene.objects if "headadapt_landmarks" in o)
    return render_preview(path, root, scan_obj)
