"""Operators: thin wrappers that gather arrays, call one core function, write results back, report.

The scan's mesh is never changed (its landmarks live in a custom property of the scan object);
results go to new objects in the "HeadAdapt result" collection. Every operator that changes the
scene is undoable.
"""

import json
import pathlib

import bpy
from bpy_extras.io_utils import ExportHelper, ImportHelper

from ..blender import bridge, landmarks, scene
from ..blender.scene import head_root
from ..core import mpeg4
from ..core.exceptions import HeadAdaptError


def template():
    """The bundled template (loaded once per session: core.template.bundled_template)."""
    from ..core.template import bundled_template
    return bundled_template()


def settings(context):
    return context.scene.headadapt


def scan_problem(context):
    """None when the scene has a usable scan, else what is wrong (for poll messages and reports)."""
    scan = settings(context).scan
    if scan is None:
        return "no scan selected: pick the scan object in the Scan panel"
    if scan.type != "MESH":
        return f"{scan.name!r} is not a mesh"
    if len(scan.data.polygons) == 0:
        return f"scan {scan.name!r} has no faces (a point cloud is not a surface)"
    return None


def missing_calibration_fdps(context):
    """Calibration FDPs not yet placed on the scan."""
    pts = landmarks.get_landmarks(settings(context).scan)
    return [k for k in mpeg4.CALIBRATION_FDPS if k not in pts]


def calibration_ready(context):
    """The scene has a usable scan with every calibration FDP placed."""
    return scan_problem(context) is None and not missing_calibration_fdps(context)


class _Base:
    bl_options = {"REGISTER", "UNDO"}

    def fail(self, msg):
        self.report({"ERROR"}, msg)
        return {"CANCELLED"}


class HEADADAPT_OT_add_template(_Base, bpy.types.Operator):
    """Add the bundled anatomical template (skin, skull, eyes, teeth, tongue, FDPs, muscles) to the scene"""
    bl_idname = "headadapt.add_template"
    bl_label = "Add Template"

    def execute(self, context):
        coll = bpy.data.collections.get("HeadAdapt template") or bpy.data.collections.new("HeadAdapt template")
        if coll.name not in context.scene.collection.children:
            context.scene.collection.children.link(coll)
        root = scene.add_template(template(), coll)
        settings(context).template_root = root
        self.report({"INFO"}, f"added the template: {len(template().skin.verts):,} skin vertices, "
                              f"{len(template().meta['fdps'])} FDPs")
        return {"FINISHED"}


class HEADADAPT_OT_use_active_as_scan(_Base, bpy.types.Operator):
    """Use the active mesh object as the scan"""
    bl_idname = "headadapt.use_active_as_scan"
    bl_label = "Use Active Object as Scan"

    @classmethod
    def poll(cls, context):
        obj = context.active_object
        return obj is not None and obj.type == "MESH" and "headadapt_part" not in obj

    def execute(self, context):
        obj = context.active_object
        if len(obj.data.polygons) == 0:
            return self.fail(f"{obj.name!r} has no faces: a scan must be a surface mesh")
        settings(context).scan = obj
        self.report({"INFO"}, f"scan: {obj.name} ({len(obj.data.vertices):,} vertices)")
        return {"FINISHED"}


class HEADADAPT_OT_import_landmarks(_Base, ImportHelper, bpy.types.Operator):
    """Import FDP landmarks for the scan from JSON or a MeshLab .pp file (scan coordinates)"""
    bl_idname = "headadapt.import_landmarks"
    bl_label = "Import Landmarks"
    filter_glob: bpy.props.StringProperty(default="*.json;*.pp", options={"HIDDEN"})

    @classmethod
    def poll(cls, context):
        return scan_problem(context) is None

    def execute(self, context):
        from ..core import meshio
        try:
            pts, meta = meshio.read_landmark_file(self.filepath)
        except HeadAdaptError as exc:
            return self.fail(str(exc))
        sha = meta.get("template_sha256")
        if sha and sha != template().meta["content_sha256"]:
            return self.fail(f"{pathlib.Path(self.filepath).name} was made for another template "
                             f"({sha[:12]}...), not this one ({template().meta['content_sha256'][:12]}...)")
        landmarks.set_landmarks(settings(context).scan, pts)
        self.report({"INFO"}, f"imported {len(pts)} FDPs")
        return {"FINISHED"}


class HEADADAPT_OT_export_landmarks(ExportHelper, bpy.types.Operator):
    """Export the scan's FDP landmarks as JSON or MeshLab .pp (scan coordinates)"""
    bl_idname = "headadapt.export_landmarks"
    bl_label = "Export Landmarks"
    filename_ext = ".json"
    filter_glob: bpy.props.StringProperty(default="*.json;*.pp", options={"HIDDEN"})

    def check(self, context):
        return False   # keep the user's extension (.json or .pp)

    @classmethod
    def poll(cls, context):
        return scan_problem(context) is None and bool(landmarks.get_landmarks(settings(context).scan))

    def execute(self, context):
        from ..core import meshio
        pts = landmarks.get_landmarks(settings(context).scan)
        try:
            meshio.write_landmarks(self.filepath, pts, template_sha256=template().meta["content_sha256"])
        except HeadAdaptError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        self.report({"INFO"}, f"wrote {len(pts)} FDPs to {self.filepath}")
        return {"FINISHED"}


