"""Operators: thin wrappers that gather arrays, call one core function, write results back, report.

The scan's mesh is never changed (its landmarks live in a custom property of the scan object);
results go to new objects in the "HeadAdapt result" collection. Every operator that changes the
scene is undoable.
"""

import pathlib

import bpy
from bpy_extras.io_utils import ExportHelper, ImportHelper

from ..blender import bridge, landmarks, scene
from ..blender.scene import head_root
from ..core import mpeg4, threads
from ..core.adapt.options import MAX_LEVELS
from ..core.exceptions import HeadAdaptError
from . import jobs, kept
from .jobs import Modal
from .props import apply_display
from .runs import AdaptRun, BakeRun, CalibrateRun, SuggestRun, match_scene_unit
from .state import landmark_problem, scan_problem, settings, template


def poll_with_message(cls, problem):
    """poll()'s answer: True without a problem, else False with the problem as the greyed button's tooltip."""
    if not problem and jobs.busy() and getattr(cls, "long_run", False):
        problem = f"{jobs.busy()} is running: wait for it, or press Esc to cancel it"
    if problem:
        cls.poll_message_set(problem[:1].upper() + problem[1:])
        return False
    return True


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
        apply_display(settings(context), context)
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
        if obj is None:
            return poll_with_message(cls, "no active object: click the scan in the viewport first")
        if obj.type != "MESH":
            return poll_with_message(cls, f"the active object {obj.name!r} is not a mesh")
        if "headadapt_part" in obj:
            return poll_with_message(cls, f"{obj.name!r} is part of a HeadAdapt head, not a scan")
        return True

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
        return poll_with_message(cls, scan_problem(context))

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
        problem = scan_problem(context)
        if problem is None and not landmarks.get_landmarks(settings(context).scan):
            problem = "no landmarks on the scan to export"
        return poll_with_message(cls, problem)

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


class HEADADAPT_OT_suggest_landmarks(Modal, _Base, bpy.types.Operator):
    """Propose every missing FDP on the scan where the adaptation from the placed ones puts it, snapped to the surface (Esc cancels)"""
    bl_idname = "headadapt.suggest_landmarks"
    bl_label = "Suggest the Rest"
    long_run = True                  # one run at a time (jobs.busy): greyed while an Adapt or a Bake runs

    @classmethod
    def poll(cls, context):
        return poll_with_message(cls, landmark_problem(context))

    def make_run(self, context):
        try:
            return SuggestRun(context)
        except HeadAdaptError as exc:
            return str(exc)


def _suggestions_problem(context, fdp=""):
    scan = settings(context).scan
    sug = landmarks.get_landmarks(scan, landmarks.SUGGESTED_PROP) if scan is not None else {}
    if not sug:
        return "no suggestions yet: press Suggest the Rest first"
    if fdp and fdp not in sug:
        return f"FDP {fdp} is not among the suggestions"
    return None


def _take_suggestions(scan, names):
    """Remove the named suggestions from the scan; returns {name: point} of those removed."""
    sug = landmarks.get_landmarks(scan, landmarks.SUGGESTED_PROP)
    taken = {k: sug.pop(k) for k in names if k in sug}
    if sug:
        landmarks.set_landmarks(scan, sug, prop=landmarks.SUGGESTED_PROP)
    elif landmarks.SUGGESTED_PROP in scan:
        del scan[landmarks.SUGGESTED_PROP]
    return taken


class _Suggestions(_Base):
    """Accept or Reject Suggestions: one suggestion (the operator's fdp) or, fdp empty, all of them."""

    @classmethod
    def poll(cls, context):
        return poll_with_message(cls, _suggestions_problem(context))

    def take(self, context):
        """(the scan, {name: point} of the suggestions taken off it), or (None, the problem)."""
        problem = _suggestions_problem(context, self.fdp)
        if problem:
            return None, problem
        scan = settings(context).scan
        names = [self.fdp] if self.fdp else list(landmarks.get_landmarks(scan, landmarks.SUGGESTED_PROP))
        return scan, _take_suggestions(scan, names)

    def named(self, taken):
        return ", ".join(taken) if self.fdp else f"{len(taken)} suggestions"


class HEADADAPT_OT_accept_suggestions(_Suggestions, bpy.types.Operator):
    """Accept suggested FDPs as landmarks: one (fdp), or all of them"""
    bl_idname = "headadapt.accept_suggestions"
    bl_label = "Accept Suggestions"
    fdp: bpy.props.StringProperty(name="FDP", default="", description="The suggestion to accept (empty: all)")

    def execute(self, context):
        scan, taken = self.take(context)
        if scan is None:
            return self.fail(taken)
        pts = landmarks.get_landmarks(scan)
        pts.update({k: v for k, v in taken.items() if k not in pts})
        landmarks.set_landmarks(scan, pts)
        self.report({"INFO"}, f"accepted {self.named(taken)}: {len(pts)} FDPs placed")
        return {"FINISHED"}


