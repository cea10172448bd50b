"""Benchmark: the template adapted onto a real head CT, against that person's own skull. Prints figures.

    ./ha bench ct

The VTK headsq CT (../shared/scans/headsq_ct, or $HEADADAPT_SCANS) has one person's skin and bone.
From 15 clicked FDPs we adapt and transfer the anatomy (tools/realct.py), then compare, in the
CT's mm: the adapted skin with the CT skin; the transferred skull with the CT bone, against the
peer 'template skull placed by the calibration alone'; and the tissue depths at the landmarks
(the table's, the CT's, ours).
"""
import os
import pathlib
import sys

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from headadapt_addon.core.template import load_template
from tools import realct


def main():
    scans = pathlib.Path(os.environ.get("HEADADAPT_SCANS", ROOT.parent / "shared" / "scans"))
    if not (scans / "headsq_ct").is_dir():
        sys.exit(f"bench ct: no CT at {scans / 'headsq_ct'} (set HEADADAPT_SCANS to the scans folder)")
    case = realct.run(load_template(), scans)
    res = case.result
    d = res.distances[np.isfinite(res.distances)] * case.mm
    print(f"adapt + transfer: {case.seconds:.2f} s; calibration {res.calibration_info['method']}, "
          f"FDP rms {res.calibration_info['rms'] * case.mm:.1f} mm; flagged: {res.flagged or 'none'}")
    print(f"adapted skin on the CT skin: {len(d)} vertices matched, distance median {np.median(d):.2f} mm, "
          f"90th percentile {np.percentile(d, 90):.2f} mm")
    print()
    print(f"{'skull vs the CT bone (mm)':34s} {'median':>7s} {'p75':>7s} {'p90':>7s}")
    figures = {}
    for name, bone in (("transferred (ours)", case.transferred_bone()),
                       ("template, calibration only (peer)", case.template_bone())):
        b = case.bone_distance_mm(bone)
        figures[name] = np.median(b)
        print(f"{name:34s} {np.median(b):7.2f} {np.percentile(b, 75):7.2f} {np.percentile(b, 90):7.2f}")
    print(f"({len(case.scanned_bone())} bone points under the scanned face)")
    print()
    print(f"{'tissue depth (mm)':28s} {'table':>6s} {'CT':>6s} {'ours':>6s}")
    rows = realct.tissue_depths(case)
    for name, table, real, ours in rows:
        print(f"{name:28s} {table:6.1f} {real:6.1f} {ours:6.1f}")
    ok = [(t, r, o) for _, t, r, o in rows if np.isfinite(r) and np.isfinite(o)]
    ours, table = np.array([abs(o - r) for t, r, o in ok]), np.array([abs(t - r) for t, r, o in ok])
    for name, stat in (("median", np.median), ("mean", np.mean)):
        print(f"{name} |depth - CT| over {len(ok)} landmarks: ours {stat(ours):.2f} mm, the table's means "
              f"{stat(table):.2f} mm")


if __name__ == "__main__":
    main()
