"""Batch entry: ``python -m headadapt_addon.batch COMMAND ...`` or
``blender -b --python headadapt_addon/batch.py -- COMMAND ...``.

Commands:
  adapt --scan SCAN --landmarks L.json|L.pp --out DIR [--blend FILE] [--preview PNG]   adapt the template onto one scan
  folder --folder DIR --out DIR [--blend] [--preview] [--jobs N | --scheduler tcp://HOST:8786]
                                    adapt every scan + landmarks pair in a folder, each in its own process
  demo [--out DIR]                  adapt onto the bundled sample scan, with a .blend and a preview picture
                                    (replaces an earlier demo's files)

The log states how the fit ended (folds left, distance RMS over the face the scan shows, marker
error if the landmark file has markers); every warning (a flagged or dropped FDP, swapped labels,
folds left, a face far from the scan) is a line "headadapt: warning: ..." on stderr and in
report.json's "outcome". Results are written atomically; report.json is written last and says
"status": "done" only for a finished run, with the sha256 of the inputs it was made from. No output
may be an input of the run, and existing results are replaced only with --overwrite.

Exit codes: 0 the fit is ok; 1 internal error (a bug: the traceback is in the log); 2 bad input, an
input that cannot be read, an output that cannot be written or would replace an input or an earlier
result (one line on stderr names the file); 3 the fit finished but is not trustworthy (folds left or
the face far from the scan; its OBJ, report.json and .blend are still written). folder: 4 if any scan
failed (each named in summary.json), else 3 if any fit is not trustworthy, else 0; 130 when
interrupted (summary.json lists what did not finish).
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import hashlib
import json
import os
import pathlib
import signal
import subprocess
import sys
import tempfile
import threading
import time
import traceback
import uuid

if __name__ == "__main__" and not __package__:      # run as a script (blender --python batch.py)
    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
    __package__ = "headadapt_addon"

if __name__ == "__main__":
    # numpy asks for transparent huge pages on every array of 4 MB or more (madvise). Where the kernel's
    # THP defrag setting is "madvise" (Ubuntu's default), the first touch of such memory may stall on
    # compaction (numpy issue 31590); a 1M-vertex scan's preparation allocates gigabytes of short-lived
    # arrays, and on the 2-core test machine these faults cost 1.5-2 s of a 8.5 s command. Checked by
    # numpy at import, so set before it is imported (only here, in the command's own process and the
    # folder's children; the user's own NUMPY_MADVISE_HUGEPAGE wins; Blender's process is left alone).
    os.environ.setdefault("NUMPY_MADVISE_HUGEPAGE", "0")
    # One BLAS thread (read by OpenBLAS when numpy loads it; the user's own setting wins): the core's
    # worker threads and the bake's helper process keep the cores busy already, and OpenBLAS's own
    # threads beside them only spin for work (a 31k-vertex scan's command spent 0.4 s of system time in
    # them). With one: the 31k command 4% faster, the 1M one 2%, the 76 keys' bake on two cores 8%,
    # the answers the same to the bit.
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

ROOT = pathlib.Path(__file__).resolve().parents[1]
SAMPLE_DIR = ROOT / "assets" / "sample_scan"
SCAN_SUFFIXES = (".obj", ".ply", ".stl")
EXIT_OK, EXIT_BUG, EXIT_BAD_INPUT, EXIT_UNTRUSTWORTHY, EXIT_SCAN_FAILED, EXIT_INTERRUPTED = 0, 1, 2, 3, 4, 130


def _at_least(low, kind, strictly=False):
    """An argparse type: a number of `kind` at least (strictly: over) `low`, else the usual one-line
    argparse error (exit 2) before anything runs: --timeout 0 killed every scan at once."""
    def parse(text):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
        if value < low or (strictly and value == low) or value != value:
            raise argparse.ArgumentTypeError(f"{text} is not {'over' if strictly else 'at least'} {low}")
        return value
    return parse


def build_parser():
    """The command-line interface of the batch job."""
    from .core.adapt.options import MAX_LEVELS, AdaptOptions

    parser = argparse.ArgumentParser(prog="headadapt", description=__doc__.split("\n\n")[0],
                                     epilog=__doc__.split("\n\n")[-1],      # the exit codes
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True, metavar="{adapt,folder,demo}")   # not _scan

    def common(p, demo=False):
        p.add_argument("--levels", type=int, default=AdaptOptions.max_levels, choices=range(MAX_LEVELS + 1),
                       metavar="LEVELS", help=f"maximum number of levels after level 0, 0 to {MAX_LEVELS} "
                                              "(default %(default)s)")
        p.add_argument("--calibration", choices=("auto", "paper", "umeyama"), default="auto",
                       help="how the template is first placed on the clicks: the paper's construction from 8 "
                            "FDPs, a least-squares similarity over all clicked FDPs (umeyama), or auto (the one "
                            "nearer the clicks; default)")
        p.add_argument("--keep-flagged", action="store_true",
                       help="keep FDPs flagged as wrongly clicked (default: drop them and say so)")
        p.add_argument("--overwrite", action="store_true",
                       help="ignored: demo always replaces its own files" if demo else
                       "replace the results of an earlier run (default: refuse, exit 2)")

    a = sub.add_parser("adapt", help="adapt the template onto a scan")
    a.add_argument("--scan", required=True, help="scan mesh: OBJ, PLY or STL (any unit, any pose)")
    a.add_argument("--landmarks", required=True, help='FDPs on the scan: JSON {"points": {"3.7": [x,y,z]}} or MeshLab .pp')
    a.add_argument("--out", required=True, help="output folder (adapted_head.obj, report.json)")
    a.add_argument("--blend", help="also write a .blend with the result to this file")
    a.add_argument("--preview", help="also write a PNG of the scan beside the result with its heat map, "
                                     "front and side (1280x1280), rendered headless (Workbench)")
    common(a)
    f = sub.add_parser("folder", help="adapt every scan + landmarks pair in a folder, each scan in its own process")
    f.add_argument("--folder", required=True, help="folder of NAME.obj|ply|stl with NAME.json or NAME.pp beside it")
    f.add_argument("--out", required=True, help="output folder: one sub-folder per scan, plus summary.json")
    f.add_argument("--blend", action="store_true", help="also write OUT/NAME/NAME.blend for each scan")
    f.add_argument("--preview", action="store_true",
                   help="also write OUT/NAME/preview.png for each scan (the scan beside the head with its heat map)")
    f.add_argument("--jobs", type=_at_least(0, int), default=0, help="scans at a time (default 0: the number of cores)")
    f.add_argument("--timeout", type=_at_least(0, float, strictly=True), default=900.0,
                   help="seconds a scan may take before its process is killed (default 900)")
    f.add_argument("--memory-gb", type=_at_least(0, float, strictly=True), default=8.0,
                   help="address-space limit of each scan's process, GB (default 8)")
    f.add_argument("--scheduler", help="run the scans on this Dask distributed scheduler (tcp://HOST:8786) "
                                       "instead of local processes; OUT must be visible to its workers")
    f.add_argument("--resume", action="store_true",
                   help="keep the scans an earlier run into OUT finished from the same files and options, and run "
                        "the rest (an interrupted or failed run, new scans added to the folder)")
    common(f)
    d = sub.add_parser("demo", help="adapt the bundled template onto the bundled sample scan")
    # in a checkout out/demo; an installed extension's own folder is replaced by its next update
    here = ROOT / "out" / "demo" if (ROOT / "ha").exists() else pathlib.Path.cwd() / "headadapt_demo"
    d.add_argument("--out", default=str(here),
                   help="output folder (default out/demo in a checkout, else headadapt_demo where it is run)")
    common(d, demo=True)
    s = sub.add_parser("_scan")                      # one scan of folder mode, in its own process
    s.add_argument("job", help=argparse.SUPPRESS)
    return parser


def _say(line, stream) -> None:
    """Write a line to a standard stream so that a reader gone (a monitor's `| head`: broken pipe) or an
    encoding that cannot spell a scan's name (PYTHONIOENCODING=latin-1) never stops the run: the first
    sends the stream's later lines to /dev/null, the second writes the name with escapes."""
    try:
        try:
            print(line, file=stream, flush=True)
        except UnicodeEncodeError:
            encoding = getattr(stream, "encoding", None) or "ascii"
            print(line.encode(encoding, "backslashreplace").decode(encoding), file=stream, flush=True)
    except BrokenPipeError:
        with contextlib.suppress(OSError, ValueError):
            os.dup2(os.open(os.devnull, os.O_WRONLY), stream.fileno())


def _stdout(line):
    _say(line, sys.stdout)


def _stderr(line):
    _say(line, sys.stderr)


# ---------------------------------------------------------------------------------------------
# outputs never destroy inputs
# ---------------------------------------------------------------------------------------------
def same_file(a: os.PathLike | str, b: os.PathLike | str) -> bool:
    """Whether paths a and b name the same file: the same path once resolved (symbolic links, ..), or
    the same file on disk (hard links)."""
    a, b = pathlib.Path(a), pathlib.Path(b)
    if os.path.abspath(a) == os.path.abspath(b) or a.resolve() == b.resolve():
        return True
    try:
        return os.path.samefile(a, b)
    except OSError:
        return False


def check_outputs(inputs: list[pathlib.Path], outputs: dict[str, pathlib.Path], overwrite: bool,
                  hint: str = "--overwrite replaces it", replaceable=()) -> None:
    """FileFormatError (exit 2) if an output is one of the inputs, two outputs are one file, or an output
    not in `replaceable` exists and overwrite is false (the message ends with `hint`). outputs: {what it
    is: path}."""
    from .core.exceptions import FileFormatError

    items = list(outputs.items())
    for what, out in items:
        for inp in inputs:
            if same_file(out, inp):
                raise FileFormatError(f"refusing to write {out} ({what}): it is {inp}, an input of this run")
    for i, (what, out) in enumerate(items):
        for other, path in items[i + 1:]:
            if same_file(out, path):
                raise FileFormatError(f"refusing to write {out}: it would be both the {what} and the {other}")
    if not overwrite:
        for what, out in items:
            if out.exists() and out not in replaceable:
                raise FileFormatError(f"refusing to replace {out} ({what} of an earlier run); {hint}")


def remove_results(paths) -> None:
    """Delete earlier results (missing ones are fine); FileFormatError names one that cannot be deleted."""
    from .core.exceptions import FileFormatError

    for path in paths:
        try:
            pathlib.Path(path).unlink(missing_ok=True)
        except NotADirectoryError:
            pass                          # its folder is a file: nothing there to delete
        except OSError as exc:
            raise FileFormatError(f"cannot replace {path}: {exc.strerror or exc}") from None


def remove_temporaries(paths) -> None:
    """Delete what an atomic write of each path leaves when its process is killed mid-write: the hidden
    ".NAME.*" files (meshio.write_atomic, the .blend's) and ".STEM.*" folders (the preview's) beside it."""
    import shutil

    for path in map(pathlib.Path, paths):
        if not path.parent.is_dir():
            continue
        for left in {*path.parent.glob(f".{path.name}.*"), *path.parent.glob(f".{path.stem}.*")}:
            with contextlib.suppress(OSError):
                shutil.rmtree(left) if left.is_dir() else left.unlink()


def check_writable(outputs: dict[str, pathlib.Path]) -> None:
    """FileFormatError (exit 2) naming the first output whose folder cannot be made or written, found
    before the run rather than after its fit (a file in the folder's place, no permission, /proc): a
    file is created and deleted in the output's folder, or in its nearest existing parent (nothing
    made is left behind)."""
    from .core.exceptions import FileFormatError

    for what, out in outputs.items():
        folder = pathlib.Path(os.path.abspath(out)).parent
        while not folder.exists() and folder != folder.parent:
            folder = folder.parent
        try:
            if not folder.is_dir():
                raise FileFormatError(f"cannot write {out} ({what}): {folder} is a file, not a folder")
            fd, probe = tempfile.mkstemp(prefix=f".{out.name}.", suffix=".probe", dir=folder)
            os.close(fd)
            os.unlink(probe)
        except OSError as exc:
            raise FileFormatError(f"cannot write {out} ({what}): {exc.strerror or exc}") from None


@contextlib.contextmanager
def holding(out_dir: os.PathLike | str):
    """Hold the output folder for this run (an exclusive flock on the folder itself): a second HeadAdapt
    run into it while this one lasts is refused (FileFormatError: exit 2), as two runs writing the same
    files would leave reports that contradict their results. Yields (whether the folder is held: False
    where flock is missing or cannot lock a folder, Windows, NFS; whether this run made it). The lock ends with the process, however it ends (kill -9 too), so
    nothing is left to clean; a folder made here for it and left empty is removed."""
    from .core.exceptions import FileFormatError

    out = pathlib.Path(os.path.abspath(out_dir))
    made = out                            # the first folder of the path this run makes, if any
    while not made.parent.exists() and made.parent != made:
        made = made.parent
    made = None if out.exists() else made
    try:
        import fcntl
        out.mkdir(parents=True, exist_ok=True)
        fd = os.open(out, os.O_RDONLY)
    except (ImportError, OSError):          # no flock here, or a folder that cannot be made (checked later)
        yield False, False
        return
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            held = True
        except BlockingIOError:
            raise FileFormatError(f"{out}: another HeadAdapt run is writing into this folder now; wait for it "
                                  "to end, or give another --out") from None
        except OSError:                   # a file system that cannot lock a folder (NFS emulates flock with
            held = False                  # a write lock, refused on a folder): the run goes on unguarded
        yield held, made is not None
    finally:
        os.close(fd)
        folder = out
        while made is not None:           # the folders made here, if this run left them empty (bad input)
            try:
                folder.rmdir()
            except OSError:
                break
            if folder == made:
                break
            folder = folder.parent


def failed_before(outputs: dict[str, pathlib.Path], held: bool = False) -> set:
    """{the report} when the only output there is a report.json of a run that failed or was interrupted:
    it holds an error, no result, so a run after the input is mended may replace it without --overwrite.
    With the folder held (holding), a report still "running" is one whose run was killed (SIGTERM, kill
    -9, a lost machine): replaceable too."""
    report = outputs["report"]
    if any(path.exists() for what, path in outputs.items() if what != "report"):
        return set()
    try:
        status = json.loads(report.read_text()).get("status")
    except (OSError, ValueError, AttributeError):
        return set()
    return {report} if status in ("failed", "interrupted") or (held and status == "running") else set()


def file_sha256(path: os.PathLike | str) -> str:
    """sha256 of a file's bytes, read in 1 MB blocks."""
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


# ---------------------------------------------------------------------------------------------
# one scan
# ---------------------------------------------------------------------------------------------
def result_paths(out_dir: os.PathLike | str, blend: os.PathLike | str | None = None,
                 preview: os.PathLike | str | None = None) -> dict[str, pathlib.Path]:
    """{what: path} of everything a run of adapt writes: the adapted OBJ, report.json, the .blend and
    the preview PNG."""
    out_dir = pathlib.Path(out_dir)
    paths = {"adapted OBJ": out_dir / "adapted_head.obj", "report": out_dir / "report.json"}
    if blend:
        paths["--blend file"] = pathlib.Path(blend)
    if preview:
        paths["--preview image"] = pathlib.Path(preview)
    return paths


def earlier_outputs(out_dir, inputs) -> list[pathlib.Path]:
    """The files an earlier run into out_dir wrote (its report.json's "outputs") that lie in out_dir and
    are none of `inputs`: what --overwrite removes beside the outputs of the run to come."""
    out_dir = pathlib.Path(out_dir)
    try:
        listed = json.loads((out_dir / "report.json").read_text(encoding="utf-8")).get("outputs") or {}
    except (OSError, ValueError, AttributeError):
        return []
    found = []
    for path in map(pathlib.Path, listed.values() if isinstance(listed, dict) else ()):
        if path.parent.resolve() == out_dir.resolve() and not any(same_file(path, i) for i in inputs):
            found.append(path)
    return found


def run_adapt(scan_path, landmarks_path, out_dir, levels=None, calibration="auto", keep_flagged=False,
              blend=None, overwrite=False, run_id=None, log=_stdout, warn=_stderr, preview=None):
    """Adapt the template onto one scan file; write adapted_head.obj (+ the .blend) and report.json last,
    all atomically; return the report. Progress goes to log, one line per warning to warn;
    report["outcome"]["ok"] says whether the fit can be trusted (main: exit code 3 if not).

    Refuses (FileFormatError) an output that is an input, a second run into out_dir while this one
    lasts (holding) and, unless overwrite, any existing result but the report of a run that failed,
    was interrupted or was killed; with overwrite the earlier results are deleted first. Any failure
    after that leaves report.json with "status": "failed" and the error (and no result beside it),
    then raises."""
    with holding(out_dir) as (held, made):
        return _run_adapt(scan_path, landmarks_path, out_dir, levels, calibration, keep_flagged, blend, overwrite,
                          run_id, log, warn, preview, held, made)


def _run_adapt(scan_path, landmarks_path, out_dir, levels, calibration, keep_flagged, blend, overwrite, run_id,
               log, warn, preview, held, made=False):
    """run_adapt's work, the output folder held (or not, where flock is missing: held False); made: the
    folder was made for this run (input refused before anything was written there: nothing is)."""
    from .core import __version__, meshio
    from .core.adapt import outcome as outcome_text
    from .core.exceptions import FileFormatError, HeadAdaptError

    t0 = time.perf_counter()
    out_dir = pathlib.Path(out_dir)
    outputs = result_paths(out_dir, blend, preview)
    check_outputs([pathlib.Path(scan_path), pathlib.Path(landmarks_path)], outputs, overwrite,
                  replaceable=failed_before(outputs, held))
    if preview and pathlib.Path(preview).suffix.lower() != ".png":
        raise FileFormatError(f"--preview {preview}: the preview is a PNG image, name a .png file")
    if blend and pathlib.Path(blend).suffix.lower() != ".blend":
        raise FileFormatError(f"--blend {blend}: Blender opens a .blend file, name a .blend file")
    check_writable(outputs)
    if overwrite:                         # the earlier run's other files too (its .blend, its preview)
        remove_results(earlier_outputs(out_dir, [pathlib.Path(scan_path), pathlib.Path(landmarks_path)]))
    remove_results(outputs.values())
    record = {"status": "running", "run": run_id or uuid.uuid4().hex, "scan": str(scan_path),
              "landmarks": str(landmarks_path), "headadapt_version": __version__,
              "options": run_options(levels, calibration, keep_flagged),
              "outputs": {what: str(path) for what, path in outputs.items()}}
    try:
        verts, tris = meshio.read_mesh(scan_path)
        verts = as_blender_stores(verts)
        points, meta = meshio.read_landmark_file(landmarks_path)
        markers = meta.get("markers")
        record["stage_seconds"] = {"read": time.perf_counter() - t0}
        try:
            record["inputs_sha256"] = {"scan": file_sha256(scan_path), "landmarks": file_sha256(landmarks_path)}
        except OSError as exc:
            raise FileFormatError(f"cannot read {exc.filename}: {exc.strerror}") from None
        meshio.write_atomic(outputs["report"], json.dumps(record, indent=1))
        made = False                      # the folder holds this run's report now
        report = _adapt_and_write(record, verts, tris, points, markers, outputs, levels, calibration, keep_flagged,
                                  t0, log, warn)
    except BaseException as exc:
        if isinstance(exc, HeadAdaptError):
            record.update(status="failed", error=str(exc))
        elif isinstance(exc, KeyboardInterrupt):
            record.update(status="interrupted", error=f"{scan_path}: interrupted")
        elif isinstance(exc, MemoryError):
            record.update(status="failed", error=f"{scan_path}: out of memory")
        else:
            record.update(status="failed", error=f"{scan_path}: internal error: {type(exc).__name__}: {exc}",
                          traceback=traceback.format_exc())
        if out_dir.is_dir() and not made:
            try:                          # the report first (out of memory, little else may work) ...
                meshio.write_atomic(outputs["report"], json.dumps(record, indent=1))
                # ... then what this run wrote before it failed, which is no result
                remove_results([path for name, path in outputs.items() if name != "report"])
            except (FileFormatError, MemoryError):
                pass                      # the original error is the one to report
        raise
    log(f"headadapt: best level {report['best_level']}; {outcome_text.verdict(report['outcome'])}")
    for line in report["warnings"]:
        warn(f"headadapt: warning: {line}")
    log(f"headadapt: wrote {', '.join(str(p) for p in outputs.values())} in {report['total_seconds']:.2f} s")
    return report


def run_options(levels=None, calibration="auto", keep_flagged=False) -> dict:
    """The choices a run was made with, as report.json records them (folder --resume keeps a result only
    if they are this run's)."""
    from .core.adapt.options import AdaptOptions
    return {"levels": AdaptOptions.max_levels if levels is None else int(levels), "calibration": calibration,
            "keep_flagged": bool(keep_flagged)}


def as_blender_stores(verts):
    """Scan vertices rounded to float32, as a Blender mesh stores them (float64 again for the fit):
    the batch and the panels then start from the same numbers and give the same head. The rounding
    is 1e-7 of the scan's size, but the fit is not smooth in its input (closest-point pairs, the
    level where E is least): on the four real scans the unrounded coordinates moved the adapted skin
    by 0.3 to 1.7% of the scan's size (headsq CT 3.3 mm, Fran 1.4 mm), at the same best level."""
    import numpy as np
    return np.asarray(verts, dtype=np.float32).astype(np.float64)


def adapt_options(levels=None, calibration="auto", keep_flagged=False):
    """The AdaptOptions of the batch's choices; the panels build theirs through this too
    (ui.operators.adapt_options), so the same scan and clicks give the same result in both (with the
    same spatial backend: spatial_backend(); inside Blender the numpy tree)."""
    from .core.adapt import AdaptOptions
    return AdaptOptions(max_levels=AdaptOptions.max_levels if levels is None else levels,
                        calibration=calibration, drop_flagged=not keep_flagged, backend=spatial_backend())


def spatial_backend():
    """The batch's spatial backend, inside Blender or not: "embree" where the embreex package is
    installed (requirements.txt: rays in C, the adaptation in about 0.8 of the time) and this is not
    a Blender executable (whose own Embree would take embreex's calls: embree.available), else the
    numpy tree (core/mesh/bvh.py), never Blender's, so the batch imports bpy only to write a .blend (importing
    it costs about a second of the command, and a worker whose memory limit stops bpy loading still
    adapts). The two give the same heads up to float32 rounding at a ray's tie (report.json:
    spatial_backend)."""
    from .core.mesh import embree
    return "embree" if embree.available() else "numpy"


def _adapt_and_write(record, verts, tris, points, markers, outputs, levels, calibration, keep_flagged, t0, log,
                     warn):
    from .core import meshio
    from .core.adapt import adapt
    from .core.adapt import outcome as outcome_text
    from .core.exceptions import HeadAdaptError, LandmarkError
    from .core.template import load_template

    tpl = load_template()
    options = adapt_options(levels, calibration, keep_flagged)
    log(f"headadapt: {pathlib.Path(record['scan']).name}: {len(verts):,} vertices, {len(tris):,} triangles, "
        f"{len(points)} FDPs")
    try:
        result = adapt(tpl, verts, tris, points, options, markers=markers,
                       progress=lambda f, msg: log(f"  {100 * f:5.1f}%  {msg}"))
    except HeadAdaptError as exc:        # the one line names the file at fault: the clicks', else the scan
        raise type(exc)(f"{record['landmarks' if isinstance(exc, LandmarkError) else 'scan']}: {exc}") from None
    report = {
        **record, "status": "done",
        "template_sha256": tpl.meta["content_sha256"],
        "scan_vertices": int(len(verts)), "scan_triangles": int(len(tris)),
        **result.report(),
        "stage_seconds": {**record["stage_seconds"], **result.stages},    # read, then the adaptation's
        "warnings": outcome_text.warning_lines(result.outcome, result.flagged, result.dropped),
    }
    skin, anatomy = result.verts_scan, None
    if "--blend file" in outputs:
        # the OBJ is the .blend's skin: the anatomy's transfer seats the eye sockets' hidden lining on the
        # eyes and lifts visible skin off the bone (the fit's skin differed by up to 7.7 mm in the lining)
        from .core.anatomy import transfer

        t_transfer = time.perf_counter()
        anatomy = transfer(tpl, result)
        report["stage_seconds"]["transfer"] = time.perf_counter() - t_transfer
        skin = result.to_scan(anatomy.parts["skin"])
    meshio.write_obj(outputs["adapted OBJ"], skin, tpl.skin.tris,
                     header="HeadAdapt adapted skin, template vertex order, scan frame and unit")
    for lv in result.levels:
        log(f"  level {lv.level}: {lv.method:6s} {lv.pairs:5d} pairs  E_d {lv.E_d:8.3f} mm^2  "
            f"RMS {lv.E_d_rms_mm:6.3f} mm  E {lv.E:8.3f}  {lv.seconds:6.2f} s")
    info = result.calibration_info
    clustered = info.get("scan_clustered")
    if clustered:
        log(f"  dense scan clustered to a {clustered['cell_mm']:g} mm grid for the fit: {clustered['vertices']:,} -> "
            f"{clustered['kept']:,} vertices")
    welded = info.get("scan_welded")
    if welded:
        log(f"  the scan's triangles did not share their corners (split vertices, a triangle soup): "
            f"{welded['vertices']:,} -> {welded['kept']:,} vertices, welded where they coincide")
    if info.get("scan_triangles_repeated"):
        log(f"  {info['scan_triangles_repeated']:,} of the scan's triangles were written twice (a double-sided "
            "export?): dropped")
    if info.get("scan_triangles_turned"):
        log(f"  {info['scan_triangles_turned']:,} of the scan's triangles were wound against their neighbours: "
            "turned to match")
    if info.get("scan_pieces_turned"):
        log(f"  {info['scan_pieces_turned']} scan piece(s) faced inward: read turned round")
    if info.get("not_leaned_on"):
        log(f"  calibration fitted to the face's firm clicks, not to {', '.join(info['not_leaned_on'])} "
            "(loosely placed: the levels take them)")
    if result.unfolded and result.unfolded["folded_triangles"]:
        how = "repaired by the level below" if result.unfolded.get("repair") == "level below" else "relaxed"
        log(f"  {result.unfolded['folded_triangles']} folded triangles {how} "
            f"({result.unfolded['vertices_relaxed']} vertices), {result.unfolded['folded_left']} left")
    stages = report["stage_seconds"]          # each stage once: the .blend's own time without its bake
    if "--preview image" in outputs:
        t_preview = time.perf_counter()
        _write_preview(outputs["--preview image"], tpl, result, verts, tris, points, report, log, anatomy)
        stages["preview"] = time.perf_counter() - t_preview
    if "--blend file" in outputs:
        t_blend = time.perf_counter()
        _write_blend(outputs["--blend file"], tpl, result, verts, tris, points, report, log, anatomy)   # + bake
        stages["blend"] = time.perf_counter() - t_blend - stages.get("bake", 0.0)
    report["total_seconds"] = time.perf_counter() - t0
    meshio.write_atomic(outputs["report"], json.dumps(report, indent=1, default=float))
    return report


def _blendout():
    """blender.blendout, whose import starts Blender (bpy), with Ctrl-C held until it has started
    (core/interrupts.py: a KeyboardInterrupt in Blender's start-up scripts crashed the process)."""
    from .core.interrupts import held_ctrl_c

    with held_ctrl_c():
        from .blender import blendout
    return blendout


def _write_preview(path, tpl, result, verts, tris, points, report, log=_stdout, anatomy=None):
    """The preview PNG through blendout (bpy); Blender's failure to render or save names the file.
    anatomy: the transfer's, when the .blend's was made already (the preview then shows that one)."""
    from .core.exceptions import FileFormatError

    blendout = _blendout()

    try:
        blendout.write_preview(path, tpl, result, verts, tris, points, report, anatomy=anatomy)
    except RuntimeError as exc:
        raise FileFormatError(f"cannot write {path}: {str(exc).strip()}") from None
    log(f"headadapt: preview (scan beside the head with its heat map, front and side) in {path}")


def _write_blend(path, tpl, result, verts, tris, points, report, log=_stdout, anatomy=None):
    """The .blend through blendout (the only place the batch job imports bpy); Blender's failure to
    save (a full disk, a folder it cannot write) becomes a FileFormatError naming the file."""
    from .core.exceptions import FileFormatError

    blendout = _blendout()

    try:
        shown = [-1]

        def baking(fraction, name):          # one line per tenth of the bake (a bake takes 3 to 8 s)
            tenth = int(10 * fraction)
            if tenth > shown[0]:
                shown[0] = tenth
                log(f"  baking {100 * fraction:5.1f}%  {name}")

        blendout.write_blend(path, tpl, result, verts, tris, points, report, progress=baking, anatomy=anatomy)
    except RuntimeError as exc:            # bpy.ops report failures as RuntimeError
        raise FileFormatError(f"cannot write {path}: {str(exc).strip()}") from None


# ---------------------------------------------------------------------------------------------
# folder mode
# ---------------------------------------------------------------------------------------------
def find_pairs(folder):
    """[(scan path, landmark path or None)] for every scan file in folder, sorted by name. Hidden files
    are no scans (macOS's "._NAME.ply" resource forks, editors' and HeadAdapt's own temporaries); a
    landmark file's suffix may be in any case (NAME.JSON), .json first where both are there."""
    folder = pathlib.Path(folder)
    files = sorted(p for p in folder.iterdir() if not p.name.startswith(".") and not p.is_dir())
    # landmark files are regular files (a named pipe would hang its scan's process until the timeout)
    landmarks = [p for p in files if p.suffix.lower() in (".json", ".pp") and p.is_file()]
    exact = {p.name: p for p in landmarks}
    folded = {p.name.casefold(): p for p in reversed(landmarks)}
    out = []
    for scan in (p for p in files if p.suffix.lower() in SCAN_SUFFIXES):
        # the name as spelt first (Kim.ply: Kim.json, kim.ply: kim.json), then in any case (NAME.JSON)
        marks = ([exact[k] for s in (".json", ".pp") if (k := scan.stem + s) in exact]
                 + [folded[k] for s in (".json", ".pp") if (k := (scan.stem + s).casefold()) in folded])
        out.append((scan, marks[0] if marks else None))
    return out


def folder_notes(folder, out, pairs, names) -> list[str]:
    """What folder mode leaves alone but a pipeline should hear of: landmark files with no scan of their
    name beside them (a scan renamed, or exported as another format), and result folders in `out` that
    are none of this run's (a scan gone, or now named NAME_obj/NAME_ply beside a new twin)."""
    notes = []
    stems = {s.stem.casefold() for s, _ in pairs}
    own = {pathlib.Path(out) / "summary.json"}              # --out may be the folder itself
    alone = sorted(p.name for p in pathlib.Path(folder).iterdir() if not p.name.startswith(".")
                   and p.suffix.lower() in (".json", ".pp") and p.stem.casefold() not in stems and not p.is_dir()
                   and not any(same_file(p, o) for o in own))
    if alone:
        notes.append(f"{len(alone)} landmark file{'s' if len(alone) != 1 else ''} with no scan of that name "
                     f"beside {'them' if len(alone) != 1 else 'it'} in {folder}, not used: {', '.join(alone[:10])}"
                     + (" ..." if len(alone) > 10 else ""))
    ours = {n.casefold() for n in names}
    other = sorted(d.name for d in pathlib.Path(out).iterdir() if d.is_dir() and d.name.casefold() not in ours
                   and (d / "report.json").is_file()) if pathlib.Path(out).is_dir() else []
    if other:
        notes.append(f"{len(other)} result folder{'s' if len(other) != 1 else ''} in {out} of no scan of this "
                     f"run, left as {'they are' if len(other) != 1 else 'it is'}: {', '.join(other[:10])}"
                     + (" ..." if len(other) > 10 else ""))
    return notes


def output_names(scans: list[pathlib.Path]) -> list[str]:
    """One output folder name per scan, distinct even where file systems ignore case: the stem, or
    STEM_EXT where scans share a stem (head.obj and head.ply: head_obj, head_ply), numbered if still taken."""
    stems = collections.Counter(s.stem.casefold() for s in scans)
    seen, names = set(), []
    for scan in scans:
        base = scan.stem if stems[scan.stem.casefold()] == 1 else f"{scan.stem}_{scan.suffix[1:].lower()}"
        name, k = base, 2
        while name.casefold() in seen:
            name, k = f"{base}-{k}", k + 1
        seen.add(name.casefold())
        names.append(name)
    return names


# One BLAS thread per scan process: folder mode runs a process per scan side by side, and OpenBLAS's
# helper threads spin without end (a scan never finishing, not an out-of-memory) once --memory-gb's
# address-space limit stops their buffers being allocated. Nor a bake helper (core/skin/parallel.py):
# the scans side by side keep the cores busy already.
SCAN_PROCESS_THREADS = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
                        "HEADADAPT_BAKE_HELPER": "0"}