class HEADADAPT_OT_reject_suggestions(_Suggestions, bpy.types.Operator):
    """Reject suggested FDPs: one (fdp), or all of them; placed landmarks are not touched"""
    bl_idname = "headadapt.reject_suggestions"
    bl_label = "Reject Suggestions"
    fdp: bpy.props.StringProperty(name="FDP", default="", description="The suggestion to reject (empty: all)")

    def execute(self, context):
        scan, taken = self.take(context)
        if scan is None:
            return self.fail(taken)
        self.report({"INFO"}, f"rejected {self.named(taken)}")
        return {"FINISHED"}


class HEADADAPT_OT_load_sample_scan(_Base, bpy.types.Operator):
    """Load the sample scan shipped with HeadAdapt (a synthetic head, mm) as the scan, to try the workflow"""
    bl_idname = "headadapt.load_sample_scan"
    bl_label = "Load Sample Scan"
    with_landmarks: bpy.props.BoolProperty(name="With its landmarks", default=False,
                                           description="Also set the sample's landmark file (all FDPs)")

    def execute(self, context):
        from ..batch import SAMPLE_DIR
        from ..core import meshio
        try:
            verts, tris = meshio.read_mesh(SAMPLE_DIR / "scan.ply")
            pts = meshio.read_landmarks(SAMPLE_DIR / "landmarks.json") if self.with_landmarks else {}
        except (HeadAdaptError, OSError) as exc:
            return self.fail(f"the sample scan cannot be read: {exc}")
        obj = bpy.data.objects.new("sample scan", bridge.new_mesh("sample scan", verts, tris))
        context.scene.collection.objects.link(obj)
        if pts:
            landmarks.set_landmarks(obj, pts)
        settings(context).scan = obj
        for other in context.view_layer.objects.selected:
            other.select_set(False)
        obj.select_set(True)
        context.view_layer.objects.active = obj
        unit = match_scene_unit(context, 0.001)              # the sample is in mm
        self.report({"INFO"}, f"sample scan: {len(verts):,} vertices, {len(pts)} landmarks; "
                              + ("Calibrate and Adapt" if pts else f"click {', '.join(mpeg4.CLICKS_8)}")
                              + (f"; the scene's unit is now the sample's ({unit})" if unit else ""))
        return {"FINISHED"}


class HEADADAPT_OT_calibrate(Modal, _Base, bpy.types.Operator):
    """Compute the similarity that brings the scan into the template frame (paper sec 3.1; Esc cancels)"""
    bl_idname = "headadapt.calibrate"
    bl_label = "Calibrate"

    @classmethod
    def poll(cls, context):
        return poll_with_message(cls, landmark_problem(context))

    def make_run(self, context):
        try:
            return CalibrateRun(context)
        except HeadAdaptError as exc:
            settings(context).calibration_rms_mm = -1.0          # the earlier tick no longer speaks for the clicks
            return str(exc)


class HEADADAPT_OT_adapt(Modal, _Base, bpy.types.Operator):
    """Adapt the template onto the scan level by level (Esc cancels); the result replaces the previous one (or is kept beside it)"""
    bl_idname = "headadapt.adapt"
    bl_label = "Adapt"
    long_run = True                  # greyed while an Adapt or a Bake runs (jobs.busy)
    levels: bpy.props.IntProperty(name="Levels", default=-1, min=-1, max=MAX_LEVELS,
                                  description="Levels after level 0 (-1: the scene setting)")

    @classmethod
    def poll(cls, context):
        return poll_with_message(cls, landmark_problem(context))

    def make_run(self, context):
        return landmark_problem(context) or AdaptRun(context, self.levels)


class HEADADAPT_OT_bake_expressions(Modal, _Base, bpy.types.Operator):
    """Simulate the skin for the chosen sets and bake them to shape keys, with a preview action (Esc cancels)"""
    bl_idname = "headadapt.bake_expressions"
    bl_label = "Bake Expressions"
    long_run = True
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
        if head_root(context) is None:
            return poll_with_message(cls, "no head in the scene: add the template or adapt first")
        return poll_with_message(cls, "")

    def make_run(self, context):
        root = head_root(context)
        if root is None:
            return "no head: add the template or adapt first"
        if not self.sets:
            return "choose at least one set to bake"
        return BakeRun(root, tuple(self.sets), self.preview)


