"""Pick Landmarks in a real Blender window (run by test_blender_binary.py under xvfb-run):

    xvfb-run -a -s "-screen 0 1600x1000x24" blender --factory-startup --enable-event-simulate START.blend \
        --python headless_tests/blender/gui_picker.py

The sample scan framed so that part of it lies behind the sidebar; the picker started; a click
simulated over the sidebar where the scan lies behind it, then one over the scan in the open view.
Prints "gui_picker: RESULT {...}": the FDPs each click placed (the sidebar's must place none).
"""
import pathlib
import sys

import bpy
from bpy_extras import view3d_utils
from mathutils import Vector

ROOT = pathlib.Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tools"))
import screenshots as shots  # its helpers (and ROOT on sys.path): register, load the sample, the sidebar

from headadapt_addon.blender import landmarks

RESULT = {}


def hits_scan(x, y):
    """Whether the ray through window pixel (x, y) meets the scan."""
    _win, area, region = shots._window()
    rv3d = area.spaces.active.region_3d
    co = (x - region.x, y - region.y)
    origin = view3d_utils.region_2d_to_origin_3d(region, rv3d, co)
    direction = view3d_utils.region_2d_to_vector_3d(region, rv3d, co)
    scan = bpy.context.scene.headadapt.scan
    inv = scan.matrix_world.inverted()
    return scan.ray_cast(inv @ origin, (inv.to_3x3() @ direction).normalized())[0]


def frame():
    """Closer, and the scan moved right until part of it lies behind the sidebar."""
    _win, area, _region = shots._window()
    rv3d = area.spaces.active.region_3d
    rv3d.view_distance *= 0.6
    rv3d.view_location = rv3d.view_location - (rv3d.view_rotation @ Vector((1.0, 0.0, 0.0))) * 0.45 * rv3d.view_distance
    area.tag_redraw()
    return 1.0


def start():
    with bpy.context.temp_override(**shots._override()):
        print("gui_picker: picker", bpy.ops.headadapt.pick_landmarks("INVOKE_DEFAULT"), flush=True)
    return 0.5


def click(where):
    def go():
        win, area, region = shots._window()
        ui = shots._sidebar(area)
        xs = range(ui.x + 20, ui.x + ui.width - 20, 15) if where == "sidebar" else range(region.x + 40, ui.x - 30, 15)
        over = [(x, y) for x in xs for y in range(region.y + 40, region.y + region.height - 40, 15) if hits_scan(x, y)]
        x, y = over[len(over) // 2]
        RESULT[where] = -len(landmarks.get_landmarks(bpy.context.scene.headadapt.scan))
        for kind, value in (("MOUSEMOVE", "NOTHING"), ("LEFTMOUSE", "PRESS"), ("LEFTMOUSE", "RELEASE")):
            win.event_simulate(kind, value, x=x, y=y)
        return 0.5
    return go


def count(where):
    def go():
        RESULT[where] += len(landmarks.get_landmarks(bpy.context.scene.headadapt.scan))
        return 0.2
    return go


def end():
    print("gui_picker: RESULT", RESULT, flush=True)
    return 0.1


shots.play([shots.setup, shots.tab, shots.redraw, frame, shots.redraw, start,
            click("sidebar"), count("sidebar"), click("view"), count("view"), end], first_interval=1.0)