def _child_command(job: dict) -> list[str]:
    """The command that runs one scan of folder mode: this Python with the package importable, or, inside
    a Blender binary (whose Python cannot import bpy), Blender itself in background mode."""
    bpy = sys.modules.get("bpy")
    blender = getattr(getattr(bpy, "app", None), "binary_path", "") if bpy else ""
    if blender:
        return [blender, "-b", "--factory-startup", "--python", str(ROOT / "headadapt_addon" / "batch.py"),
                "--", "_scan", json.dumps(job)]
    return [sys.executable, "-m", "headadapt_addon.batch", "_scan", json.dumps(job)]


_running: set = set()          # the scan processes this process started and has not yet reaped
_running_lock = threading.Lock()
_stopping = threading.Event()  # set on Ctrl-C / SIGTERM: start no more scans


def _kill(proc: subprocess.Popen) -> None:
    """End a scan process and its children (it leads its own process group)."""
    try:
        if hasattr(os, "killpg"):
            os.killpg(proc.pid, signal.SIGKILL)
        else:
            proc.kill()
    except (ProcessLookupError, PermissionError):
        pass


def run_isolated(job: dict) -> dict:
    """Run one scan of folder mode in its own process (time and memory limits, killed at the timeout) and
    return its summary entry. Runs in a thread of the local pool or as a task on a Dask worker; either
    way the scan's log is OUT/NAME/log.txt and its report.json says how it ended."""
    from .core import meshio
    from .core.exceptions import HeadAdaptError

    out_dir = pathlib.Path(job["out_dir"])
    entry = {"scan": job["scan"], "landmarks": job["landmarks"], "out": str(out_dir), "ok": False}
    if _stopping.is_set():
        return {**entry, "status": "not finished", "error": "interrupted before it started"}
    if job["landmarks"] is None:
        stem = pathlib.Path(job["scan"]).stem
        error = f"{job['scan']}: no landmark file {stem}.json or {stem}.pp beside it"
        meshio.write_atomic(out_dir / "report.json", json.dumps(
            {"status": "failed", "run": job["run"], "scan": job["scan"], "error": error}, indent=1))
        return {**entry, "status": "failed", "error": error, "seconds": 0.0}
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])),
               **SCAN_PROCESS_THREADS)
    t0 = time.monotonic()
    out_dir.mkdir(parents=True, exist_ok=True)
    with open(out_dir / "log.txt", "wb") as log_file:
        proc = subprocess.Popen(_child_command(job), stdin=subprocess.PIPE, stdout=log_file, stderr=subprocess.STDOUT,
                                env=env, start_new_session=True)
        with _running_lock:
            _running.add(proc)
        try:
            code = proc.wait(timeout=job["timeout"])
        except subprocess.TimeoutExpired:
            _kill(proc)
            code = proc.wait()
            timed_out = True
        else:
            timed_out = False
        finally:
            with _running_lock:
                _running.discard(proc)
            proc.stdin.close()
    seconds = time.monotonic() - t0
    report = _read_report(out_dir / "report.json", job["run"])
    if timed_out:
        status, error = "timeout", f"{job['scan']}: no result after {job['timeout']:g} s; its process was killed"
    elif report.get("status") in ("done", "failed"):
        status, error = report["status"], report.get("error")
    elif _stopping.is_set():
        status, error = "not finished", "interrupted while running; its process was killed"
    else:
        status = "failed"
        error = (f"{job['scan']}: its process ended with code {code}"
                 + (f" (signal {-code}: killed, out of memory?)" if code < 0 else "") + " without a result")
    if status != "done":               # no result beside a report that says so (a killed scan's files)
        results = [path for what, path in result_paths(out_dir, job["blend"], job["preview"]).items()
                   if what != "report"]
        with contextlib.suppress(HeadAdaptError):
            remove_results(results)
        remove_temporaries(results + [out_dir / "report.json"])
        meshio.write_atomic(out_dir / "report.json", json.dumps(
            {**report, "status": "failed" if status != "not finished" else status, "run": job["run"],
             "scan": job["scan"], "error": error}, indent=1))
        return {**entry, "status": status, "error": error, "seconds": seconds}
    return _done_entry(entry, report, seconds)