class HEADADAPT_OT_import_fap(_Base, ImportHelper, bpy.types.Operator):
    """Keyframe an MPEG-4 .fap animation on the baked shape keys"""
    bl_idname = "headadapt.import_fap"
    bl_label = "Import .fap"
    filename_ext = ".fap"
    filter_glob: bpy.props.StringProperty(default="*.fap", options={"HIDDEN"})

    @classmethod
    def poll(cls, context):
        if head_root(context) is None:
            return poll_with_message(cls, "no head in the scene: add the template or adapt first")
        return True

    def execute(self, context):
        from ..blender import animation
        from ..core.fapfile import read_fap
        root = head_root(context)
        name = pathlib.Path(self.filepath).name
        try:
            anim = read_fap(self.filepath)
        except HeadAdaptError as exc:
            return self.fail(str(exc))
        try:
            counts = animation.import_fap(root, anim)
        except HeadAdaptError as exc:
            return self.fail(f"{self.filepath}: {exc}")
        clipped, unbaked, merged = counts.pop("clipped"), counts.pop("unbaked"), counts.pop("lip_pairs_merged")
        self.report({"INFO"}, f"{name}: {len(anim.frames)} frames at {anim.fps:g} fps; "
                              + ", ".join(f"{v} {k}" for k, v in counts.items()))
        if merged:
            self.report({"INFO"}, f"{name}: {merged} inner and outer lip FAP pair{'s' if merged != 1 else ''} "
                                  "given together: the stronger of each plays, as their keys are one lip's motion")
        if unbaked:
            self.report({"WARNING"}, f"{name}: {len(unbaked)} key{'s' if len(unbaked) != 1 else ''} the file asks for "
                                     f"{'are' if len(unbaked) != 1 else 'is'} not baked on {root.name!r}, so not "
                                     f"played: {', '.join(unbaked[:12])}{' ...' if len(unbaked) > 12 else ''} "
                                     "(bake their set first)")
        if clipped:
            self.report({"WARNING"}, f"{name}: {len(clipped)} key{'s' if len(clipped) != 1 else ''} asked beyond what a shape key plays (-10 to 10 "
                                     "times the baked amplitude), cut there: " + ", ".join(
                                         f"{k} {v:.3g}" for k, v in sorted(clipped.items())))
        return {"FINISHED"}


class HEADADAPT_OT_save_picture(ExportHelper, bpy.types.Operator):
    """Save a picture of the result: the scan beside the adapted head with its heat map, front and side
    (PNG, 1280x1280, Workbench), as the batch's --preview writes it"""
    bl_idname = "headadapt.save_picture"
    bl_label = "Save Picture"
    filename_ext = ".png"
    filter_glob: bpy.props.StringProperty(default="*.png", options={"HIDDEN"})

    @classmethod
    def poll(cls, context):
        problem = scan_problem(context)
        if problem is None and settings(context).result_root is None:
            problem = "no result yet: adapt first"
        return poll_with_message(cls, problem)

    def execute(self, context):
        from ..blender import blendout
        s = settings(context)
        if not self.filepath.lower().endswith(".png"):
            self.report({"ERROR"}, f"{self.filepath}: name a .png file")
            return {"CANCELLED"}
        try:
            blendout.render_preview(self.filepath, s.result_root, s.scan)
        except HeadAdaptError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        self.report({"INFO"}, f"saved the picture of {s.result_root.name} beside {s.scan.name} to {self.filepath}")
        return {"FINISHED"}


classes = (HEADADAPT_OT_add_template, HEADADAPT_OT_use_active_as_scan, HEADADAPT_OT_import_landmarks,
           HEADADAPT_OT_export_landmarks, HEADADAPT_OT_clear_landmark, HEADADAPT_OT_suggest_landmarks,
           HEADADAPT_OT_accept_suggestions, HEADADAPT_OT_reject_suggestions, HEADADAPT_OT_load_sample_scan,
           HEADADAPT_OT_calibrate, HEADADAPT_OT_adapt,
           HEADADAPT_OT_bake_expressions, HEADADAPT_OT_import_fap, HEADADAPT_OT_save_picture)


_register_classes, _unregister_classes = bpy.utils.register_classes_factory(classes)


@bpy.app.handlers.persistent
def _forget_kept(*_args):
    """Another file loaded: its scans are others (and the memory is freed); a running Adapt or Bake,
    whose operator the load ended, is cancelled (else its buttons would stay greyed), and a progress
    line the file was saved with (during an Adapt) is cleared. A .blend the batch wrote (no settings:
    the batch runs without the add-on) gets its scan, result and report in the panels."""
    kept.forget()
    jobs.drop_all(bpy.context.window_manager)
    for sc in _ours(bpy.data.scenes):
        sc.headadapt.progress_text = ""
        scene.adopt_tagged(sc)


def _ours(scenes):
    """The scenes with HeadAdapt's settings (registered)."""
    return [sc for sc in scenes if getattr(sc, "headadapt", None) is not None]


def register():
    _register_classes()
    bpy.app.handlers.load_post.append(_forget_kept)


def unregister():
    if _forget_kept in bpy.app.handlers.load_post:
        bpy.app.handlers.load_post.remove(_forget_kept)
    kept.forget()
    try:                           # (Blender quitting, or disabling at start: no data to reach)
        wm, scenes = bpy.context.window_manager, list(bpy.data.scenes)
    except AttributeError:
        wm, scenes = None, []
    jobs.drop_all(wm)
    threads.shutdown()             # (the fit's worker threads: none left behind by a disabled add-on)
    for sc in _ours(scenes):       # the setting outlives the add-on in the file: no stale progress line
        sc.headadapt.progress_text = ""
    _unregister_classes()
