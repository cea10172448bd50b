"""Adapt pressed twice in a real Blender window (run by test_blender_binary.py under xvfb-run): the
sample scan with its 8 clicks, Adapt started from the button's path (invoke: a worker thread, a
timer), pressed again at once, then left to finish. Prints "gui_adapt: RESULT {...}": whether the
second press was refused while the first ran, the results made, and whether Adapt is usable again.
"""
import pathlib
import sys

import bpy

ROOT = pathlib.Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tools"))
import screenshots as shots  # its helpers (and ROOT on sys.path): register, load the sample, the clicks

RESULT = {}


def press():
    with bpy.context.temp_override(**shots._override()):
        RESULT["first"] = sorted(bpy.ops.headadapt.adapt("INVOKE_DEFAULT", levels=1))
        try:
            RESULT["second"] = sorted(bpy.ops.headadapt.adapt("INVOKE_DEFAULT", levels=1))
        except RuntimeError as exc:          # poll() refused: the greyed button's message
            RESULT["second"] = "refused: " + str(exc).strip().split("poll() ")[-1]
    return 0.5


def wait():
    from headadapt_addon.ui import jobs
    if jobs.busy():
        return ("again", 0.5)
    roots = [o for o in bpy.data.objects if o.parent is None and o.name.endswith("adapted")]
    RESULT["results"] = len(roots)
    with bpy.context.temp_override(**shots._override()):
        RESULT["usable_again"] = bool(bpy.ops.headadapt.adapt.poll())
    print("gui_adapt: RESULT", RESULT, flush=True)
    return 0.1


shots.play([shots.setup, shots.redraw, shots.clicks8, press, wait], first_interval=1.0)
