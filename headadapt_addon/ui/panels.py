"""Sidebar tab "HeadAdapt" in the 3D viewport: panels in the order of the work, each showing state."""

import json
import pathlib
import textwrap

import bpy

from ..blender import landmarks, scene
from ..blender.scene import head_root
from ..core import mpeg4
from ..core.adapt import outcome as outcome_text
from . import jobs

PANELS = (
    ("TEMPLATE", "Template"),
    ("SCAN", "Scan"),
    ("LANDMARKS", "Landmarks"),
    ("CALIBRATE", "Calibrate"),
    ("ADAPT", "Adapt"),
    ("DISPLAY", "Display"),
    ("ANATOMY", "Anatomy"),
    ("EXPRESSIONS", "Expressions"),
    ("REPORT", "Report"),
)


def _settings(context):
    return context.scene.headadapt


def _wrap(context):
    """Characters per line that fit the sidebar (its width in pixels less an icon), for
    textwrap: messages wrap instead of being cut off in a narrow sidebar (about 8 px a character)."""
    region = getattr(context, "region", None)
    if region is None or region.type != "UI" or region.width < 50:
        return 60
    return max(24, int(region.width / (8.0 * context.preferences.view.ui_scale)) - 6)


def _wrapped(layout, context, text, icon=None):
    """text as labels wrapped to the sidebar's width (_wrap), not cut; the icon on the first line, the
    others indented as far."""
    for i, part in enumerate(textwrap.wrap(text, _wrap(context))):
        if icon is None:
            layout.label(text=part)
        else:
            layout.label(text=part, icon=icon if i == 0 else "BLANK1")


def draw_template(layout, context):
    s = _settings(context)
    if s.template_root is not None and s.template_root.name in context.scene.objects:
        layout.label(text=f"In scene: {s.template_root.name}", icon="CHECKMARK")
    else:
        layout.label(text="Not in the scene yet", icon="INFO")
    layout.operator("headadapt.add_template", icon="ADD")


def draw_scan(layout, context):
    s = _settings(context)
    layout.prop(s, "scan")
    if s.scan is None:
        layout.label(text="Pick the scanned head", icon="ERROR")
    else:
        layout.label(text=f"{len(s.scan.data.vertices):,} vertices, {len(s.scan.data.polygons):,} faces")
    layout.operator("headadapt.use_active_as_scan", icon="EYEDROPPER")
    layout.operator("headadapt.load_sample_scan", icon="USER")


def draw_landmarks(layout, context):
    s = _settings(context)
    pts = landmarks.get_landmarks(s.scan)
    from .state import landmark_problem
    col = layout.column()
    col.enabled = s.scan is not None
    col.label(text=f"{len(pts)} of {len(mpeg4.FDPS)} FDPs placed")
    problem = landmark_problem(context) if s.scan is not None else None
    if problem is None and s.scan is not None:
        _wrapped(col, context, "Enough to calibrate and adapt", "CHECKMARK")
    elif problem:
        _wrapped(col, context, problem[:1].upper() + problem[1:], "ERROR")
    col.prop(s, "active_fdp")
    col.label(text=mpeg4.FDPS[s.active_fdp].label)
    if s.active_fdp in mpeg4.CLICK_HINTS:          # where people misplace it: said before they click
        _wrapped(col, context, "Click " + mpeg4.CLICK_HINTS[s.active_fdp], "INFO")
    col.operator("headadapt.pick_landmarks", icon="RESTRICT_SELECT_OFF")
    row = col.row(align=True)
    row.operator("headadapt.import_landmarks", icon="IMPORT")
    row.operator("headadapt.export_landmarks", icon="EXPORT")
    # the 8 clicks first: what calibration and Suggest the Rest start from, with a picture of where
    box = col.box().column(align=True)
    box.label(text=f"The 8 clicks: {sum(k in pts for k in mpeg4.CLICKS_8)} of 8")
    picture = reference_preview()
    if picture is not None and sum(k in pts for k in mpeg4.CLICKS_8) < 8:
        box.template_icon(icon_value=picture.icon_id, scale=7.0)
    flagged = landmarks.get_flagged(s.scan, pts)
    for name in mpeg4.CLICKS_8:
        _fdp_row(box, context, name, pts, flagged)
    row = col.row(align=True)
    row.operator("headadapt.suggest_landmarks", icon="LIGHT")
    _progress(col, context, "Suggest the Rest")
    suggested = landmarks.get_landmarks(s.scan, landmarks.SUGGESTED_PROP) if s.scan is not None else {}
    if suggested:      # each suggestion accepted or rejected on its own, or all at once
        box = col.box().column(align=True)
        row = box.row(align=True)
        row.label(text=f"{len(suggested)} suggested")
        row.operator("headadapt.accept_suggestions", text="All", icon="CHECKMARK").fdp = ""
        row.operator("headadapt.reject_suggestions", text="None", icon="X").fdp = ""
        for name in suggested:
            row = box.row(align=True)
            row.label(text=f"{name}  {mpeg4.FDPS[name].label}", icon="LIGHT")
            row.operator("headadapt.accept_suggestions", text="", icon="CHECKMARK").fdp = name
            row.operator("headadapt.reject_suggestions", text="", icon="X").fdp = name
    # the rest folded away
    others = [k for k in mpeg4.FDPS if k not in mpeg4.CLICKS_8]
    row = col.row()
    row.prop(s, "show_all_fdps", emboss=False, icon="DISCLOSURE_TRI_DOWN" if s.show_all_fdps else "DISCLOSURE_TRI_RIGHT",
             text=f"Other FDPs: {sum(k in pts for k in others)} of {len(others)}")
    if s.show_all_fdps:
        box = col.box().column(align=True)
        for name in others:
            _fdp_row(box, context, name, pts, flagged)
    elif any(k in flagged for k in others):     # folded away, but a click there needs looking at
        box = col.box().column(align=True)
        for name in others:
            if name in flagged:
                _fdp_row(box, context, name, pts, flagged)


