"""The README's screenshots, taken from a real Blender window (not rendered): docs/img/landmarks.png,
docs/img/panels.png and docs/img/heat_map.png.

    blender -b --factory-startup --python-expr "import bpy; bpy.ops.wm.save_as_mainfile(filepath='/tmp/start.blend')"
    xvfb-run -a -s "-screen 0 1600x1000x24" blender --factory-startup --enable-event-simulate /tmp/start.blend \
        --python tools/screenshots.py

(a file on the command line: no splash screen; event simulation: the sidebar's HeadAdapt tab is
clicked as a user clicks it)

The extension is registered by hand (its folder on sys.path, register()), as a user who installed it
would have it; the steps are the walkthrough's: Load Sample Scan, the 8 clicks (from the sample's
landmark file: a script cannot aim a hand), Suggest the Rest,
Calibrate, Adapt. Blender's own screenshot operator writes the pictures, from timers, once the window
has drawn what each step changed. PLYFILE_TRIMESH names a folder with plyfile and trimesh where
Blender's Python has none (Debian's); the extension's zip bundles them.
"""
import os
import pathlib
import sys
import traceback

import bpy

ROOT = pathlib.Path(__file__).resolve().parents[1]
OUT = pathlib.Path(os.environ.get("HEADADAPT_SHOTS", ROOT / "docs" / "img"))
sys.path.insert(0, str(ROOT))
if os.environ.get("PLYFILE_TRIMESH"):
    sys.path.insert(0, os.environ["PLYFILE_TRIMESH"])

import headadapt_addon  # noqa: E402
from headadapt_addon.batch import SAMPLE_DIR  # noqa: E402
from headadapt_addon.core import meshio, mpeg4  # noqa: E402


def _window():
    win = bpy.context.window_manager.windows[0]
    area = max((a for a in win.screen.areas if a.type == "VIEW_3D"), key=lambda a: a.width * a.height)
    return win, area, next(r for r in area.regions if r.type == "WINDOW")


def _override():
    win, area, region = _window()
    return {"window": win, "screen": win.screen, "area": area, "region": region}


def _sidebar(area):
    return next(r for r in area.regions if r.type == "UI")


def setup():
    win, area, _region = _window()
    for obj in list(bpy.data.objects):
        bpy.data.objects.remove(obj)
    headadapt_addon.register()
    space = area.spaces.active
    space.show_region_ui = True
    space.show_region_toolbar = False
    space.overlay.show_floor = space.overlay.show_axis_x = space.overlay.show_axis_y = False
    with bpy.context.temp_override(**_override()):
        bpy.ops.headadapt.load_sample_scan()
        s = bpy.context.scene.headadapt
        _front(s.scan)
        # the face's direction from the sample's own landmark file (the scene is not touched)
        import numpy as np

        from headadapt_addon.core.adapt import calibration
        from headadapt_addon.ui.state import visible_template_fdps
        clicks = meshio.read_landmarks(SAMPLE_DIR / "landmarks.json")
        sim, _info = calibration.calibrate(clicks, visible_template_fdps())
        m = np.array(sim.matrix4())[:3, :3]                                          # scan -> template
        face_view(np.linalg.inv(m / np.cbrt(np.linalg.det(m))))
        bpy.ops.view3d.view_selected()
    return 1.0


def redraw():
    """Give the window time to draw (the reference picture's preview loads after the first draw)."""
    for area in _window()[0].screen.areas:
        area.tag_redraw()
    return 2.0


def clicks8():
    """The 8 clicks placed (here from the sample's landmark file), Suggest the Rest, Calibrate."""
    with bpy.context.temp_override(**_override()):
        s = bpy.context.scene.headadapt
        clicks = meshio.read_landmarks(SAMPLE_DIR / "landmarks.json")
        from headadapt_addon.blender import landmarks
        landmarks.set_landmarks(s.scan, {k: clicks[k] for k in mpeg4.CLICKS_8})
        bpy.ops.headadapt.suggest_landmarks()
        bpy.ops.headadapt.calibrate()
    return 1.0


def tab():
    """Click the sidebar's HeadAdapt tab (the fourth: Item, Tool, View, HeadAdapt; 175 px below its top)."""
    win, area, _region = _window()
    ui = _sidebar(area)
    x, y = ui.x + ui.width - 10, ui.y + ui.height - 175
    for kind, value in (("MOUSEMOVE", "NOTHING"), ("LEFTMOUSE", "PRESS"), ("LEFTMOUSE", "RELEASE")):
        win.event_simulate(kind, value, x=x, y=y)
    return 1.0