def _done_entry(entry: dict, report: dict, seconds: float) -> dict:
    """The summary entry of a scan adapted: entry's scan, landmarks and out, the rest from its report."""
    return {**entry, "status": "done", "ok": True, "outcome_ok": report["outcome"]["ok"],
            "best_level": report["best_level"], "E_d_rms_mm": report["levels"][report["best_level"]]["E_d_rms_mm"],
            "outcome": report["outcome"], "seconds": seconds, "flagged_fdps": list(report["flagged_fdps"]),
            "warnings": report["warnings"], "inputs_sha256": report["inputs_sha256"]}


def kept_result(job: dict, template_sha256: str) -> dict | None:
    """folder --resume: the summary entry of a scan an earlier run into the same folder finished (report.json
    "done", every output of this run's options there) from the same scan and landmark bytes, template,
    HeadAdapt version and options as this run would use, marked "kept"; None if it is to run again."""
    from .core import __version__

    out_dir = pathlib.Path(job["out_dir"])
    try:
        report = json.loads((out_dir / "report.json").read_text())
    except (OSError, ValueError):
        return None
    if (not isinstance(report, dict) or report.get("status") != "done" or job["landmarks"] is None
            or report.get("template_sha256") != template_sha256 or report.get("headadapt_version") != __version__
            or report.get("options") != run_options(job["levels"], job["calibration"], job["keep_flagged"])
            or not all(p.is_file() for p in result_paths(out_dir, job["blend"], job["preview"]).values())):
        return None
    try:
        same = report.get("inputs_sha256") == {"scan": file_sha256(job["scan"]), "landmarks": file_sha256(job["landmarks"])}
        entry = {"scan": job["scan"], "landmarks": job["landmarks"], "out": str(out_dir), "ok": False}
        return {**_done_entry(entry, report, float(report["total_seconds"])), "kept": report["run"]} if same else None
    except (OSError, KeyError, TypeError, IndexError):
        return None