def _fdp_row(layout, context, name, pts, flagged):
    """One FDP's row: placed (a check), the one the picker places next, or not yet; a click the last
    fit (Adapt, Suggest the Rest) judged wrong, and not moved since, is marked with the fit's reason."""
    row = layout.row(align=True)
    why = flagged.get(name)
    active = _settings(context).active_fdp
    mark = ("ERROR" if why else "CHECKMARK") if name in pts else ("RADIOBUT_ON" if name == active else "BLANK1")
    row.label(text=f"{name}  {mpeg4.FDPS[name].label}", icon=mark)
    if name in pts:
        row.operator("headadapt.clear_landmark", text="", icon="X").fdp = name
    if why:
        _wrapped(layout, context, f"The fit judges it wrong: {why}; move it or clear it", "BLANK1")


def _progress(layout, context, what):
    """A running Adapt's, Bake's or Suggest the Rest's progress, in its own panel (the status bar says it too)."""
    s = _settings(context)
    if s.progress_text and jobs.busy() == what:
        _wrapped(layout, context, s.progress_text.removeprefix("HeadAdapt: "), "TIME")


def draw_calibrate(layout, context):
    s = _settings(context)
    layout.prop(s, "calibration")
    if s.calibration_rms_mm >= 0:
        layout.label(text=f"Calibrated: RMS {s.calibration_rms_mm:.2f} mm", icon="CHECKMARK")
    layout.operator("headadapt.calibrate", icon="ORIENTATION_GLOBAL")


def draw_adapt(layout, context):
    s = _settings(context)
    layout.prop(s, "max_levels")
    layout.prop(s, "drop_flagged")
    row = layout.row(align=True)
    row.operator("headadapt.adapt", text="Adapt", icon="PLAY").levels = -1
    row.operator("headadapt.adapt", text="Level 0").levels = 0
    layout.prop(s, "keep_results")
    _progress(layout, context, "Adapt")
    if s.result_root is not None:
        _wrapped(layout, context, f"Result: {s.result_root.name}", "CHECKMARK")


def draw_display(layout, context):
    s = _settings(context)
    layout.prop(s, "show_heat_map")
    if s.show_heat_map:          # the legend: the heat map's colours at their distances to the scan
        row = layout.row(align=True)
        for i in range(4):
            col = row.column(align=True)
            col.label(text=s.bl_rna.properties[f"legend_{i}"].name)
            col.prop(s, f"legend_{i}", text="")
        layout.label(text="distance to the scan")
        layout.label(text="grey: no scan there")
    layout.prop(s, "scan_as_wire")
    row = layout.row(align=True)
    row.prop(s, "show_fdps", toggle=True)
    row.prop(s, "show_markers", toggle=True)
    row.prop(s, "show_muscles", toggle=True)


def draw_anatomy(layout, context):
    s = _settings(context)
    if s.result_root is None:
        _wrapped(layout, context, "Adapt first: the anatomy follows the adaptation", "INFO")
    else:
        _wrapped(layout, context, "The anatomy follows the result", "CHECKMARK")


def draw_expressions(layout, context):
    root = head_root(context)
    if root is None:
        layout.label(text="Add the template or adapt first", icon="INFO")
    else:
        skin = scene.template_objects(root).get("skin")
        baked = len(json.loads(skin.get("headadapt_keys", "{}"))) if skin else 0
        _wrapped(layout, context, f"{baked} keys baked on {root.name}" if baked else f"{root.name}: not baked yet",
                 "CHECKMARK" if baked else "INFO")
    layout.operator("headadapt.bake_expressions")
    _progress(layout, context, "Bake")
    layout.operator("headadapt.import_fap", icon="IMPORT")