class HEADADAPT_OT_clear_landmark(_Base, bpy.types.Operator):
    """Remove one FDP from the scan"""
    bl_idname = "headadapt.clear_landmark"
    bl_label = "Remove Landmark"
    fdp: bpy.props.StringProperty()

    def execute(self, context):
        scan = settings(context).scan
        pts = landmarks.get_landmarks(scan)
        pts.pop(self.fdp, None)
        landmarks.set_landmarks(scan, pts)
        return {"FINISHED"}


def _scan_arrays(context):
    scan = settings(context).scan
    verts, tris = bridge.mesh_arrays(scan, world=False)
    return scan, verts, tris


class HEADADAPT_OT_suggest_landmarks(_Base, bpy.types.Operator):
    """Propose every missing FDP on the scan from the placed ones (calibration + level-0 map, snapped to the surface)"""
    bl_idname = "headadapt.suggest_landmarks"
    bl_label = "Suggest the Rest"

    @classmethod
    def poll(cls, context):
        return calibration_ready(context)

    def execute(self, context):
        from ..core.adapt import suggest
        scan, verts, tris = _scan_arrays(context)
        try:
            proposed = suggest.suggest_fdps(template(), verts, tris, landmarks.get_landmarks(scan))
        except HeadAdaptError as exc:
            return self.fail(str(exc))
        landmarks.set_landmarks(scan, proposed, prop=landmarks.SUGGESTED_PROP)
        self.report({"INFO"}, f"suggested {len(proposed)} FDPs: accept them or move them")
        return {"FINISHED"}


class HEADADAPT_OT_accept_suggestions(_Base, bpy.types.Operator):
    """Accept the suggested FDPs as landmarks"""
    bl_idname = "headadapt.accept_suggestions"
    bl_label = "Accept Suggestions"

    @classmethod
    def poll(cls, context):
        scan = settings(context).scan
        return scan is not None and bool(landmarks.get_landmarks(scan, landmarks.SUGGESTED_PROP))

    def execute(self, context):
        scan = settings(context).scan
        pts = landmarks.get_landmarks(scan)
        sug = landmarks.get_landmarks(scan, landmarks.SUGGESTED_PROP)
        pts.update({k: v for k, v in sug.items() if k not in pts})
        landmarks.set_landmarks(scan, pts)
        del scan[landmarks.SUGGESTED_PROP]
        self.report({"INFO"}, f"{len(pts)} FDPs placed")
        return {"FINISHED"}


class HEADADAPT_OT_calibrate(_Base, bpy.types.Operator):
    """Compute the similarity that brings the scan into the template frame (paper sec 3.1)"""
    bl_idname = "headadapt.calibrate"
    bl_label = "Calibrate"

    @classmethod
    def poll(cls, context):
        return calibration_ready(context)

    def execute(self, context):
        from ..core.adapt import calibration
        s = settings(context)
        pts = landmarks.get_landmarks(s.scan)
        tpl_pts = template().fdp_points()
        try:
            given = calibration.validate_landmarks(pts, what=f"scan {s.scan.name!r}")
            given = {k: v for k, v in given.items() if k in tpl_pts}
            sim, info = calibration.calibrate(given, tpl_pts, method=s.calibration)
        except HeadAdaptError as exc:
            return self.fail(str(exc))
        s.calibration_rms_mm = info["rms"] * 1000.0
        s.scan["headadapt_calibration"] = json.dumps({"matrix": sim.matrix4().tolist(), **{
            k: v for k, v in info.items() if k != "residuals"}}, default=float)
        self.report({"INFO"}, f"calibrated ({info['method']}): RMS {s.calibration_rms_mm:.2f} mm over "
                              f"{len(given)} FDPs, scale {sim.scale:.4g}")
        return {"FINISHED"}


