"""Operators: thin wrappers that gather arrays, call one core function, write results back, report.

The scan's mesh is never changed (its landmarks live in a custom property of the scan object);
results go to new objects in the "HeadAdapt result" collection. Every operator that changes the
scene is undoable.
"""

import json
import pathlib

import bpy
import numpy as np
from bpy_extras.io_utils import ExportHelper, ImportHelper

from ..blender import bridge, landmarks, scene
from ..blender.scene import head_root
from ..core import mpeg4, threads
from ..core.adapt.options import MAX_LEVELS
from ..core.exceptions import HeadAdaptError
from . import jobs, kept
from .jobs import Job, Modal, Run
from .props import apply_display


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
    if context.scene.objects.get(scan.name) != scan:
        return f"the scan {scan.name!r} is not in the scene (deleted?): pick the scan object in the Scan panel"
    scale = scan.matrix_world.to_scale()
    if max(scale) - min(scale) > 1e-4 * max(abs(max(scale)), 1e-12):
        # the result's root takes the scan's transform, and an object cannot hold the shear that a
        # stretch and the fit's turn make together: the head would be drawn off the scan
        return (f"the scan {scan.name!r} is scaled unevenly ({', '.join(f'{c:g}' for c in scale)}): apply "
                "its scale first (Object > Apply > Scale)")
    if len(scan.data.polygons) == 0:
        return f"scan {scan.name!r} has no faces (a point cloud is not a surface)"
    return None


def visible_template_fdps():
    """The template FDPs a scanner can see ({id: (3,)} template frame): the ones adapt calibrates on."""
    from ..core.adapt.options import SCANNER_VISIBLE_PARTS
    tpl = template()
    return {k: p for k, p in tpl.fdp_points().items() if tpl.meta["fdps"][k]["part"] in SCANNER_VISIBLE_PARTS}


def landmark_problem(context):
    """None when the scan and its landmarks are what the batch's adapt accepts (core.adapt.calibration:
    at least MIN_FDPS visible FDPs, finite, distinct, not on one line or plane; the paper's method
    also needs its 8), else what is missing, as a sentence for a poll message or a report."""
    from ..core.adapt import calibration
    problem = scan_problem(context)
    if problem:
        return problem
    s = settings(context)
    pts = landmarks.get_landmarks(s.scan)
    if not pts:
        return (f"no landmarks on {s.scan.name!r}: click at least {calibration.MIN_FDPS} FDPs "
                f"(best {', '.join(mpeg4.CLICKS_8)}) or import a landmark file")
    try:
        given = calibration.validate_landmarks(pts, what=f"scan {s.scan.name!r}")
    except HeadAdaptError as exc:
        return str(exc)
    visible = visible_template_fdps()
    usable = [k for k in given if k in visible]
    if len(usable) < calibration.MIN_FDPS:
        return (f"{len(usable)} of the placed FDPs lie on the skin or the eyes; calibration needs at least "
                f"{calibration.MIN_FDPS} (best {', '.join(mpeg4.CLICKS_8)})")
    if s.calibration == "paper":
        missing = [k for k in mpeg4.CALIBRATION_FDPS if k not in given]
        if missing:
            return ("the paper's calibration needs FDP " + ", ".join(missing)
                    + ": place them or choose Auto or Least squares")
    return None


def calibration_ready(context):
    """The scene has a usable scan with enough landmarks to calibrate and adapt (the batch's rule)."""
    return landmark_problem(context) is None


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


def _scan_arrays(context):
    scan = settings(context).scan
    verts, tris = bridge.mesh_arrays(scan, world=False)
    return scan, verts, tris


