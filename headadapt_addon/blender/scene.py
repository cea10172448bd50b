"""Put the template head into a Blender scene: one root empty with every part under it.

Layout (all objects tagged with the custom property ``headadapt_part``)::

    HA Template (empty, root)
      skin (mesh, quads, vertex group per region, int attribute ha_region)
      cranium (mesh)
      Jaw pivot (empty at the jaw pivot; rotate about its local X to open the jaw)
        mandible, teeth_lower (meshes)
      eye_l, eye_r, teeth_upper, tongue (meshes)
      FDPs (empty) -> "FDP 3.7 (ROOT)" ... (sphere empties on the surface; property headadapt_fdp)
      Markers (empty) -> "Marker glabella" ...
      Muscles (empty) -> one curve per linear muscle (attachment -> insertion), one closed
                         curve per sphincter ellipse
    FDPs, markers and muscles (the helpers) start hidden: the panels' Display toggles show them.
"""

import json

import bpy
import numpy as np

from . import bridge

ROOT_NAME = "HA Template"
COLOURS = {
    "skin": (0.86, 0.68, 0.58, 1.0), "cranium": (0.93, 0.9, 0.8, 1.0), "mandible": (0.9, 0.85, 0.72, 1.0),
    "eye_l": (0.95, 0.95, 0.95, 1.0), "eye_r": (0.95, 0.95, 0.95, 1.0),
    "teeth_upper": (1.0, 1.0, 0.92, 1.0), "teeth_lower": (1.0, 1.0, 0.92, 1.0),
    "tongue": (0.8, 0.35, 0.35, 1.0), "fdp": (0.1, 0.45, 1.0, 1.0), "marker": (1.0, 0.6, 0.0, 1.0),
    "muscle": (0.75, 0.1, 0.1, 1.0), "sphincter": (0.55, 0.1, 0.45, 1.0),
}
FDP_SIZE_M = 0.0015
HELPER_PARTS = ("fdps", "fdp", "markers", "marker", "muscles", "muscle", "sphincter")


def _material(name, colour):
    mat = bpy.data.materials.get(f"HA {name}") or bpy.data.materials.new(f"HA {name}")
    mat.diffuse_color = colour
    return mat


def _link(obj, collection, parent, part):
    collection.objects.link(obj)
    obj.parent = parent
    obj["headadapt_part"] = part
    return obj


def _mesh_object(name, verts, quads, collection, parent, colour):
    obj = bpy.data.objects.new(name, bridge.new_mesh(name, verts, quads))
    obj.data.materials.append(_material(name, colour))
    obj.color = colour
    return _link(obj, collection, parent, name)


def _empty(name, collection, parent, part, location=(0, 0, 0), kind="PLAIN_AXES", size=0.01):
    obj = bpy.data.objects.new(name, None)
    obj.empty_display_type = kind
    obj.empty_display_size = size
    obj.location = location
    return _link(obj, collection, parent, part)


def _curve(name, points, collection, parent, colour, cyclic=False, bevel=0.0008):
    data = bpy.data.curves.new(name, "CURVE")
    data.dimensions = "3D"
    data.bevel_depth = bevel
    spline = data.splines.new("POLY")
    spline.points.add(len(points) - 1)
    co = np.hstack([np.asarray(points, dtype=np.float32), np.ones((len(points), 1), np.float32)])
    spline.points.foreach_set("co", co.ravel())
    spline.use_cyclic_u = cyclic
    data.materials.append(_material(name.split()[0], colour))
    obj = bpy.data.objects.new(name, data)
    obj.color = colour
    return obj


