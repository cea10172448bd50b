"""Benchmark: the artist's buttons on a dense scan, in Blender (the bpy module), timed as they are pressed.

    ./ha bench panel [--sizes 1M] [--repeat 2]

Per size, the scan-like head of ./ha bench scale (made once and kept; its 11 clicks) in a fresh
Blender file: imported by Blender's own PLY importer, made the scan, its clicks imported, then each
operator through bpy.ops as a script presses it (the work waited for), seconds of each:
  Calibrate              judge the clicks (the adaptation's step 1; kept for the Adapt that follows)
  Adapt                  the fit and the anatomy transfer on the scan Calibrate prepared, the result
                         objects built
  Adapt again            the same (the prepared scan given back by the Adapt before)
  Suggest the Rest       proposals for the FDPs not clicked, the clicks judged as Calibrate judged them
                         (the same: kept), snapped to the scan as that prepared it
  Adapt alone            Adapt with the kept calibration dropped (ui/kept.forget): no Calibrate before it
  Suggest the Rest alone the same for Suggest the Rest (as an artist's first press, before Calibrate)
and the stage seconds of Adapt alone's report. --repeat runs of the whole sequence; each figure is
the fastest of them.
"""
import argparse
import json
import pathlib
import sys
import time

ROOT = pathlib.Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "headless_tests" / "bench"))


def session(scan, marks):
    """{button: seconds} of one pass, and the last Adapt's report."""
    import bpy

    import headadapt_addon
    from headadapt_addon.ui import kept

    bpy.ops.wm.read_homefile(use_empty=False, use_factory_startup=True)
    for obj in list(bpy.data.objects):
        bpy.data.objects.remove(obj)
    headadapt_addon.register()
    try:
        win = bpy.context.window_manager.windows[0]
        area = next(a for a in win.screen.areas if a.type == "VIEW_3D")
        times = {}
        with bpy.context.temp_override(window=win, screen=win.screen, area=area):
            t0 = time.perf_counter()
            assert bpy.ops.wm.ply_import(filepath=str(scan)) == {"FINISHED"}
            times["PLY import (Blender's)"] = time.perf_counter() - t0
            assert bpy.ops.headadapt.use_active_as_scan() == {"FINISHED"}
            assert bpy.ops.headadapt.import_landmarks(filepath=str(marks)) == {"FINISHED"}

            def press(label, op):
                t0 = time.perf_counter()
                assert op() == {"FINISHED"}, label
                times[label] = time.perf_counter() - t0

            press("Calibrate", bpy.ops.headadapt.calibrate)
            press("Adapt", bpy.ops.headadapt.adapt)
            press("Adapt again", bpy.ops.headadapt.adapt)
            press("Suggest the Rest", bpy.ops.headadapt.suggest_landmarks)
            kept.forget()
            press("Adapt alone", bpy.ops.headadapt.adapt)
            kept.forget()
            press("Suggest the Rest alone", bpy.ops.headadapt.suggest_landmarks)
            report = json.loads(bpy.context.scene.headadapt.report_json)
        return times, report
    finally:
        headadapt_addon.unregister()


def main(argv=None):
    from bench_scale import parse_size, scale_head, vertex_count

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", default="1M", help="scan vertex counts, e.g. 30k,1M")
    parser.add_argument("--repeat", type=int, default=2, help="passes per size (each figure: the fastest)")
    args = parser.parse_args(argv)
    for n in [parse_size(s) for s in args.sizes.split(",") if s]:
        scan, marks = scale_head(n)
        runs = [session(scan, marks) for _ in range(max(args.repeat, 1))]
        best = {k: min(r[0][k] for r in runs) for k in runs[0][0]}
        print(f"\n{vertex_count(scan):,}-vertex scan, in Blender {__import__('bpy').app.version_string} "
              f"(fastest of {len(runs)}):")
        for k, v in best.items():
            print(f"  {k:24s} {v:6.2f} s")
        report = runs[-1][1]
        print("  Adapt alone's stages (s): " + ", ".join(f"{k} {v:.2f}" for k, v in report["stage_seconds"].items()))


if __name__ == "__main__":
    main()