class SuggestRun(Run):
    """One Suggest the Rest: the clicks judged as Calibrate judges them and the adaptation from them on
    a Job (about 1 s at 31k vertices, 2 s as a first press on 1M), the suggestions written at the end."""
    what = "Suggest the Rest"

    def __init__(self, context):
        from ..core.adapt import suggest
        self.clicks = clicks = gather_clicks(context)
        self.scan = clicks.scan

        def work(say):
            say(0.0, "judging the clicks")
            answer, _rms = judge_clicks(clicks)
            fit, sim = answer[0], answer[3]
            # where the adaptation from these clicks puts the rest (the scan as that judging prepared
            # it, not prepared again), snapped to that scan (its tree made already; a dense scan's clusters)
            wrong = {}
            proposed = suggest.suggest_fdps(clicks.tpl, clicks.verts, clicks.tris, clicks.pts,
                                            snap=suggest.snap_to_prepared(fit.scan, sim), options=clicks.options,
                                            calibrated=answer, flagged=wrong,
                                            progress=lambda f, msg: say(0.05 + 0.95 * f, msg))
            return answer, proposed, wrong

        self.work = work
        self.job = Job(work)

    def needs(self):
        return (self.scan,)

    def finish(self, context, value, report):
        answer, proposed, wrong = value
        kept.keep(self.clicks.key, answer)           # for the Adapt that follows (ui/kept.py)
        now = landmarks.get_landmarks(self.scan)
        if set(now) != set(self.clicks.pts) or any(not np.array_equal(now[k], self.clicks.pts[k]) for k in now):
            report({"WARNING"}, "the clicks changed while Suggest the Rest ran: nothing suggested; press it again")
            return {"CANCELLED"}
        if not proposed:
            report({"INFO"}, "every FDP a scanner sees is placed already: nothing to suggest")
            return {"FINISHED"}
        landmarks.set_landmarks(self.scan, proposed, prop=landmarks.SUGGESTED_PROP)
        landmarks.set_flagged(self.scan, wrong, self.clicks.pts)      # marked in the list until moved
        msg = f"suggested {len(proposed)} FDPs: accept or reject them one by one, or all at once"
        if wrong:           # the fit they came from judged a click wrong: say which, before it is built on
            report({"WARNING"}, msg + "; the fit judges a click wrong: " + "; ".join(
                f"FDP {k} ({mpeg4.FDPS[k].label}): {why}" for k, why in wrong.items()) + ": move it or clear it")
        else:
            report({"INFO"}, msg)
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


class HEADADAPT_OT_accept_suggestions(_Base, bpy.types.Operator):
    """Accept suggested FDPs as landmarks: one (fdp), or all of them"""
    bl_idname = "headadapt.accept_suggestions"
    bl_label = "Accept Suggestions"
    fdp: bpy.props.StringProperty(name="FDP", default="", description="The suggestion to accept (empty: all)")

    @classmethod
    def poll(cls, context):
        return poll_with_message(cls, _suggestions_problem(context))

    def execute(self, context):
        problem = _suggestions_problem(context, self.fdp)
        if problem:
            return self.fail(problem)
        scan = settings(context).scan
        names = [self.fdp] if self.fdp else list(landmarks.get_landmarks(scan, landmarks.SUGGESTED_PROP))
        pts = landmarks.get_landmarks(scan)
        taken = _take_suggestions(scan, names)
        pts.update({k: v for k, v in taken.items() if k not in pts})
        landmarks.set_landmarks(scan, pts)
        self.report({"INFO"}, f"accepted {', '.join(taken) if self.fdp else f'{len(taken)} suggestions'}: "
                              f"{len(pts)} FDPs placed")
        return {"FINISHED"}


class HEADADAPT_OT_reject_suggestions(_Base, bpy.types.Operator):
    """Reject suggested FDPs: one (fdp), or all of them; placed landmarks are not touched"""
    bl_idname = "headadapt.reject_suggestions"
    bl_label = "Reject Suggestions"
    fdp: bpy.props.StringProperty(name="FDP", default="", description="The suggestion to reject (empty: all)")

    @classmethod
    def poll(cls, context):
        return poll_with_message(cls, _suggestions_problem(context))

    def execute(self, context):
        problem = _suggestions_problem(context, self.fdp)
        if problem:
            return self.fail(problem)
        scan = settings(context).scan
        names = [self.fdp] if self.fdp else list(landmarks.get_landmarks(scan, landmarks.SUGGESTED_PROP))
        taken = _take_suggestions(scan, names)
        self.report({"INFO"}, f"rejected {', '.join(taken) if self.fdp else f'{len(taken)} suggestions'}")
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