def _read_report(path: pathlib.Path, run: str) -> dict:
    """report.json if it belongs to this run, else {}."""
    try:
        report = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    return report if isinstance(report, dict) and report.get("run") == run else {}


def _scan_main(job_text: str) -> int:
    """The process of one scan in folder mode: memory limit, end with the parent, adapt, exit code."""
    job = json.loads(job_text)
    # The parent holds our stdin open; when it dies (kill -9) the pipe closes and this scan stops too.
    # (Started before the memory limit, which can leave no room for a thread's stack.)
    threading.Thread(target=_exit_with_parent, daemon=True).start()
    # the fit's modules (scipy's libraries) loaded before the limit, which is for the work: loaded under
    # it, they took the room the failure's own report needed
    from .core.adapt import adapt  # noqa: F401
    try:
        import resource
    except ImportError:                  # Windows: no address-space limit
        pass
    else:
        limit = int(job["memory_gb"] * (1 << 30))
        _, hard = resource.getrlimit(resource.RLIMIT_AS)
        resource.setrlimit(resource.RLIMIT_AS, (limit if hard == resource.RLIM_INFINITY else min(limit, hard), hard))
    return _adapt_exit_code(job["scan"], job["landmarks"], job["out_dir"], job["levels"], job["calibration"],
                            job["keep_flagged"], job["blend"], True, job["run"],
                            memory_hint=f" (the limit is {job['memory_gb']:g} GB: --memory-gb)",
                            preview=job.get("preview"))


