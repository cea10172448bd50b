"""Batch entry: ``python -m headadapt_addon.batch COMMAND ...`` or
``blender -b --python headadapt_addon/batch.py -- COMMAND ...``.

Commands:
  adapt --scan SCAN --landmarks L.json|L.pp --out DIR   adapt the template onto one scan
  folder --folder DIR --out DIR [--jobs N]              adapt every scan + landmarks pair in a folder
  demo [--out DIR]                                      adapt onto the bundled sample scan

The log states how the fit ended (folds left, distance RMS over the face the scan shows, marker
error if the landmark file has markers); every warning (a flagged or dropped FDP, swapped labels,
folds left, a face far from the scan) is a line "headadapt: warning: ..." on stderr and in
report.json's "outcome".

Exit codes: 0 the fit is ok; 2 bad input (one line on stderr names it); 3 the fit finished but is
not trustworthy (outcome.ok false: folds left or the face far from the scan; the OBJ, report.json
and .blend are still written). folder: 3 if any scan's fit is not trustworthy and none failed; with
failures (named in summary.json) 0 if any scan was adapted, 1 if none.
"""

import argparse
import json
import pathlib
import sys
import time

if __name__ == "__main__" and not __package__:      # run as a script (blender --python batch.py)
    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
    __package__ = "headadapt_addon"                  # noqa: A001

ROOT = pathlib.Path(__file__).resolve().parents[1]
SAMPLE_DIR = ROOT / "assets" / "sample_scan"


def build_parser():
    """The command-line interface of the batch job."""
    parser = argparse.ArgumentParser(prog="headadapt", description=__doc__.split("\n\n")[0],
                                     epilog=__doc__.split("\n\n")[-1],      # the exit codes
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)

    def common(p):
        p.add_argument("--levels", type=int, default=4, help="maximum number of levels after level 0 (default 4)")
        p.add_argument("--calibration", choices=("auto", "paper", "umeyama"), default="auto")
        p.add_argument("--keep-flagged", action="store_true",
                       help="keep FDPs flagged as wrongly clicked (default: drop them and say so)")
        p.add_argument("--blend", help="also write a .blend with the result")

    a = sub.add_parser("adapt", help="adapt the template onto a scan")
    a.add_argument("--scan", required=True, help="scan mesh: OBJ, PLY or STL (any unit, any pose)")
    a.add_argument("--landmarks", required=True, help='FDPs on the scan: JSON {"points": {"3.7": [x,y,z]}} or MeshLab .pp')
    a.add_argument("--out", required=True, help="output folder (adapted_head.obj, report.json)")
    common(a)
    f = sub.add_parser("folder", help="adapt every scan + landmarks pair in a folder (process pool)")
    f.add_argument("--folder", required=True, help="folder of NAME.obj|ply|stl with NAME.json or NAME.pp beside it")
    f.add_argument("--out", required=True, help="output folder; one sub-folder per scan, plus summary.json")
    f.add_argument("--jobs", type=int, default=0, help="worker processes (default: the number of cores)")
    common(f)
    d = sub.add_parser("demo", help="adapt the bundled template onto the bundled sample scan")
    d.add_argument("--out", default=str(ROOT / "out" / "demo"), help="output folder (default out/demo)")
    common(d)
    return parser


def _stderr(line):
    print(line, file=sys.stderr)