class HEADADAPT_OT_calibrate(_Base, bpy.types.Operator):
    """Compute the similarity that brings the scan into the template frame (paper sec 3.1)"""
    bl_idname = "headadapt.calibrate"
    bl_label = "Calibrate"

    @classmethod
    def poll(cls, context):
        return poll_with_message(cls, landmark_problem(context))

    def execute(self, context):
        s = settings(context)
        s.calibration_rms_mm = -1.0
        try:
            _verts, _tris, (_fit, _tpl_fdps, q_fdp, sim, info), rms_mm = check_clicks(context)
        except HeadAdaptError as exc:
            return self.fail(str(exc))
        head_mm = head_size_mm()
        s.calibration_rms_mm = rms_mm
        s.scan["headadapt_calibration"] = json.dumps({"matrix": sim.matrix4().tolist(), **{
            k: v for k, v in info.items() if k != "residuals"}}, default=float)
        notes = info["handedness"]["notes"]
        msg = (f"calibrated ({info['method']}): RMS {rms_mm:.2f} mm over {len(q_fdp)} FDPs "
               f"({100 * rms_mm / head_mm:.1f}% of the head's width), scan unit = {1000 * sim.scale:.4g} mm")
        if notes:
            self.report({"WARNING"}, msg + "; " + "; ".join(notes))
        else:
            self.report({"INFO"}, msg)
        return {"FINISHED"}


def check_clicks(context):
    """The batch's step 1 on the scene's clicks (labels put right, the similarity, every click on the
    scan), the RMS judged against the head's width: (the scan's verts and tris as read, pipeline.calibrate's
    answer (fit, template FDPs, clicked FDPs, similarity, info), RMS mm), or a HeadAdaptError naming the
    cause (too few, another unit, wrong names, a mirrored scan)."""
    clicks = gather_clicks(context)
    answer, rms_mm = judge_clicks(clicks)
    kept.keep(clicks.key, answer)           # for the Adapt that follows (ui/kept.py)
    return clicks.verts, clicks.tris, answer, rms_mm


def gather_clicks(context):
    """What judging the scene's clicks needs, read in the main thread (the scan's arrays, its clicks,
    the options, their digest, the template), or a HeadAdaptError naming what is missing."""
    from types import SimpleNamespace
    problem = landmark_problem(context)
    if problem:
        raise HeadAdaptError(problem)
    scan, verts, tris = _scan_arrays(context)
    pts = landmarks.get_landmarks(scan)
    options = adapt_options(settings(context))
    return SimpleNamespace(scan=scan, verts=verts, tris=tris, pts=pts, options=options, tpl=template(),
                           key=kept.digest(verts, tris, pts, options), head_mm=head_size_mm())


def judge_clicks(clicks):
    """gather_clicks' clicks judged (numpy only: a worker thread may run it): (pipeline.calibrate's
    answer, its RMS in mm), the answer kept from the last judging of the same scan, clicks and options
    if there is one; or a HeadAdaptError naming the cause (another unit, wrong names, a mirrored scan)."""
    from ..core.adapt import calibration, pipeline
    answer = kept.get(clicks.key)           # the same scan, clicks and options judged before: as it was
    try:
        if answer is None:
            answer = pipeline.calibrate(clicks.tpl, clicks.verts, clicks.tris, clicks.pts, clicks.options)
            pipeline.check_on_surface(answer[0].scan, answer[2], clicks.options)
    except HeadAdaptError as exc:
        hint = calibration.unit_hint(clicks.verts, clicks.pts)
        raise HeadAdaptError(str(exc) + (f"; {hint}" if hint and hint.lower() not in str(exc).lower() else "")) from exc
    rms_mm = answer[4]["rms"] * 1000.0
    head_mm = clicks.head_mm
    if rms_mm > CALIBRATION_RMS_LIMIT * head_mm:
        raise HeadAdaptError(f"the landmarks do not fit the template's face: calibration RMS {rms_mm:.1f} mm is "
                             f"{100 * rms_mm / head_mm:.0f}% of the head's width ({head_mm:.0f} mm; limit "
                             f"{100 * CALIBRATION_RMS_LIMIT:.0f}%): FDPs given the wrong names, or a mirrored scan")
    return answer, rms_mm