def _exit_with_parent() -> None:
    """Read stdin (a pipe from the parent, never written) until it closes, then end this process at once.
    os.read, not sys.stdin: a daemon thread blocked in a buffered reader aborts the interpreter's exit."""
    while os.read(0, 4096):
        pass
    os._exit(EXIT_BUG)


def _adapt_exit_code(scan, landmarks, out, levels, calibration, keep_flagged, blend, overwrite, run_id=None,
                     memory_hint="", preview=None):
    """run_adapt with the error contract: 0/3 by the outcome, 2 with one line for bad input; an internal
    error prints its traceback and one line naming the scan, exit 1."""
    from .core.exceptions import HeadAdaptError

    try:
        report = run_adapt(scan, landmarks, out, levels, calibration, keep_flagged, blend, overwrite, run_id,
                           preview=preview)
    except HeadAdaptError as exc:
        _stderr(f"headadapt: error: {exc}")
        return EXIT_BAD_INPUT
    except MemoryError:
        _stderr(f"headadapt: error: {scan}: out of memory{memory_hint}")
        return EXIT_BUG
    except KeyboardInterrupt:             # Ctrl-C, SIGTERM: one line, no traceback; report.json says so
        _stderr(f"headadapt: interrupted: {scan} not adapted (its report.json says so; run it again to redo it)")
        return EXIT_INTERRUPTED
    except Exception:
        traceback.print_exc()
        _stderr(f"headadapt: internal error while adapting {scan} (the traceback above); please report it")
        return EXIT_BUG
    return EXIT_OK if report["outcome"]["ok"] else EXIT_UNTRUSTWORTHY