def run_adapt(scan_path, landmarks_path, out_dir, levels=4, calibration="auto", keep_flagged=False,
              blend=None, log=print, warn=_stderr):
    """Adapt the template onto one scan file; write adapted_head.obj + report.json (atomic); return the
    report. Progress goes to log, one line per warning to warn; report["outcome"]["ok"] says whether
    the fit can be trusted (main: exit code 3 if not)."""
    from .core import meshio
    from .core.adapt import outcome as outcome_text
    from .core.adapt.pipeline import AdaptOptions, adapt
    from .core.template import load_template

    t0 = time.perf_counter()
    out_dir = pathlib.Path(out_dir)
    tpl = load_template()
    verts, tris = meshio.read_mesh(scan_path)
    points = meshio.read_landmarks(landmarks_path)
    meta = meshio.read_landmarks.last_meta
    markers = meta.get("markers")
    options = AdaptOptions(max_levels=levels, calibration=calibration, drop_flagged=not keep_flagged)
    log(f"headadapt: {pathlib.Path(scan_path).name}: {len(verts):,} vertices, {len(tris):,} triangles, "
        f"{len(points)} FDPs")
    result = adapt(tpl, verts, tris, points, options, markers=markers,
                   progress=lambda f, msg: log(f"  {100 * f:5.1f}%  {msg}"))
    report = {
        "scan": str(scan_path), "landmarks": str(landmarks_path),
        "template_sha256": tpl.meta["content_sha256"],
        "scan_vertices": int(len(verts)), "scan_triangles": int(len(tris)),
        **result.report(),
        "total_seconds": time.perf_counter() - t0,
    }
    meshio.write_obj(out_dir / "adapted_head.obj", result.verts_scan, tpl.skin.tris,
                     header="HeadAdapt adapted skin, template vertex order, scan frame and unit")
    meshio.write_atomic(out_dir / "report.json", json.dumps(report, indent=1, default=float))
    for lv in result.levels:
        log(f"  level {lv.level}: {lv.method:5s} {lv.pairs:5d} pairs  E_d {lv.E_d:8.3f} mm^2  "
            f"RMS {lv.E_d_rms_mm:6.3f} mm  E {lv.E:8.3f}  {lv.seconds:6.2f} s")
    if result.calibration_info.get("scan_pieces_turned"):
        log(f"  {result.calibration_info['scan_pieces_turned']} scan piece(s) faced inward: read turned round")
    if result.unfolded and result.unfolded["folded_triangles"]:
        log(f"  {result.unfolded['folded_triangles']} folded triangles relaxed "
            f"({result.unfolded['vertices_relaxed']} vertices), {result.unfolded['folded_left']} left")
    log(f"headadapt: best level {result.best_level}; {outcome_text.verdict(result.outcome)}")
    for line in outcome_text.warning_lines(result.outcome, result.flagged, result.dropped):
        warn(f"headadapt: warning: {line}")
    log(f"headadapt: wrote {out_dir / 'adapted_head.obj'} and {out_dir / 'report.json'} in "
        f"{report['total_seconds']:.2f} s")
    if blend:
        from .blender import blendout
        blendout.write_blend(blend, tpl, result, verts, tris, points, report)
        log(f"headadapt: wrote {blend}")
    return report


def find_pairs(folder):
    """[(scan path, landmark path or None)] for every scan file in folder, sorted by name."""
    folder = pathlib.Path(folder)
    out = []
    for scan in sorted(p for p in folder.iterdir() if p.suffix.lower() in (".obj", ".ply", ".stl")):
        marks = [scan.with_suffix(s) for s in (".json", ".pp") if scan.with_suffix(s).is_file()]
        out.append((scan, marks[0] if marks else None))
    return out


def _folder_job(job):
    scan, marks, out_dir, levels, calibration, keep_flagged, blend = job
    from .core.exceptions import HeadAdaptError
    if marks is None:
        return {"scan": str(scan), "ok": False, "error": f"no landmark file {scan.stem}.json or {scan.stem}.pp beside it"}
    warnings = []
    try:
        rep = run_adapt(scan, marks, out_dir, levels, calibration, keep_flagged,
                        str(pathlib.Path(out_dir) / f"{scan.stem}.blend") if blend else None, log=lambda *a: None,
                        warn=lambda line: warnings.append(line.removeprefix("headadapt: warning: ")))
    except HeadAdaptError as exc:
        return {"scan": str(scan), "ok": False, "error": str(exc)}
    best = rep["levels"][rep["best_level"]]
    return {"scan": str(scan), "ok": True, "outcome_ok": rep["outcome"]["ok"], "best_level": rep["best_level"],
            "E_d_rms_mm": best["E_d_rms_mm"], "outcome": rep["outcome"], "seconds": rep["total_seconds"],
            "flagged_fdps": list(rep["flagged_fdps"]), "warnings": warnings}