CALIBRATION_RMS_LIMIT = 0.05     # of the head's width: people's faces differ from the template's by 1-3%


def head_size_mm():
    """The template head's width (ear to ear), mm: what calibration residuals are judged against."""
    return float(np.ptp(template().skin.verts[:, 0])) * 1000.0


def adapt_options(s, levels=-1):
    """The AdaptOptions of the scene settings s (levels >= 0 overrides s.max_levels): the one place the
    panels make their options, from the same fields and defaults as the batch (batch.adapt_options)."""
    from ..batch import adapt_options as batch_options
    return batch_options(levels=s.max_levels if levels < 0 else levels, calibration=s.calibration,
                         keep_flagged=not s.drop_flagged)


def remove_result(root):
    """Delete a result hierarchy (the root, everything under it, their meshes and curves) and its
    collection when that is left empty."""
    objs = [root, *root.children_recursive]
    colls = {c for o in objs for c in o.users_collection}
    datas = [o.data for o in objs if o.data is not None]
    for o in objs:
        bpy.data.objects.remove(o, do_unlink=True)
    for d in datas:
        if d.users == 0:
            (bpy.data.meshes if isinstance(d, bpy.types.Mesh) else bpy.data.curves).remove(d)
    for c in colls:
        if c.name in bpy.data.collections and not c.all_objects:
            bpy.data.collections.remove(c)


def leave_edit_mode(context, root):
    """Object Mode, when the object in Edit Mode is root or lies under it (its edits kept): the name of
    that object, else None. Keys written or objects removed under Edit Mode are lost or left dangling."""
    obj = context.view_layer.objects.active if context.view_layer else None
    if obj is None or obj.mode != "EDIT" or scene.root_of(obj) != root:
        return None
    obj.update_from_editmode()
    bpy.ops.object.mode_set(mode="OBJECT")
    return obj.name


def match_scene_unit(context, scale):
    """A scene still in Blender's default unit (metres, scale 1) takes the scan's (scale: metres per scan
    unit, blendout.set_scene_unit), as the batch's .blend does, so a scan in mm reads as a head of
    250 mm, not 250 m: the unit's name (lower case), or None when nothing changed."""
    from ..blender import blendout
    u = context.scene.unit_settings
    if (u.system, u.scale_length, u.length_unit) != ("METRIC", 1.0, "METERS"):
        return None
    blendout.set_scene_unit(context.scene, scale)
    return None if u.length_unit == "METERS" else u.length_unit.lower()