def run_folder(folder, out, jobs=0, levels=None, calibration="auto", keep_flagged=False, blend=False, overwrite=False,
               timeout=900.0, memory_gb=8.0, scheduler=None, log=_stdout, warn=_stderr, preview=False, resume=False):
    """Adapt every scan + landmarks pair of a folder, each scan in its own process (local threads start
    them, or the tasks of a Dask cluster at `scheduler`); return the summary, also in OUT/summary.json,
    which is rewritten after every scan and after an interruption (Ctrl-C, SIGTERM: "interrupted" true,
    the scans not done "not finished"). A scan adapted with an outcome that is not ok counts as done
    with warnings ("outcome_ok": false); a failed scan never stops the others. With resume, the scans an
    earlier run finished (kept_result) are kept as they are, named "kept" in the summary, and only the
    others run (their earlier files replaced). A second run into `out` while this one lasts is refused
    (holding)."""
    from .core.exceptions import FileFormatError

    folder, out = pathlib.Path(folder), pathlib.Path(out)
    if scheduler:           # a worker runs in its own folder: the paths it is given mean the same there
        folder, out = pathlib.Path(os.path.abspath(folder)), pathlib.Path(os.path.abspath(out))
    if not folder.is_dir():
        raise FileFormatError(f"{folder}: {'not a folder' if folder.exists() else 'no such folder'}")
    with holding(out):
        return _run_folder(folder, out, jobs, levels, calibration, keep_flagged, blend, overwrite, timeout,
                           memory_gb, scheduler, log, warn, preview, resume)


