"""Calibrate, then Adapt pressed twice in a real Blender window (run by test_blender_binary.py under
xvfb-run): the sample scan with its 8 clicks, Calibrate from its button (a worker thread: what it
answered, whether Adapt was greyed meanwhile, the calibration written when it ended), Adapt started from the button's path (invoke: a worker thread, a
timer), pressed again at once, then left to finish. Prints "gui_adapt: RESULT {...}": whether the
second press was refused while the first ran, the results made, and whether Adapt is usable again;
then Suggest the Rest from its button (a worker thread too): what it answered, whether Adapt was
greyed meanwhile, and the suggestions written when it ended.
"""
import pathlib
import sys

import bpy

ROOT = pathlib.Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tools"))
import screenshots as shots  # its helpers (and ROOT on sys.path): register, load the sample, the clicks

RESULT = {}


def calibrate():
    from headadapt_addon.ui import jobs
    with bpy.context.temp_override(**shots._override()):
        RESULT["calibrate"] = sorted(bpy.ops.headadapt.calibrate("INVOKE_DEFAULT"))
        RESULT["calibrate_busy"] = jobs.busy()
        RESULT["adapt_greyed_by_calibrate"] = not bpy.ops.headadapt.adapt.poll()
    return 0.5


def calibrated():
    from headadapt_addon.ui import jobs
    if jobs.busy():
        return ("again", 0.5)
    s = bpy.context.scene.headadapt
    RESULT["calibrated_rms_mm"] = round(s.calibration_rms_mm, 2)
    RESULT["calibration_stored"] = "headadapt_calibration" in s.scan
    return 0.1


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
    return 0.1


def suggest():
    from headadapt_addon.ui import jobs
    with bpy.context.temp_override(**shots._override()):
        RESULT["suggest"] = sorted(bpy.ops.headadapt.suggest_landmarks("INVOKE_DEFAULT"))
        RESULT["suggest_busy"] = jobs.busy()
        RESULT["adapt_greyed"] = not bpy.ops.headadapt.adapt.poll()
    return 0.5


def suggested():
    from headadapt_addon.blender import landmarks
    from headadapt_addon.ui import jobs
    if jobs.busy():
        return ("again", 0.5)
    scan = bpy.context.scene.headadapt.scan
    RESULT["suggested"] = len(landmarks.get_landmarks(scan, landmarks.SUGGESTED_PROP))
    print("gui_adapt: RESULT", RESULT, flush=True)
    return 0.1


shots.play([shots.setup, shots.redraw, shots.clicks8, calibrate, calibrated, press, wait, suggest, suggested], first_interval=1.0)