class AdaptRun(Run):
    """One Adapt of the scene's scan: the fit and the anatomy transfer on a Job, the result objects
    built in the main thread when it is done."""
    what = "Adapt"

    def __init__(self, context, levels=-1):
        import time

        from ..core.adapt import adapt
        from ..core.anatomy import transfer
        self.t0 = time.perf_counter()
        s = settings(context)
        self.scan, verts, tris = _scan_arrays(context)
        self.pts = pts = landmarks.get_landmarks(self.scan)
        opts = adapt_options(s, levels)
        tpl = template()
        # the scan as the last Calibrate prepared it, if that was this scan with these clicks and options:
        # this run's alone until it is done (ui/kept.py)
        self.key = kept.digest(verts, tris, pts, opts)
        self.calibrated = calibrated = kept.take(self.key)

        def work(say):
            result = adapt(tpl, verts, tris, pts, opts, progress=lambda f, msg: say(0.9 * f, msg),
                           calibrated=calibrated)
            say(0.9, "carrying the anatomy along")
            return result, transfer(tpl, result)

        self.work = work
        self.job = Job(work)

    def needs(self):
        return (self.scan,)

    def finish(self, context, value, report):
        """Build the result objects (replacing the last result unless kept), store the report, say how it went."""
        import time
        result, anatomy = value
        if self.calibrated is not None:
            kept.keep(self.key, self.calibrated)      # for the next Adapt of the same

        from ..blender import blendout
        from ..core.adapt import outcome as outcome_text
        s = settings(context)
        jobs.show_progress(context, 1.0, "building the result objects")
        # the last result of this scan is replaced (one made before results were tagged with their
        # scan: the one shown); other scans' results stay
        old = s.result_root
        if old is not None and old.get("headadapt_scan") not in (None, self.scan):
            old = None
        mine = scene.scan_results(context.scene, self.scan)
        if old is None and mine:
            old = mine[-1]
        replaced = None
        if old is not None and not s.keep_results and old.name in bpy.data.objects:
            replaced = old.name
            leave_edit_mode(context, old)
            remove_result(old)
        root = blendout.build_result_objects(template(), result, context.scene, self.scan.matrix_world,
                                             anatomy=anatomy, name=self.scan.name)
        root["headadapt_scan"] = self.scan
        if s.scan != self.scan:
            s.scan = self.scan
        s.report_json = json.dumps(result.report(), default=float)
        s.result_root = root
        landmarks.set_flagged(self.scan, result.flagged, self.pts)     # marked in the list until moved
        if context.view_layer.objects.active is None:      # the replaced result was the active object
            context.view_layer.objects.active = root
        apply_display(s, context)          # heat map on, scan as wire, helpers as the toggles say
        msg = (f"adapted: best level {result.best_level}, {outcome_text.verdict(result.outcome)}, "
               f"{time.perf_counter() - self.t0:.1f} s")
        if replaced:
            msg += f"; it replaces the earlier result {replaced!r} (Keep earlier results keeps them)"
        unit = match_scene_unit(context, result.similarity.scale)
        if unit:
            msg += f"; the scene's unit is now the scan's ({unit})"
        mods = [m.name for m in self.scan.modifiers if m.show_viewport]
        if mods:
            msg += (f"; the scan's modifiers ({', '.join(mods)}) were not applied: the fit is on its mesh "
                    "without them")
        turned = result.calibration_info.get("scan_pieces_turned", 0)
        if turned:
            msg += f"; {turned} scan piece(s) faced inward and were read turned round"
        clustered = result.calibration_info.get("scan_clustered")
        if clustered:
            msg += (f"; the dense scan was fitted on its {clustered['kept']:,} clusters "
                    f"({clustered['cell_mm']:g} mm grid)")
        warnings = outcome_text.warning_lines(result.outcome, result.flagged, result.dropped)
        if warnings:        # not ok (folds left, far from the scan) or flagged FDPs: say why (Report panel too)
            report({"WARNING"}, msg + "; " + "; ".join(warnings))
        else:
            report({"INFO"}, msg)
        return {"FINISHED"}


class BakeRun(Run):
    """One Bake of the head's expressions: the simulation on a Job, the shape keys written at the end."""
    what = "Bake"

    def __init__(self, root, kinds, preview):
        from ..blender import animation
        from ..core.skin import bake
        self.root, self.kinds, self.preview = root, kinds, preview
        tpl, anatomy = template(), animation.stored_anatomy(template(), root)
        self.rest = animation.written_rest(tpl, anatomy)

        def work(say):
            return bake.bake(tpl, anatomy, kinds=kinds, progress=lambda f, name: say(f, f"baking {name}"))

        self.work = work
        self.job = Job(work)

    def needs(self):
        return (self.root,)

    def finish(self, context, value, report):
        from ..blender import blendout
        jobs.show_progress(context, 1.0, "writing the shape keys")
        # keys written under Edit Mode are lost when it is left (its own copy of the mesh wins)
        left = leave_edit_mode(context, self.root)
        timing = blendout.apply_bake(self.root, *value, self.kinds, self.preview, self.rest)
        cores = f", {timing['helper_keys']} of them on a second core" if timing["helper_keys"] else ""
        report({"INFO"}, f"baked {timing['keys']} shape keys on {self.root.name!r} "
                         f"({timing['per_key_s'] * 1000:.0f} ms per key{cores})"
                         + (f"; {left} was taken out of Edit Mode to receive them" if left else ""))
        return {"FINISHED"}


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