class HEADADAPT_OT_adapt(_Base, bpy.types.Operator):
    """Adapt the template onto the scan level by level; the result goes to a new 'HeadAdapt result' collection"""
    bl_idname = "headadapt.adapt"
    bl_label = "Adapt"
    levels: bpy.props.IntProperty(name="Levels", default=-1, min=-1, max=8,
                                  description="Levels after level 0 (-1: the scene setting)")

    @classmethod
    def poll(cls, context):
        return calibration_ready(context)

    def execute(self, context):
        from ..blender import blendout
        from ..core.adapt import AdaptOptions, adapt
        from ..core.adapt import outcome as outcome_text
        s = settings(context)
        problem = scan_problem(context)
        if problem:
            return self.fail(problem)
        scan, verts, tris = _scan_arrays(context)
        pts = landmarks.get_landmarks(scan)
        wm = context.window_manager
        wm.progress_begin(0, 100)
        try:
            opts = AdaptOptions(max_levels=s.max_levels if self.levels < 0 else self.levels,
                                calibration=s.calibration, drop_flagged=s.drop_flagged)
            result = adapt(template(), verts, tris, pts, opts,
                           progress=lambda f, msg: wm.progress_update(int(100 * f)))
        except HeadAdaptError as exc:
            return self.fail(str(exc))
        finally:
            wm.progress_end()
        report = result.report()
        s.report_json = json.dumps(report, default=float)
        root = blendout.build_result_objects(template(), result, context.scene, scan.matrix_world)
        s.result_root = root
        msg = (f"adapted: best level {result.best_level}, {outcome_text.verdict(result.outcome)}, "
               f"{result.seconds:.2f} s")
        turned = result.calibration_info.get("scan_pieces_turned", 0)
        if turned:
            msg += f"; {turned} scan piece(s) faced inward and were read turned round"
        warnings = outcome_text.warning_lines(result.outcome, result.flagged, result.dropped)
        if warnings:        # not ok (folds left, far from the scan) or flagged FDPs: say why (Report panel too)
            self.report({"WARNING"}, msg + "; " + "; ".join(warnings))
        else:
            self.report({"INFO"}, msg)
        return {"FINISHED"}


class HEADADAPT_OT_bake_expressions(_Base, bpy.types.Operator):
    """Simulate the skin for the chosen sets and bake them to shape keys, with a preview action"""
    bl_idname = "headadapt.bake_expressions"
    bl_label = "Bake Expressions"
    sets: bpy.props.EnumProperty(
        name="Sets", options={"ENUM_FLAG"}, default={"expression", "viseme", "fap", "arkit"},
        items=[("expression", "Expressions", "joy, sadness, anger, fear, disgust, surprise"),
               ("viseme", "Visemes", "the 14 MPEG-4 visemes"),
               ("fap", "FAPs", "one key per low-level FAP the anatomy can express"),
               ("arkit", "ARKit 52", "ARKit's 52 blendshapes (eyeBlinkLeft, jawOpen, ...), simulated")])
    preview: bpy.props.BoolProperty(name="Preview action", default=True,
                                    description="Keyframe the six expressions one after another")

    @classmethod
    def poll(cls, context):
        return head_root(context) is not None

    def execute(self, context):
        from ..blender import blendout
        root = head_root(context)
        if root is None:
            return self.fail("no head: add the template or adapt first")
        if not self.sets:
            return self.fail("choose at least one set to bake")
        wm = context.window_manager
        wm.progress_begin(0, 100)
        try:
            timing = blendout.bake_result(template(), root, kinds=tuple(self.sets), preview=self.preview,
                                          progress=lambda f, _name: wm.progress_update(int(100 * f)))
        except HeadAdaptError as exc:
            return self.fail(str(exc))
        finally:
            wm.progress_end()
        self.report({"INFO"}, f"baked {timing['keys']} shape keys on {root.name!r} "
                              f"({timing['per_key_s'] * 1000:.0f} ms per key)")
        return {"FINISHED"}


class HEADADAPT_OT_import_fap(_Base, ImportHelper, bpy.types.Operator):
    """Keyframe an MPEG-4 .fap animation on the baked shape keys"""
    bl_idname = "headadapt.import_fap"
    bl_label = "Import .fap"
    filename_ext = ".fap"
    filter_glob: bpy.props.StringProperty(default="*.fap", options={"HIDDEN"})

    @classmethod
    def poll(cls, context):
        return head_root(context) is not None

    def execute(self, context):
        from ..blender import animation
        from ..core.fapfile import read_fap
        root = head_root(context)
        try:
            anim = read_fap(self.filepath)
            counts = animation.import_fap(root, anim)
        except HeadAdaptError as exc:
            return self.fail(str(exc))
        self.report({"INFO"}, f"{pathlib.Path(self.filepath).name}: {len(anim.frames)} frames at {anim.fps:g} fps; "
                              + ", ".join(f"{v} {k}" for k, v in counts.items()))
        return {"FINISHED"}


classes = (HEADADAPT_OT_add_template, HEADADAPT_OT_use_active_as_scan, HEADADAPT_OT_import_landmarks,
           HEADADAPT_OT_export_landmarks, HEADADAPT_OT_clear_landmark, HEADADAPT_OT_suggest_landmarks,
           HEADADAPT_OT_accept_suggestions, HEADADAPT_OT_calibrate, HEADADAPT_OT_adapt,
           HEADADAPT_OT_bake_expressions, HEADADAPT_OT_import_fap)


register, unregister = bpy.utils.register_classes_factory(classes)