def _run_folder(folder, out, jobs, levels, calibration, keep_flagged, blend, overwrite, timeout, memory_gb,
                scheduler, log, warn, preview, resume):
    """run_folder's work, the output folder held."""
    from .core import meshio
    from .core.exceptions import FileFormatError
    from .core.template import TEMPLATE_DIR

    pairs = find_pairs(folder)
    if not pairs:
        raise FileFormatError(f"{folder}: no OBJ, PLY or STL scans in this folder")
    names = output_names([s for s, _ in pairs])
    run = uuid.uuid4().hex
    work = [{"scan": str(s), "landmarks": str(m) if m else None, "out_dir": str(out / name), "name": name,
             "blend": str(out / name / f"{name}.blend") if blend else None, "levels": levels,
             "preview": str(out / name / "preview.png") if preview else None,
             "calibration": calibration, "keep_flagged": keep_flagged, "timeout": timeout, "memory_gb": memory_gb,
             "run": run} for (s, m), name in zip(pairs, names)]
    kept = {}
    if resume:
        template_sha256 = json.loads((TEMPLATE_DIR / "template.json").read_text())["content_sha256"]
        kept = {job["scan"]: e for job in work if (e := kept_result(job, template_sha256)) is not None}
    every, work = work, [job for job in work if job["scan"] not in kept]
    outputs = {"summary": out / "summary.json"}
    for job in work:
        outputs.update({f"{what} of {job['name']}": path for what, path in
                        {**result_paths(job["out_dir"], job["blend"], job["preview"]),
                         "log": pathlib.Path(job["out_dir"]) / "log.txt"}.items()})
    check_outputs([p for pair in pairs for p in pair if p], outputs, overwrite or resume,
                  "--resume runs the scans it did not finish, --overwrite redoes them all")
    client = _dask_client(scheduler) if scheduler else None    # unreachable: refused before a file changes
    # an earlier run's files of the scans to run: those its reports list (a .blend, a preview this run
    # writes no more), and what a killed run's atomic writes left
    earlier = [path for job in work for path in earlier_outputs(
        job["out_dir"], [pathlib.Path(job["scan"])] + ([pathlib.Path(job["landmarks"])] if job["landmarks"] else []))]
    remove_results([*outputs.values(), *earlier])
    remove_temporaries([*outputs.values(), *earlier])
    entries = {job["scan"]: kept.get(job["scan"]) or {"scan": job["scan"], "landmarks": job["landmarks"],
                                                      "out": job["out_dir"], "status": "not finished", "ok": False}
               for job in every}
    summary = {"folder": str(folder), "out": str(out), "scheduler": scheduler or "local", "run": run,
               "interrupted": False}

    def write_summary():
        scans = list(entries.values())
        summary.update(done=sum(e["ok"] for e in scans),
                       done_with_warnings=sum(e["ok"] and bool(e.get("warnings")) for e in scans),
                       not_trustworthy=sum(e["ok"] and not e["outcome_ok"] for e in scans),
                       failed=sum(e["status"] in ("failed", "timeout") for e in scans),
                       not_finished=sum(e["status"] == "not finished" for e in scans), scans=scans)
        meshio.write_atomic(out / "summary.json", json.dumps(summary, indent=1, default=float))

    write_summary()
    t0, finished = time.monotonic(), 0

    def record(entry):
        nonlocal finished
        entries[entry["scan"]] = entry
        finished += 1
        name = pathlib.Path(entry["scan"]).name
        if entry["ok"]:
            from .core.adapt import outcome as outcome_text
            what = (f"{'ok  ' if entry['outcome_ok'] else 'WARN'} {name}: level {entry['best_level']}, "
                    f"{outcome_text.verdict(entry['outcome'])}")
        else:
            what = f"{'FAIL' if entry['status'] != 'not finished' else 'STOP'} {name}: {entry['error']}"
        elapsed = time.monotonic() - t0
        eta = elapsed / finished * (len(work) - finished)
        log(f"[{finished}/{len(work)}] {what} ({entry.get('seconds', 0.0):.1f} s); "
            f"elapsed {_clock(elapsed)}, ETA {_clock(eta)}")
        for line in entry.get("warnings", []):
            warn(f"headadapt: warning: {name}: {line}")
        write_summary()

    how = f"({'Dask scheduler ' + scheduler if scheduler else 'local processes'})"
    if resume:
        log(f"headadapt: {len(every)} scans in {folder}: {len(kept)} done by an earlier run, kept (--resume); "
            f"{len(work)} to adapt into {out} {how}")
    else:
        log(f"headadapt: {len(work)} scans from {folder} into {out} {how}")
    for line in folder_notes(folder, out, pairs, names):
        warn(f"headadapt: warning: {line}")
    previous = _on_sigterm_interrupt()
    try:
        if scheduler:
            _run_dask(client, work, record)
        else:
            _run_local(work, jobs or min(len(work), os.cpu_count() or 1), record)
    except KeyboardInterrupt:
        summary["interrupted"] = True
        log(f"headadapt: interrupted: {sum(e['status'] == 'not finished' for e in entries.values())} scans "
            "not finished")
    finally:
        _restore_sigterm(previous)
        write_summary()
    log(f"headadapt: {summary['done']} adapted ({summary['not_trustworthy']} not trustworthy, "
        f"{summary['done_with_warnings']} with warnings), "
        f"{summary['failed']} failed, {summary['not_finished']} not finished; wrote {out / 'summary.json'}")
    return summary


