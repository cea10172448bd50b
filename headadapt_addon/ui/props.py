"""Scene settings of the HeadAdapt workflow (bpy.types.Scene.headadapt)."""

import bpy

from ..core import mpeg4
from ..core.adapt.options import AdaptOptions


def _is_mesh(_self, obj):
    return obj.type == "MESH" and "headadapt_part" not in obj


class HeadAdaptSettings(bpy.types.PropertyGroup):
    """What the panels show and the operators use."""
    scan: bpy.props.PointerProperty(name="Scan", type=bpy.types.Object, poll=_is_mesh,
                                    description="The scanned head (never modified)")
    template_root: bpy.props.PointerProperty(name="Template", type=bpy.types.Object)
    result_root: bpy.props.PointerProperty(name="Result", type=bpy.types.Object)
    active_fdp: bpy.props.EnumProperty(
        name="FDP", items=[(k, k, f.label) for k, f in mpeg4.FDPS.items()], default="2.1",
        description="The FDP the next click places")
    max_levels: bpy.props.IntProperty(name="Levels", default=AdaptOptions.max_levels, min=0, max=8,
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
    progress_text: bpy.props.StringProperty(name="Progress", default="",
                                            description="What a running Adapt or Bake is doing")


def register():
    bpy.utils.register_class(HeadAdaptSettings)
    bpy.types.Scene.headadapt = bpy.props.PointerProperty(type=HeadAdaptSettings)


def unregister():
    del bpy.types.Scene.headadapt
    bpy.utils.unregister_class(HeadAdaptSettings)
