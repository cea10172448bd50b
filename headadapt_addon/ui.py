"""Sidebar tab "HeadAdapt" in the 3D viewport: panels in the order of the work."""

import bpy

PANELS = (
    ("TEMPLATE", "Template"),
    ("SCAN", "Scan"),
    ("LANDMARKS", "Landmarks"),
    ("CALIBRATE", "Calibrate"),
    ("ADAPT", "Adapt"),
    ("ANATOMY", "Anatomy"),
    ("EXPRESSIONS", "Expressions"),
    ("REPORT", "Report"),
)


class HEADADAPT_PT_base:
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "HeadAdapt"


def _make_panel(key, label, order):
    def draw(self, context):
        self.layout.label(text="Not available yet")

    return type(
        f"HEADADAPT_PT_{key.lower()}",
        (HEADADAPT_PT_base, bpy.types.Panel),
        {"bl_idname": f"HEADADAPT_PT_{key.lower()}", "bl_label": label, "bl_order": order, "draw": draw},
    )


classes = tuple(_make_panel(key, label, i) for i, (key, label) in enumerate(PANELS))


def register():
    for cls in classes:
        bpy.utils.register_class(cls)


def unregister():
    for cls in reversed(classes):
        bpy.utils.unregister_class(cls)