def add_template(tpl, collection=None, name=ROOT_NAME):
    """Add the template (metres, Blender frame) under one new root empty; return the root object."""
    collection = collection or bpy.context.scene.collection
    root = bpy.data.objects.new(name, None)
    root.empty_display_size = 0.05
    collection.objects.link(root)
    root["headadapt_part"] = "root"
    root["headadapt_template_sha256"] = tpl.meta["content_sha256"]
    root["headadapt_head_pivot"] = [float(c) for c in tpl.meta["head_pivot"]]   # what the head turns about

    skin = _mesh_object("skin", tpl.skin.verts, tpl.skin.quads, collection, root, COLOURS["skin"])
    attr = skin.data.attributes.new("ha_region", "INT", "POINT")
    attr.data.foreach_set("value", tpl.region.astype(np.int32))
    for i, region in enumerate(tpl.region_names):
        skin.vertex_groups.new(name=f"region {region}").add(np.flatnonzero(tpl.region == i).tolist(), 1.0, "REPLACE")
    _mesh_object("cranium", tpl.parts["cranium"].verts, tpl.parts["cranium"].quads, collection, root,
                 COLOURS["cranium"])

    jaw = tpl.meta["jaw"]
    pivot = np.asarray(jaw["pivot"])
    jaw_empty = _empty("Jaw pivot", collection, root, "jaw_pivot", pivot, "ARROWS", 0.02)
    for part in ("mandible", "teeth_lower"):
        obj = _mesh_object(part, tpl.parts[part].verts - pivot, tpl.parts[part].quads, collection,
                           jaw_empty, COLOURS[part])
        obj.location = (0, 0, 0)
    for part in ("eye_l", "eye_r", "teeth_upper", "tongue"):
        _mesh_object(part, tpl.parts[part].verts, tpl.parts[part].quads, collection, root, COLOURS[part])

    group = _empty("FDPs", collection, root, "fdps")
    for fdp_id, point in tpl.fdp_points().items():
        # the head's name after the id: Blender reads a name's last ".N" as a copy's number, so a second
        # head's "FDP 10.1" became "FDP 10.011", another FDP's name to the eye
        obj = _empty(f"FDP {fdp_id} ({root.name})", collection, group, "fdp", point, "SPHERE", FDP_SIZE_M)
        obj["headadapt_fdp"] = fdp_id
        obj["headadapt_label"] = tpl.meta["fdps"][fdp_id]["label"]
        obj.color = COLOURS["fdp"]
    group = _empty("Markers", collection, root, "markers")
    for marker, point in tpl.marker_points().items():
        obj = _empty(f"Marker {marker}", collection, group, "marker", point, "CUBE", FDP_SIZE_M)
        obj["headadapt_marker"] = marker
        obj.color = COLOURS["marker"]

    group = _empty("Muscles", collection, root, "muscles")
    for muscle in tpl.meta["muscles"]:
        ends = [tpl.surface_point(muscle["attachment"]), tpl.surface_point(muscle["insertion"])]
        obj = _link(_curve(muscle["name"], ends, collection, group, COLOURS["muscle"]), collection, group,
                    "muscle")
        obj["headadapt_muscle"] = muscle["name"]
    angles = np.linspace(0, 2 * np.pi, 48, endpoint=False)[:, None]
    for sph in tpl.meta["sphincters"]:
        a, b = (np.asarray(x) for x in sph["axes"])
        ring = np.asarray(sph["centre"]) + np.cos(angles) * a + np.sin(angles) * b
        obj = _link(_curve(sph["name"], ring, collection, group, COLOURS["sphincter"], cyclic=True), collection,
                    group, "sphincter")
        obj["headadapt_muscle"] = sph["name"]
    for obj in root.children_recursive:     # the helpers hidden until asked for (view.set_helpers_visible)
        if obj.get("headadapt_part") in HELPER_PARTS:
            obj.hide_set(True)                # the eye: still evaluated (world matrices right)
            obj.hide_render = True
    bpy.context.view_layer.update()   # world matrices of the new hierarchy
    return root


def template_objects(root):
    """{headadapt_part or name: object} of every object under a template root (recursive)."""
    out = {}
    for obj in root.children_recursive:
        key = obj.get("headadapt_part", obj.name)
        if key in ("fdp", "marker", "muscle", "sphincter", "legend_label"):
            key = obj.name
        out[key] = obj
    return out


def root_of(obj):
    """The head root (a result's or the template's) obj is or lies under, else None."""
    while obj is not None and obj.get("headadapt_part") not in ("result_root", "root"):
        obj = obj.parent
    return obj


def scan_results(sc, scan):
    """The result roots in scene sc made from the object scan (tagged "headadapt_scan" by Adapt)."""
    return [o for o in sc.objects if o.get("headadapt_part") == "result_root" and scan is not None
            and o.get("headadapt_scan") == scan]


def follow_scan(s, sc):
    """Point the panels at the scan's own state when the scan changes: its result (the one shown, if
    it is the scan's; else its last), that result's report, and the RMS of the scan's calibration. A
    result made before results were tagged with their scan is left as it is."""
    root = s.result_root
    if root is not None and root.get("headadapt_scan") is None and root.name in sc.objects:
        return
    mine = scan_results(sc, s.scan)
    if root not in mine:
        s.result_root = mine[-1] if mine else None
        s.report_json = s.result_root.get("headadapt_report", "") if s.result_root else ""
    cal = s.scan.get("headadapt_calibration") if s.scan is not None else None
    try:
        s.calibration_rms_mm = float(json.loads(cal)["rms"]) * 1000.0 if cal else -1.0
    except (ValueError, KeyError, TypeError):
        s.calibration_rms_mm = -1.0


def head_root(context):
    """The head expressions act on: the selected one (the active object is a head or lies under one),
    else the adaptation result if there is one, else the template."""
    picked = root_of(context.active_object) if context.active_object is not None else None
    if picked is not None and picked.name in context.scene.objects:
        return picked
    s = getattr(context.scene, "headadapt", None)
    chosen = s and (s.result_root or s.template_root)
    if chosen is not None:
        return chosen
    # a .blend the batch wrote (or one whose settings were lost): the roots are tagged on the objects
    roots = {o.get("headadapt_part"): o for o in context.scene.objects if o.get("headadapt_part") in
             ("result_root", "root")}
    return roots.get("result_root") or roots.get("root")


def adopt_tagged(sc):
    """A scene whose HeadAdapt settings are empty but which holds a result the batch wrote (tagged
    objects, no settings: the batch runs without the add-on): its result, report and scan (the one
    mesh carrying its landmarks) set, so the panels show them and their buttons act on them."""
    s = sc.headadapt
    if s.result_root is None:
        roots = [o for o in sc.objects if o.get("headadapt_part") == "result_root"]
        if len(roots) == 1:
            s.result_root = roots[0]
            if not s.report_json and "headadapt_report" in roots[0]:
                s.report_json = roots[0]["headadapt_report"]
    if s.scan is None:
        scans = [o for o in sc.objects if o.type == "MESH" and "headadapt_landmarks" in o]
        if len(scans) == 1:
            s.scan = scans[0]
