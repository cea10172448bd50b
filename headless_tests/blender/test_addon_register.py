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


def test_enabling_the_add_on_does_not_load_the_fit_nor_scipy():
    """Blender registers an enabled add-on at every start: registering imported the whole adaptation
    and scipy behind it (0.2 s warm, 0.67 s cold on a 2-core machine). Now they load at the first
    button that needs them."""
    import subprocess
    import sys

    probe = ("import sys, bpy, headadapt_addon; headadapt_addon.register();"
             "print('LOADED', sorted(m for m in ('scipy', 'headadapt_addon.core.adapt.pipeline') if m in sys.modules));"
             "from headadapt_addon.core.adapt import adapt; print('ADAPT', callable(adapt))")
    res = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120)
    assert "LOADED []" in res.stdout and "ADAPT True" in res.stdout, res.stdout + res.stderr


def test_disabling_the_add_on_leaves_no_worker_thread(clean_scene):
    import threading
    import time

    from headadapt_addon.core import threads

    headadapt_addon.register()
    assert threads.pool().submit(sum, [1, 2]).result() == 3            # as a fit's first step does
    headadapt_addon.unregister()
    deadline = time.time() + 5
    while time.time() < deadline and any(t.name.startswith("headadapt") for t in threading.enumerate()):
        time.sleep(0.05)
    assert not [t.name for t in threading.enumerate() if t.name.startswith("headadapt")]