def face_view(rotation):
    """Look at the face from the front: rotation (3x3) turns the template frame (face at -Y) into the world."""
    import math

    import mathutils
    _win, area, _region = _window()
    rv3d = area.spaces.active.region_3d
    rv3d.view_perspective = "ORTHO"
    rv3d.view_rotation = (mathutils.Matrix(rotation).to_quaternion()
                          @ mathutils.Euler((math.pi / 2, 0.0, 0.0)).to_quaternion())


def _front(obj):
    """Look at obj from the front (the sample scan faces -Y) and frame it."""
    for o in bpy.context.view_layer.objects.selected:
        o.select_set(False)
    obj.select_set(True)
    bpy.context.view_layer.objects.active = obj
    bpy.ops.view3d.view_axis(type="FRONT")
    bpy.ops.view3d.view_selected()


def shot(name):
    def take():
        for o in bpy.context.view_layer.objects.selected:
            o.select_set(False)
        OUT.mkdir(parents=True, exist_ok=True)
        with bpy.context.temp_override(**_override()):
            bpy.ops.screen.screenshot_area(filepath=str(OUT / name))
        _small(OUT / name)
        print(f"screenshots: wrote {OUT / name} ({(OUT / name).stat().st_size // 1024} kB)", flush=True)
        return 0.5
    return take


CROP_LEFT_PX, SCALE, LEVELS = 170, 0.78, 20     # README pictures stay under 200 kB (a house test)


def _small(path):
    """Crop the empty left of the viewport, scale down and round each channel to LEVELS values, so
    the PNG compresses to under 200 kB; written in place."""
    import numpy as np
    img = bpy.data.images.load(str(path))
    w, h = img.size
    px = np.empty(w * h * 4, dtype=np.float32)
    img.pixels.foreach_get(px)
    px = px.reshape(h, w, 4)[:, CROP_LEFT_PX:]
    small = bpy.data.images.new("small", px.shape[1], h)
    small.pixels.foreach_set(px.ravel())
    width, height = int(px.shape[1] * SCALE), int(h * SCALE)
    small.scale(width, height)
    q = np.empty(width * height * 4, dtype=np.float32)
    small.pixels.foreach_get(q)
    small.pixels.foreach_set(np.round(q * (LEVELS - 1)) / (LEVELS - 1))
    settings = bpy.context.scene.render.image_settings
    settings.file_format, settings.color_mode, settings.compression = "PNG", "RGB", 100
    small.save_render(str(path), scene=bpy.context.scene)
    bpy.data.images.remove(img)
    bpy.data.images.remove(small)


def adapt():
    with bpy.context.temp_override(**_override()):
        s = bpy.context.scene.headadapt
        bpy.ops.headadapt.accept_suggestions()
        print("screenshots: adapt", bpy.ops.headadapt.adapt(), flush=True)
        for o in bpy.context.view_layer.objects.selected:
            o.select_set(False)
        _front(s.scan)
        root = s.result_root
        face_view(root.matrix_world.to_3x3().normalized())
        bpy.ops.view3d.view_selected()
        s.scan.select_set(False)
    return 2.0


def scroll_sidebar():
    """Scroll the sidebar down to the Display and Report panels."""
    _win, area, _region = _window()
    ui = _sidebar(area)
    with bpy.context.temp_override(**{**_override(), "region": ui}):
        for _ in range(6):
            bpy.ops.view2d.scroll_down(page=True)
    return 1.0


STEPS = [setup, tab, redraw, redraw, shot("landmarks.png"), clicks8, redraw, shot("panels.png"), adapt, scroll_sidebar, shot("heat_map.png")]


def play(steps, first_interval=2.0):
    """Run steps one after another from Blender's timers, then quit Blender (also after a step fails,
    its traceback printed). A step returns the seconds to wait before the next, or ("again", seconds)
    to be run again after them (waiting for something)."""
    steps = list(steps)

    def run():
        try:
            if steps:
                answer = steps[0]()
                if isinstance(answer, tuple):
                    return answer[1]
                steps.pop(0)
                return answer
        except Exception:
            traceback.print_exc()
            steps.clear()
        bpy.ops.wm.quit_blender()
        return None

    bpy.app.timers.register(run, first_interval=first_interval)


if __name__ == "__main__":            # blender --python tools/screenshots.py (importable for its helpers)
    play(STEPS)
