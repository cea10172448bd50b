"""The long work of the buttons (Calibrate, Suggest the Rest, Adapt, Bake) as Runs (jobs.Run: core work on a worker
thread, the scene written in the main thread when it is done), and the judging of the clicks that
Calibrate and Suggest the Rest share; with the scene edits Adapt's result needs (the last result
removed, Edit Mode left, the scene's unit)."""

import json

import bpy
import numpy as np

from ..blender import landmarks, scene
from ..core import mpeg4
from ..core.exceptions import HeadAdaptError
from . import jobs, kept
from .jobs import Job, Run
from .props import apply_display
from .state import adapt_options, head_size_mm, landmark_problem, scan_arrays, settings, template


def gather_clicks(context):
    """What judging the scene's clicks needs, read in the main thread (the scan's arrays, its clicks,
    the options, their digest, the template), or a HeadAdaptError naming what is missing."""
    from types import SimpleNamespace
    problem = landmark_problem(context)
    if problem:
        raise HeadAdaptError(problem)
    scan, verts, tris = scan_arrays(context)
    pts = landmarks.get_landmarks(scan)
    options = adapt_options(settings(context))
    return SimpleNamespace(scan=scan, verts=verts, tris=tris, pts=pts, options=options, tpl=template(),
                           key=kept.digest(verts, tris, pts, options), head_mm=head_size_mm())


def judge_clicks(clicks):
    """gather_clicks' clicks judged (numpy only: a worker thread may run it): (pipeline.calibrate's
    answer, its RMS in mm), the answer kept from the last judging of the same scan, clicks and options
    if there is one; or a HeadAdaptError naming the cause (another unit, wrong names, a mirrored scan)."""
    from ..core.adapt import calibration, pipeline, reach
    answer = kept.get(clicks.key)           # the same scan, clicks and options judged before: as it was
    try:
        if answer is None:
            answer = pipeline.calibrate(clicks.tpl, clicks.verts, clicks.tris, clicks.pts, clicks.options)
            reach.check_on_surface(answer[0].scan, answer[2], clicks.options)
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


def clicks_moved(scan, pts):
    """Whether the scan's clicks differ from pts (a click moved, added or removed since a run began)."""
    now = landmarks.get_landmarks(scan)
    return set(now) != set(pts) or any(not np.array_equal(now[k], pts[k]) for k in now)


class CalibrateRun(Run):
    """One Calibrate: the clicks judged (pipeline.calibrate: the scan into the template's frame, a dense
    scan clustered, its normals and spatial tree; about 1 s at 1M vertices, more on the larger scans
    the readers take) on a Job, the calibration written to the scan at the end."""
    what = "Calibrate"

    def __init__(self, context):
        self.clicks = gather_clicks(context)
        self.scan = self.clicks.scan

        def work(say):
            say(0.0, "calibrating: the scan into the template's frame, its normals and spatial tree")
            try:
                value = judge_clicks(self.clicks)
            except HeadAdaptError as exc:        # said, and the last calibration's tick taken off, in finish
                return exc
            say(1.0, "calibrated")
            return value

        self.work = work
        self.job = Job(work)

    def needs(self):
        return (self.scan,)

    def finish(self, context, value, report):
        if isinstance(value, HeadAdaptError):
            return fail_calibration(context, str(value), report)
        (_fit, _tpl_fdps, q_fdp, sim, info), rms_mm = value
        clicks = self.clicks
        kept.keep(clicks.key, value[0])               # for the Adapt that follows (ui/kept.py)
        if clicks_moved(self.scan, clicks.pts):
            report({"WARNING"}, "the clicks changed while Calibrate ran: nothing written; press it again")
            return {"CANCELLED"}
        s = settings(context)
        s.calibration_rms_mm = rms_mm
        self.scan["headadapt_calibration"] = json.dumps({"matrix": sim.matrix4().tolist(), **{
            k: v for k, v in info.items() if k != "residuals"}}, default=float)
        notes = info["handedness"]["notes"]
        msg = (f"calibrated ({info['method']}): RMS {rms_mm:.2f} mm over {len(q_fdp)} FDPs "
               f"({100 * rms_mm / clicks.head_mm:.1f}% of the head's width), scan unit = {1000 * sim.scale:.4g} mm")
        if notes:
            report({"WARNING"}, msg + "; " + "; ".join(notes))
        else:
            report({"INFO"}, msg)
        return {"FINISHED"}


def fail_calibration(context, problem, report):
    """A Calibrate refused: the problem said, and the tick of an earlier calibration taken off (it no
    longer speaks for the clicks)."""
    settings(context).calibration_rms_mm = -1.0
    report({"ERROR"}, problem)
    return {"CANCELLED"}


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
        if clicks_moved(self.scan, self.clicks.pts):
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
        self.scan, verts, tris = scan_arrays(context)
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
        if clicks_moved(self.scan, self.pts):          # the result stands, but not for the clicks shown now
            warnings = ["the clicks changed while Adapt ran: this result is from the clicks as they were when it "
                        "started; press Adapt again for the new ones"] + warnings
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