def draw_report(layout, context):
    s = _settings(context)
    if not s.report_json:
        layout.label(text="No adaptation yet")
        return
    rep = json.loads(s.report_json)
    table = layout.column(align=True)
    # the whole table needs about 50 characters across; a narrower sidebar gets its essentials
    wide = _wrap(context) >= WIDE_REPORT_CHARS
    for cells in report_rows(rep, wide):      # one row per level: read across, as a table is read
        row = table.row(align=True)
        for cell in cells:
            row.label(text=cell)
    if not wide:
        _wrapped(table, context, "RMS in mm, time in s; E_d, E_m, E: widen the sidebar")
    dropped = rep.get("dropped_fdps") or []
    layout.label(text="Dropped clicks: " + (", ".join(dropped) if dropped else "none"),
                 icon="X" if dropped else "CHECKMARK")
    layout.label(text=rep.get("stopped_because", ""))
    outcome = rep.get("outcome")
    if outcome:
        layout.label(text="Fit ok" if outcome["ok"] else "Fit NOT trustworthy",
                     icon="CHECKMARK" if outcome["ok"] else "ERROR")
        for line in outcome_text.measures(outcome):
            _wrapped(layout, context, line)
    for line in outcome_text.warning_lines(outcome, rep.get("flagged_fdps"), rep.get("dropped_fdps", ())):
        _wrapped(layout, context, line, "ERROR")
    _wrapped(layout, context, "Heat map and its legend: Display panel")
    layout.operator("headadapt.save_picture", icon="RENDER_STILL")


WIDE_REPORT_CHARS = 50     # characters across the sidebar (_wrap) from which the Report shows E_d, E_m and E
NARROW_REPORT = ("Level", "Pairs", "RMS mm", "Time s")      # the columns shown in a narrower one,
NARROW_HEADS = {"RMS mm": "RMS", "Time s": "Time"}           # their units on a line below (cut there)


def report_rows(rep, wide=True):
    """The Report panel's level table as rows of cells, the header first (units in it); the best level
    starred; E_m (held-out markers, mm^2) only where markers were given. Not wide: level, pairs, RMS
    and seconds only (a default-width sidebar cuts seven columns to their first letters)."""
    markers = any(lv.get("E_m") is not None for lv in rep["levels"])
    columns = [("Level", lambda lv: f"{lv['level']}{'*' if lv['level'] == rep['best_level'] else ''}"),
               ("Pairs", lambda lv: str(lv["pairs"])),
               ("E_d mm²", lambda lv: f"{lv['E_d']:.3f}"),
               ("RMS mm", lambda lv: "-" if lv.get("E_d_rms_mm") is None else f"{lv['E_d_rms_mm']:.2f}"),
               ("E_m mm²", lambda lv: "-" if lv.get("E_m") is None else f"{lv['E_m']:.2f}"),
               ("E mm²", lambda lv: f"{lv['E']:.3f}"),
               ("Time s", lambda lv: f"{lv['seconds']:.1f}")]
    shown = [(head, cell) for head, cell in columns if (wide or head in NARROW_REPORT)
             and (markers or head != "E_m mm²")]
    heads = [head if wide else NARROW_HEADS.get(head, head) for head, _ in shown]
    return [heads] + [[cell(lv) for _, cell in shown] for lv in rep["levels"]]


DRAW = {"TEMPLATE": draw_template, "SCAN": draw_scan, "LANDMARKS": draw_landmarks,
        "CALIBRATE": draw_calibrate, "ADAPT": draw_adapt, "DISPLAY": draw_display, "ANATOMY": draw_anatomy,
        "EXPRESSIONS": draw_expressions, "REPORT": draw_report}


class HEADADAPT_PT_base:
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "HeadAdapt"


def _make_panel(key, label, order):
    def draw(self, context):
        DRAW[key](self.layout, context)

    return type(
        f"HEADADAPT_PT_{key.lower()}",
        (HEADADAPT_PT_base, bpy.types.Panel),
        {"bl_idname": f"HEADADAPT_PT_{key.lower()}", "bl_label": label, "bl_order": order, "draw": draw},
    )


classes = tuple(_make_panel(key, label, i) for i, (key, label) in enumerate(PANELS))


_register_classes, _unregister_classes = bpy.utils.register_classes_factory(classes)
REFERENCE = pathlib.Path(__file__).resolve().parents[2] / "assets" / "reference" / "clicks8.png"
_previews = {}


def reference_preview():
    """The 8 clicks' reference picture (tools/render_reference.py) as a preview, None if it is missing."""
    coll = _previews.get("coll")
    if coll is None or not REFERENCE.is_file():
        return None
    if "clicks8" not in coll:
        coll.load("clicks8", str(REFERENCE), "IMAGE")
    return coll["clicks8"]


def register():
    import bpy.utils.previews
    _previews["coll"] = bpy.utils.previews.new()
    _register_classes()


def unregister():
    _unregister_classes()
    coll = _previews.pop("coll", None)
    if coll is not None:
        import bpy.utils.previews
        bpy.utils.previews.remove(coll)
