"""Scene settings of the HeadAdapt workflow (bpy.types.Scene.headadapt)."""

import bpy

from ..blender import scene, view
from ..core import mpeg4
from ..core.adapt.options import MAX_LEVELS, AdaptOptions


def _is_mesh(_self, obj):
    return obj.type == "MESH" and "headadapt_part" not in obj


def screens(context):
    """The screens of every open window (the 3D views the display toggles act on)."""
    return [w.screen for w in context.window_manager.windows if w.screen is not None]


def heads(s):
    return [r for r in (s.template_root, s.result_root) if r is not None]


def apply_display(s, context):
    """Make the scene look as the Display toggles say: heat map (once there is a result: the
    template has none, and would lose its colours), scan as wire, helpers."""
    if s.result_root is not None:
        view.show_heat_map(screens(context), s.show_heat_map)
    if s.scan is not None:
        view.show_scan_as_wire(s.scan, s.scan_as_wire and s.result_root is not None)
    for root in heads(s):
        for kind in view.HELPERS:
            view.set_helpers_visible(root, kind, getattr(s, f"show_{kind}"))


def _update(self, context):
    apply_display(self, context)


def _scan_changed(self, context):
    """Another scan: the panels show its own result, report and calibration (scene.follow_scan)."""
    scene.follow_scan(self, context.scene)


def _legend(mm):
    return lambda _self: tuple(float(c) for c in view.heat_colours([mm])[0, :3])


class HeadAdaptSettings(bpy.types.PropertyGroup):
    """What the panels show and the operators use."""
    scan: bpy.props.PointerProperty(name="Scan", type=bpy.types.Object, poll=_is_mesh, update=_scan_changed,
                                    description="The scanned head (never modified)")
    template_root: bpy.props.PointerProperty(name="Template", type=bpy.types.Object)
    result_root: bpy.props.PointerProperty(name="Result", type=bpy.types.Object)
    active_fdp: bpy.props.EnumProperty(
        name="FDP", items=[(k, k, f.label) for k, f in mpeg4.FDPS.items()], default=mpeg4.CLICKS_8[0],
        description="The FDP the next click places")
    max_levels: bpy.props.IntProperty(name="Levels", default=AdaptOptions.max_levels, min=0, max=MAX_LEVELS,
                                      description="Maximum number of refinement levels after level 0")
    calibration: bpy.props.EnumProperty(
        name="Calibration", default="auto",
        items=[("auto", "Auto", "The better of the paper's and least squares"),
               ("paper", "Paper", "Paper sec 3.1 from 8 FDPs"),
               ("umeyama", "Least squares", "Similarity over all FDPs")])
    drop_flagged: bpy.props.BoolProperty(name="Drop wrong clicks", default=True,
                                         description="Drop FDPs flagged as wrongly clicked and refit")
    calibration_rms_mm: bpy.props.FloatProperty(name="Calibration RMS (mm)", default=-1.0)
    report_json: bpy.props.StringProperty(name="Report", default="")
    keep_results: bpy.props.BoolProperty(name="Keep earlier results", default=False,
                                         description="Adapt adds a new result beside the earlier ones "
                                                     "instead of replacing the last")
    show_all_fdps: bpy.props.BoolProperty(name="Other FDPs", default=False,
                                          description="Unfold the FDPs beyond the 8 clicks (optional: "
                                                      "Suggest the Rest proposes them)")
    show_heat_map: bpy.props.BoolProperty(name="Heat map", default=True, update=_update,
                                          description="Colour the result's skin by its distance to the scan "
                                                      "(Solid shading by the colour attribute)")
    scan_as_wire: bpy.props.BoolProperty(name="Scan as wire", default=True, update=_update,
                                         description="Draw the scan as wire over the result, so they are told apart")
    show_fdps: bpy.props.BoolProperty(name="FDPs", default=False, update=_update,
                                      description="Show the head's 82 FDP empties")
    show_markers: bpy.props.BoolProperty(name="Markers", default=False, update=_update,
                                         description="Show the held-out marker empties")
    show_muscles: bpy.props.BoolProperty(name="Muscles", default=False, update=_update,
                                         description="Show the muscle and sphincter curves")
    legend_0: bpy.props.FloatVectorProperty(name="0", subtype="COLOR", size=3, get=_legend(0.0))
    legend_1: bpy.props.FloatVectorProperty(name="1", subtype="COLOR", size=3, get=_legend(1.0))
    legend_2: bpy.props.FloatVectorProperty(name="1.5", subtype="COLOR", size=3, get=_legend(1.5))
    legend_3: bpy.props.FloatVectorProperty(name="3+ mm", subtype="COLOR", size=3, get=_legend(3.0))
    progress_text: bpy.props.StringProperty(name="Progress", default="",
                                            description="What a running Adapt or Bake is doing")


def register():
    bpy.utils.register_class(HeadAdaptSettings)
    bpy.types.Scene.headadapt = bpy.props.PointerProperty(type=HeadAdaptSettings)


def unregister():
    del bpy.types.Scene.headadapt
    bpy.utils.unregister_class(HeadAdaptSettings)
