"""Blender tests: each leaves Blender's factory file behind it, so no test sees another's objects."""

import pytest

import headadapt_addon


@pytest.fixture(autouse=True)
def fresh_file():
    """After each test, Blender's empty factory file again."""
    yield
    import bpy

    bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)


@pytest.fixture
def ui_scene():
    """Factory startup (with a window and a 3D view), the add-on registered; yields an override dict."""
    import bpy

    bpy.ops.wm.read_homefile(use_empty=False, use_factory_startup=True)
    for obj in list(bpy.data.objects):
        bpy.data.objects.remove(obj)
    headadapt_addon.register()
    win = bpy.context.window_manager.windows[0]
    area = next(a for a in win.screen.areas if a.type == "VIEW_3D")
    yield {"window": win, "screen": win.screen, "area": area}
    headadapt_addon.unregister()
