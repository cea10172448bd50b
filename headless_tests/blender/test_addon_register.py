"""The add-on registers its sidebar tab and unregisters cleanly under the bpy module."""

import headadapt_addon


def test_register_adds_sidebar_panels_in_work_order(clean_scene):
    import bpy

    headadapt_addon.register()
    try:
        from headadapt_addon.ui import panels as ui

        labels = [cls.bl_label for cls in ui.classes]
        assert labels == ["Template", "Scan", "Landmarks", "Calibrate", "Adapt", "Display", "Anatomy",
                          "Expressions", "Report"]
        for cls in ui.classes:
            registered = getattr(bpy.types, cls.bl_idname, None)
            assert registered is not None, cls.bl_idname
            assert registered.bl_category == "HeadAdapt"
    finally:
        headadapt_addon.unregister()
    assert getattr(bpy.types, "HEADADAPT_PT_template", None) is None