def run_folder(folder, out, jobs=0, levels=4, calibration="auto", keep_flagged=False, blend=False, log=print,
               warn=_stderr):
    """Adapt every scan + landmarks pair of a folder in a process pool; failures are reported, not fatal.
    A scan adapted with an outcome that is not ok counts as done with warnings ("outcome_ok": false)."""
    import concurrent.futures
    import os

    from .core import meshio
    from .core.adapt import outcome as outcome_text
    pairs = find_pairs(folder)
    if not pairs:
        from .core.exceptions import FileFormatError
        raise FileFormatError(f"{folder}: no OBJ, PLY or STL scans in this folder")
    out = pathlib.Path(out)
    work = [(s, m, out / s.stem, levels, calibration, keep_flagged, blend) for s, m in pairs]
    workers = jobs or min(len(work), os.cpu_count() or 1)
    import multiprocessing
    ctx = multiprocessing.get_context("spawn")     # bpy and fork do not mix
    with concurrent.futures.ProcessPoolExecutor(max_workers=workers, mp_context=ctx) as pool:
        results = list(pool.map(_folder_job, work))
    for r in results:
        name = pathlib.Path(r["scan"]).name
        if not r["ok"]:
            log(f"  FAIL {name}: {r['error']}")
            continue
        log(f"  {'ok  ' if r['outcome_ok'] else 'WARN'} {name}: level {r['best_level']}, "
            f"{outcome_text.verdict(r['outcome'])}, {r['seconds']:.1f} s")
        for line in r["warnings"]:
            warn(f"headadapt: warning: {name}: {line}")
    summary = {"folder": str(folder), "done": sum(r["ok"] for r in results),
               "done_with_warnings": sum(r["ok"] and not r["outcome_ok"] for r in results),
               "failed": sum(not r["ok"] for r in results), "scans": results}
    meshio.write_atomic(out / "summary.json", json.dumps(summary, indent=1, default=float))
    log(f"headadapt: {summary['done']} adapted ({summary['done_with_warnings']} not trustworthy), "
        f"{summary['failed']} failed; wrote {out / 'summary.json'}")
    return summary


def main(argv=None):
    """Run one batch command; returns the process exit code (module docstring: 0 ok, 2 bad input,
    3 the fit finished but is not trustworthy; folder: 1 when no scan could be adapted)."""
    from .core.exceptions import HeadAdaptError

    if argv is None:
        argv = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]
    args = build_parser().parse_args(argv)
    try:
        if args.command == "demo":
            out = pathlib.Path(args.out)
            report = run_adapt(SAMPLE_DIR / "scan.ply", SAMPLE_DIR / "landmarks.json", out, args.levels,
                               args.calibration, args.keep_flagged, args.blend or str(out / "demo.blend"))
        elif args.command == "folder":
            summary = run_folder(args.folder, args.out, args.jobs, args.levels, args.calibration, args.keep_flagged,
                                 bool(args.blend))
            if summary["failed"]:
                return 0 if summary["done"] else 1
            return 3 if summary["done_with_warnings"] else 0
        else:
            report = run_adapt(args.scan, args.landmarks, args.out, args.levels, args.calibration,
                               args.keep_flagged, args.blend)
    except HeadAdaptError as exc:
        print(f"headadapt: error: {exc}", file=sys.stderr)
        return 2
    return 0 if report["outcome"]["ok"] else 3


if __name__ == "__main__":
    try:
        code = main()
    except Exception:          # a bug, not bad input: Blender would print it and still exit 0
        import traceback
        traceback.print_exc()
        print("headadapt: internal error (the traceback above); please report it", file=sys.stderr)
        code = 1
    if "bpy" in sys.modules and getattr(sys.modules["bpy"].app, "background", False) and code:
        sys.stderr.flush()
    sys.exit(code)