def _clock(seconds: float) -> str:
    seconds = int(round(seconds))
    return f"{seconds // 3600}:{seconds // 60 % 60:02d}:{seconds % 60:02d}"


def _on_sigterm_interrupt():
    """SIGTERM ends folder mode as Ctrl-C does (summary written); returns the handler it replaced."""
    if threading.current_thread() is not threading.main_thread():
        return None
    return signal.signal(signal.SIGTERM, signal.default_int_handler)


def _restore_sigterm(previous) -> None:
    if previous is not None:
        signal.signal(signal.SIGTERM, previous)


def _run_local(work: list[dict], jobs: int, record) -> None:
    """The scans in a pool of `jobs` threads, each waiting on one scan's process; on KeyboardInterrupt
    the scans not started are dropped, the running ones killed, and the interrupt passes on."""
    import concurrent.futures

    _stopping.clear()
    pool = concurrent.futures.ThreadPoolExecutor(max_workers=max(1, jobs))
    futures, recorded = [pool.submit(run_isolated, job) for job in work], set()
    try:
        for fut in concurrent.futures.as_completed(futures):
            recorded.add(fut)
            record(fut.result())
    except KeyboardInterrupt:
        _stopping.set()
        with _running_lock:
            for proc in list(_running):
                _kill(proc)
        pool.shutdown(wait=True, cancel_futures=True)
        for fut in futures:     # scans that ended before the interrupt reached them
            if fut not in recorded and fut.done() and not fut.cancelled() and fut.result()["status"] != "not finished":
                record(fut.result())
        raise
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
        _stopping.clear()


def _dask_client(scheduler: str):
    """A Dask distributed Client of the scheduler at `scheduler`; dask is imported only here (HeadAdaptError:
    Dask missing, or the scheduler not reached within 20 s)."""
    from .core.exceptions import HeadAdaptError

    try:
        from distributed import Client
    except ImportError:
        raise HeadAdaptError("--scheduler needs Dask: pip install 'dask[distributed]'") from None
    try:
        return Client(scheduler, timeout="20s")
    except (OSError, TimeoutError, ValueError) as exc:
        raise HeadAdaptError(f"cannot reach the Dask scheduler {scheduler}: {exc}") from None


def _run_dask(client, work: list[dict], record) -> None:
    """The same per-scan jobs (run_isolated) as tasks on a Dask distributed cluster (client: _dask_client's).
    On KeyboardInterrupt the tasks are cancelled (a running scan still ends at its timeout)."""
    import importlib

    from distributed import as_completed

    # the task by its module's name (run as ``python -m``, this module is __main__, which workers lack)
    task = importlib.import_module("headadapt_addon.batch").run_isolated
    with client:
        futures = {client.submit(task, job, key=f"headadapt-{job['name']}-{job['run']}", pure=False): job
                   for job in work}
        try:
            for fut in as_completed(futures):
                job = futures[fut]
                try:
                    entry = fut.result()
                except Exception as exc:           # the task itself failed on the worker
                    entry = {"scan": job["scan"], "landmarks": job["landmarks"], "out": job["out_dir"], "ok": False,
                             "status": "failed", "error": f"{job['scan']}: Dask task failed: {type(exc).__name__}: {exc}"}
                record(entry)
        except KeyboardInterrupt:
            client.cancel(list(futures))
            raise


def main(argv=None):
    """Run one batch command; returns the process exit code (module docstring)."""
    from .core.exceptions import HeadAdaptError

    if argv is None:
        argv = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]
    args = build_parser().parse_args(argv)
    if args.command == "_scan":
        return _scan_main(args.job)
    if args.command == "adapt":
        return _adapt_exit_code(args.scan, args.landmarks, args.out, args.levels, args.calibration, args.keep_flagged,
                                args.blend, args.overwrite, preview=args.preview)
    if args.command == "demo":           # the demo's own files, from the bundled inputs: always replaced
        out = pathlib.Path(args.out)
        return _adapt_exit_code(SAMPLE_DIR / "scan.ply", SAMPLE_DIR / "landmarks.json", out, args.levels,
                                args.calibration, args.keep_flagged, out / "demo.blend", True,
                                preview=out / "preview.png")
    try:
        if args.resume and args.overwrite:
            raise HeadAdaptError("--resume keeps an earlier run's results and --overwrite redoes them: give one")
        summary = run_folder(args.folder, args.out, args.jobs, args.levels, args.calibration, args.keep_flagged,
                             args.blend, args.overwrite, args.timeout, args.memory_gb, args.scheduler,
                             preview=args.preview, resume=args.resume)
    except HeadAdaptError as exc:
        _stderr(f"headadapt: error: {exc}")
        return EXIT_BAD_INPUT
    if summary["interrupted"]:
        return EXIT_INTERRUPTED
    if summary["failed"] or summary["not_finished"]:
        return EXIT_SCAN_FAILED
    return EXIT_UNTRUSTWORTHY if summary["not_trustworthy"] else EXIT_OK


if __name__ == "__main__":
    try:
        code = main()
    except Exception:          # a bug, not bad input: Blender would print it and still exit 0
        traceback.print_exc()
        print("headadapt: internal error (the traceback above); please report it", file=sys.stderr)
        code = EXIT_BUG
    if "bpy" in sys.modules and getattr(sys.modules["bpy"].app, "background", False) and code:
        sys.stderr.flush()
    sys.exit(code)
