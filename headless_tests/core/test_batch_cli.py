"""The batch command line's contract: no command line overwrites its own inputs; existing results are
replaced only with --overwrite; a failed run leaves report.json "failed" and no result beside it;
bad input, a full disk or an unwritable folder exit 2 with one line naming the file; a bug exits 1
with its traceback in the log and one line naming the scan."""
import hashlib
import json
import os
import shutil
import subprocess
import sys

import pytest

from headadapt_addon.batch import ROOT, SAMPLE_DIR


def batch(*args, env=None, timeout=300):
    return subprocess.run([sys.executable, "-m", "headadapt_addon.batch", *map(str, args)], capture_output=True,
                          text=True, timeout=timeout, cwd=ROOT, env=env)


def one_error_line(proc):
    """The single stderr line of a refused or bad-input run (exit 2)."""
    assert proc.returncode == 2, proc.stdout + proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("headadapt: error: ") and "Traceback" not in proc.stderr, lines
    return lines[0]


def digest(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture
def inputs(tmp_path):
    """A copy of the sample scan and its landmarks in tmp_path/in."""
    (tmp_path / "in").mkdir()
    shutil.copy(SAMPLE_DIR / "scan.ply", tmp_path / "in" / "scan.ply")
    shutil.copy(SAMPLE_DIR / "landmarks.json", tmp_path / "in" / "landmarks.json")
    return tmp_path / "in" / "scan.ply", tmp_path / "in" / "landmarks.json"


def _hard_link(src, dst):
    dst.parent.mkdir(parents=True, exist_ok=True)
    os.link(src, dst)


def _sym_link(src, dst):
    dst.parent.mkdir(parents=True, exist_ok=True)
    dst.symlink_to(src)


# Each case: how to lay the inputs out, the command line, the path the refusal names.
CASES = {
    "blend is the scan": (None, lambda s, m, o: ["adapt", "--scan", s, "--landmarks", m, "--out", o, "--blend", s], "s"),
    "blend is the landmarks": (None, lambda s, m, o: ["adapt", "--scan", s, "--landmarks", m, "--out", o,
                                                      "--blend", m], "m"),
    "scan named adapted_head.obj in --out": (
        "scan_in_out", lambda s, m, o: ["adapt", "--scan", o / "adapted_head.obj", "--landmarks", m, "--out", o],
        "adapted_head.obj"),
    "landmarks named report.json in --out": (
        "marks_in_out", lambda s, m, o: ["adapt", "--scan", s, "--landmarks", o / "report.json", "--out", o],
        "report.json"),
    "out holds a hard link to the scan": (
        "hard_link", lambda s, m, o: ["adapt", "--scan", s, "--landmarks", m, "--out", o], "adapted_head.obj"),
    "out holds a symbolic link to the scan": (
        "sym_link", lambda s, m, o: ["adapt", "--scan", s, "--landmarks", m, "--out", o], "adapted_head.obj"),
    "blend is the report": (None, lambda s, m, o: ["adapt", "--scan", s, "--landmarks", m, "--out", o,
                                                   "--blend", o / "report.json"], "report.json"),
    "folder writes summary.json over a landmark file": (
        "summary_scan", lambda s, m, o: ["folder", "--folder", s.parent, "--out", s.parent], "summary.json"),
}


@pytest.mark.parametrize("case", list(CASES))
def test_no_command_line_overwrites_its_inputs(tmp_path, inputs, case):
    scan, marks = inputs
    out = tmp_path / "out"
    layout, argv, named = CASES[case]
    if layout == "scan_in_out":
        from headadapt_addon.core import meshio
        meshio.write_obj(out / "adapted_head.obj", *meshio.read_mesh(scan))
    elif layout == "marks_in_out":
        out.mkdir()
        shutil.copy(marks, out / "report.json")
    elif layout == "hard_link":
        _hard_link(scan, out / "adapted_head.obj")
    elif layout == "sym_link":
        _sym_link(scan, out / "adapted_head.obj")
    elif layout == "summary_scan":
        scan.rename(scan.with_name("summary.ply"))
        marks.rename(marks.with_name("summary.json"))
        scan, marks = scan.with_name("summary.ply"), marks.with_name("summary.json")
    before = {p: digest(p) for p in [*tmp_path.rglob("*")] if p.is_file() and not p.is_symlink()}
    proc = batch(*argv(scan, marks, out), "--overwrite")      # refused even with --overwrite
    line = one_error_line(proc)
    assert "refusing to write" in line and {"s": str(scan), "m": str(marks)}.get(named, named) in line, line
    after = {p: digest(p) for p in [*tmp_path.rglob("*")] if p.is_file() and not p.is_symlink()}
    assert after == before                                     # nothing written, nothing changed


@pytest.mark.slow
def test_results_are_replaced_only_with_overwrite_and_a_failed_rerun_leaves_no_stale_result(tmp_path, inputs):
    scan, marks = inputs
    out = tmp_path / "out"
    proc = batch("adapt", "--scan", scan, "--landmarks", marks, "--out", out, "--levels", "1")
    assert proc.returncode == 0
    report = json.loads((out / "report.json").read_text())
    assert report["status"] == "done"
    # the sample clicks every FDP: calibration leaves the loose ones to the levels, and says so
    loose = report["calibration"]["not_leaned_on"]
    assert "11.4" in loose and "3.7" not in loose
    assert f"calibration fitted to the face's firm clicks, not to {', '.join(loose)}" in proc.stdout
    stages = report["stage_seconds"]        # where the time went, without the .blend's transfer and bake
    assert list(stages) == ["read", "calibrate", "prepare", "level_0", "level_1", "snap", "unfold"], stages
    assert all(s > 0 for s in stages.values()) and sum(stages.values()) <= report["total_seconds"]
    assert report["inputs_sha256"] == {"scan": digest(scan), "landmarks": digest(marks)}
    kept = {p.name: digest(p) for p in out.iterdir()}
    line = one_error_line(batch("adapt", "--scan", scan, "--landmarks", marks, "--out", out, "--levels", "1"))
    assert f"refusing to replace {out / 'adapted_head.obj'}" in line and "--overwrite" in line
    assert {p.name: digest(p) for p in out.iterdir()} == kept
    # the scan goes bad; the rerun with --overwrite fails and takes the old result with it
    scan.write_bytes(scan.read_bytes()[:5000])
    line = one_error_line(batch("adapt", "--scan", scan, "--landmarks", marks, "--out", out, "--overwrite"))
    assert str(scan) in line
    assert sorted(p.name for p in out.iterdir()) == ["report.json"]
    failed = json.loads((out / "report.json").read_text())
    assert failed["status"] == "failed" and failed["error"] == line.removeprefix("headadapt: error: ")


@pytest.mark.slow
def test_a_full_disk_exits_2_naming_the_file(tmp_path, inputs):
    """A file-size limit of 64 kB stands in for a full disk: report.json ("running") fits, the OBJ not."""
    scan, marks = inputs
    out = tmp_path / "out"
    code = ("import resource, signal, sys\n"
            "signal.signal(signal.SIGXFSZ, signal.SIG_IGN)\n"
            "resource.setrlimit(resource.RLIMIT_FSIZE, (65536, resource.RLIM_INFINITY))\n"
            "from headadapt_addon.batch import main\n"
            f"sys.exit(main(['adapt', '--scan', {str(scan)!r}, '--landmarks', {str(marks)!r}, '--out', {str(out)!r},"
            " '--levels', '0']))\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=300)
    line = one_error_line(proc)
    assert line == f"headadapt: error: cannot write {out / 'adapted_head.obj'}: File too large"
    assert sorted(p.name for p in out.iterdir()) == ["report.json"]
    assert json.loads((out / "report.json").read_text())["status"] == "failed"


def test_a_run_interrupted_after_its_obj_leaves_only_its_report_and_reruns_without_overwrite(tmp_path, inputs):
    """Ctrl-C during the .blend (its bake) left adapted_head.obj beside an "interrupted" report.json, and
    the rerun was refused without --overwrite."""
    scan, marks = inputs
    out = tmp_path / "out"
    code = ("import sys\n"
            "import headadapt_addon.batch as b\n"
            "def ctrl_c(*args, **kwargs):\n"
            "    assert (b.pathlib.Path(sys.argv[1]) / 'adapted_head.obj').exists()\n"
            "    raise KeyboardInterrupt\n"
            "b._write_blend = ctrl_c\n"
            f"sys.exit(b.main(['adapt', '--scan', {str(scan)!r}, '--landmarks', {str(marks)!r}, '--out', sys.argv[1],"
            " '--levels', '0', '--blend', sys.argv[1] + '/head.blend']))\n")
    proc = subprocess.run([sys.executable, "-c", code, str(out)], capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert proc.returncode == 130, proc.stderr
    assert sorted(p.name for p in out.iterdir()) == ["report.json"]
    assert json.loads((out / "report.json").read_text())["status"] == "interrupted"
    assert proc.stderr.strip().splitlines()[-1].startswith(f"headadapt: interrupted: {scan} not adapted")
    assert "Traceback" not in proc.stderr
    assert batch("adapt", "--scan", scan, "--landmarks", marks, "--out", out, "--levels", "1").returncode == 0


@pytest.mark.slow
def test_overwrite_removes_the_earlier_run_s_other_files_in_the_folder_and_nothing_else(tmp_path, inputs):
    """--overwrite with other outputs left the earlier run's .blend and preview beside the new result;
    report.json now lists what a run wrote, and --overwrite removes those in the output folder."""
    scan, marks = inputs
    out = tmp_path / "out"
    assert batch("adapt", "--scan", scan, "--landmarks", marks, "--out", out, "--levels", "1").returncode == 0
    report = json.loads((out / "report.json").read_text())
    assert report["outputs"] == {"adapted OBJ": str(out / "adapted_head.obj"), "report": str(out / "report.json")}
    # as if the earlier run had also written a preview and a .blend, one of them outside the folder
    (out / "head.png").write_bytes(b"png")
    (tmp_path / "elsewhere.blend").write_bytes(b"blend")
    report["outputs"].update({"--preview image": str(out / "head.png"), "--blend file": str(tmp_path / "elsewhere.blend"),
                              "scan?": str(scan)})
    (out / "report.json").write_text(json.dumps(report))
    assert batch("adapt", "--scan", scan, "--landmarks", marks, "--out", out, "--levels", "1",
                 "--overwrite").returncode == 0
    assert sorted(p.name for p in out.iterdir()) == ["adapted_head.obj", "report.json"]
    assert (tmp_path / "elsewhere.blend").exists() and scan.exists()


def test_an_unwritable_output_folder_exits_2_naming_it(tmp_path, inputs):
    scan, marks = inputs
    (tmp_path / "file").write_text("")
    line = one_error_line(batch("adapt", "--scan", scan, "--landmarks", marks, "--out", tmp_path / "file" / "out"))
    assert f"cannot write {tmp_path / 'file' / 'out'}/" in line and f"{tmp_path / 'file'} is a file, not a folder" in line


def test_a_bug_exits_1_with_the_traceback_in_the_log_and_the_scan_named(tmp_path, inputs):
    scan, marks = inputs
    code = ("import sys\n"
            "import headadapt_addon.core.adapt as core_adapt\n"
            "def broken(*args, **kwargs):\n"
            "    raise ZeroDivisionError('a bug')\n"
            "core_adapt.adapt = broken\n"
            "from headadapt_addon.batch import main\n"
            f"sys.exit(main(['adapt', '--scan', {str(scan)!r}, '--landmarks', {str(marks)!r}, "
            f"'--out', {str(tmp_path / 'out')!r}]))\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert proc.returncode == 1, proc.stderr
    assert "Traceback" in proc.stderr and "ZeroDivisionError: a bug" in proc.stderr
    assert proc.stderr.strip().splitlines()[-1] == (f"headadapt: internal error while adapting {scan} "
                                                    "(the traceback above); please report it")
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert report["status"] == "failed" and "ZeroDivisionError" in report["traceback"]
    assert not (tmp_path / "out" / "adapted_head.obj").exists()


@pytest.mark.slow
def test_a_plain_batch_run_never_imports_blender(tmp_path, inputs):
    """python -m headadapt_addon.batch adapt without --blend runs with bpy and mathutils unimportable
    (the spatial backend is Embree's or numpy's, never Blender's; importing bpy costs about a second of
    the command); report.json names the backend."""
    scan, marks = inputs
    out = tmp_path / "out"
    code = ("import sys\n"
            "sys.modules['bpy'] = sys.modules['mathutils'] = None   # any import of them raises ImportError\n"
            "from headadapt_addon.batch import main\n"
            f"rc = main(['adapt', '--scan', {str(scan)!r}, '--landmarks', {str(marks)!r}, '--out', {str(out)!r},"
            " '--levels', '1'])\n"
            "assert sys.modules['bpy'] is None and sys.modules['mathutils'] is None\n"
            "sys.exit(rc)\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    report = json.loads((out / "report.json").read_text())
    assert report["status"] == "done"
    from headadapt_addon.core.mesh import embree
    assert report["spatial_backend"] == ("embree" if embree.available() else "numpy")


def _midpoint_split(verts, tris):
    """Every triangle cut into four at its edges' midpoints (the surface unchanged, edges halved)."""
    import numpy as np

    e = np.sort(np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]]), axis=1)
    edges, inv = np.unique(e, axis=0, return_inverse=True)
    mid = len(verts) + inv.ravel().reshape(3, -1).T                     # per triangle: mid of 01, 12, 20
    a, b, c = tris.T
    ab, bc, ca = mid.T
    new = np.concatenate([np.c_[a, ab, ca], np.c_[ab, b, bc], np.c_[ca, bc, c], np.c_[ab, bc, ca]])
    return np.vstack([verts, verts[edges].mean(axis=1)]), new


@pytest.mark.slow
def test_a_dense_scan_is_fitted_on_its_clusters_and_says_so(tmp_path, inputs):
    """The sample scan cut finer (median edge 0.9 mm in the template's frame, 131k vertices) is fitted
    on its 1 mm grid's clusters; the log and report.json say so, and the fit is ok. Its --preview
    (drawn from such clusters too) is written."""
    from headadapt_addon.core import meshio
    from tools import testheads

    scan, marks = inputs
    verts, tris = meshio.read_mesh(scan)[:2]
    dense = tmp_path / "in" / "dense.ply"
    testheads.write_ply(dense, *_midpoint_split(verts, tris))
    proc = batch("adapt", "--scan", dense, "--landmarks", marks, "--out", tmp_path / "out",
                 "--preview", tmp_path / "out" / "preview.png")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert (tmp_path / "out" / "preview.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    clustered = report["calibration"]["scan_clustered"]
    assert clustered["cell_mm"] == 1.0 and clustered["vertices"] == report["scan_vertices"] > 3.5 * len(verts)
    assert clustered["kept"] < 0.6 * clustered["vertices"]
    assert f"{clustered['vertices']:,} -> {clustered['kept']:,} vertices" in proc.stdout
    assert report["outcome"]["ok"] and report["outcome"]["seen_rms_mm"] < 0.5


def test_clicks_in_another_unit_exit_2_naming_the_landmark_file(tmp_path, inputs):
    """Clicks in millimetres on a scan in metres: calibration shrinks the scan to a speck (clustering then
    erased it, and the run ended in an internal error); now one line names the landmark file and the unit."""
    scan, marks = inputs
    points = json.loads(marks.read_text())["points"]
    mm = tmp_path / "in" / "clicks_mm.json"
    mm.write_text(json.dumps({"points": {k: [1000 * c for c in p] for k, p in points.items()}}))
    line = one_error_line(batch("adapt", "--scan", scan, "--landmarks", mm, "--out", tmp_path / "out"))
    assert line.startswith(f"headadapt: error: {mm}: The landmarks are about 10^3 times larger than the scan: "
                           "they are in another unit"), line
    assert "(FDP " in line and "in the template's frame)" in line, line
    assert json.loads((tmp_path / "out" / "report.json").read_text())["status"] == "failed"
    # the clicks mended, the run again into the same folder: the failed report held no result, so it is
    # replaced without --overwrite; a result is not
    again = batch("adapt", "--scan", scan, "--landmarks", marks, "--out", tmp_path / "out", "--levels", "1")
    assert again.returncode in (0, 3), again.stderr
    assert json.loads((tmp_path / "out" / "report.json").read_text())["status"] == "done"
    third = batch("adapt", "--scan", scan, "--landmarks", marks, "--out", tmp_path / "out", "--levels", "1")
    assert third.returncode == 2 and "refusing to replace" in third.stderr


@pytest.mark.parametrize("case, expected", [
    ("another frame", " mm outside the scan's bounding box after calibration: markers must be measured on this scan"),
    ("another unit", "The markers are about 10^3 times larger than the scan: they are in another unit"),
    ("a misspelt name", 'marker "glabela" is neither an FDP nor one of the template\'s markers (glabella, nasion, '),
])
def test_markers_in_another_frame_unit_or_name_exit_2_naming_the_landmark_file(tmp_path, inputs, case, expected):
    """Held-out markers choose the level by their error (E = alpha E_d + beta E_m, sec 5). The sample's
    markers left where they were while its scan and clicks were turned upside down chose level 0 (marker
    RMS 1030 mm), and the run ended "not trustworthy, the fit did not reach the scan", exit 3; a misspelt
    marker was left out of the figure unsaid. Now such a file is bad input: one line names it and the
    marker, and nothing is fitted."""
    scan, marks = inputs
    data = json.loads(marks.read_text())
    markers = data["markers"]
    if case == "another frame":
        markers = {k: [p[0], p[1], p[2] + 1000.0] for k, p in markers.items()}
    elif case == "another unit":
        markers = {k: [1000 * c for c in p] for k, p in markers.items()}
    else:
        markers = {("glabela" if k == "glabella" else k): p for k, p in markers.items()}
    bad = tmp_path / "in" / "markers_bad.json"
    bad.write_text(json.dumps({**data, "markers": markers}))
    line = one_error_line(batch("adapt", "--scan", scan, "--landmarks", bad, "--out", tmp_path / "out"))
    assert line.startswith(f"headadapt: error: {bad}: "), line
    assert expected in line and (case != "another frame" or ": marker glabella is 9" in line), line
    assert not (tmp_path / "out" / "adapted_head.obj").exists()
    assert json.loads((tmp_path / "out" / "report.json").read_text())["status"] == "failed"


def test_levels_out_of_range_are_refused_before_anything_is_read(tmp_path, inputs):
    scan, marks = inputs
    proc = batch("adapt", "--scan", scan, "--landmarks", marks, "--out", tmp_path / "out", "--levels", "9")
    assert proc.returncode == 2 and "argument --levels: invalid choice: 9" in proc.stderr, proc.stderr
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("case", ["blend in a folder that is a file", "preview where no file can be made",
                                  "blend not named .blend"])
def test_an_output_that_cannot_be_written_is_refused_before_the_fit(tmp_path, inputs, case):
    """Found before the fit (before, a --preview in /proc ended in an internal error after it, and a
    --blend named .txt was written as one): one line naming the file, nothing made, the inputs as they were."""
    scan, marks = inputs
    (tmp_path / "file").write_text("")
    extra, named = {
        "blend in a folder that is a file": (["--blend", tmp_path / "file" / "sub" / "h.blend"], "is a file, not a folder"),
        "preview where no file can be made": (["--preview", "/proc/headadapt-test.png"], "/proc/headadapt-test.png"),
        "blend not named .blend": (["--blend", tmp_path / "h.txt"], "name a .blend file"),
    }[case]
    before = {p: digest(p) for p in tmp_path.rglob("*") if p.is_file()}
    proc = batch("adapt", "--scan", scan, "--landmarks", marks, "--out", tmp_path / "out", *extra)
    line = one_error_line(proc)
    assert named in line and str(extra[1]) in line, line
    assert "level" not in proc.stdout                        # refused before the fit
    assert {p: digest(p) for p in tmp_path.rglob("*") if p.is_file()} == before
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("arg", [("--timeout", "0"), ("--memory-gb", "-1"), ("--jobs", "-2"), ("--timeout", "nan")])
def test_folder_limits_that_would_fail_every_scan_are_refused_before_anything_runs(tmp_path, inputs, arg):
    """--timeout 0 killed every scan at once and --memory-gb 0 failed each 'out of memory' (exit 4 after
    a run over the whole folder); now argparse's one error line, exit 2, nothing made."""
    scan, _marks = inputs
    proc = batch("folder", "--folder", scan.parent, "--out", tmp_path / "out", *arg)
    assert proc.returncode == 2 and f"argument {arg[0]}: {arg[1]} is not" in proc.stderr, proc.stderr
    assert not (tmp_path / "out").exists()


def test_the_demo_writes_beside_the_user_not_into_an_installed_extension(tmp_path, monkeypatch):
    """Run from an installed extension (no ./ha beside the package), demo wrote into the extension's
    own folder, which Blender deletes on the next update; in a checkout it keeps out/demo."""
    from headadapt_addon import batch

    assert batch.build_parser().parse_args(["demo"]).out == str(batch.ROOT / "out" / "demo")
    installed = tmp_path / "extensions" / "user_default" / "headadapt"
    (installed / "headadapt_addon").mkdir(parents=True)
    monkeypatch.setattr(batch, "ROOT", installed)
    monkeypatch.chdir(tmp_path)
    assert batch.build_parser().parse_args(["demo"]).out == str(tmp_path / "headadapt_demo")


def test_a_second_run_into_a_folder_in_use_is_refused_and_a_killed_run_s_report_is_replaced(tmp_path, inputs):
    """A stranger's pipeline check: a run and a --resume of it into the same --out wrote the same scans
    at once (reports "failed" beside finished OBJs). While a run holds --out (flock on the folder) a
    second is refused, naming it; a report left "running" by a run killed (SIGTERM, kill -9) no
    longer blocks the same command, once nothing holds the folder."""
    import fcntl

    scan, marks = inputs
    out = tmp_path / "out"
    out.mkdir()
    fd = os.open(out, os.O_RDONLY)
    fcntl.flock(fd, fcntl.LOCK_EX)                    # another run, still going
    try:
        for args in (["adapt", "--scan", scan, "--landmarks", marks, "--out", out],
                     ["folder", "--folder", scan.parent, "--out", out, "--resume"]):
            line = one_error_line(batch(*args, "--levels", "0"))
            assert line == f"headadapt: error: {out}: another HeadAdapt run is writing into this folder now; " \
                           "wait for it to end, or give another --out"
        assert list(out.iterdir()) == []
    finally:
        os.close(fd)
    (out / "report.json").write_text(json.dumps({"status": "running", "run": "killed"}))
    proc = batch("adapt", "--scan", scan, "--landmarks", marks, "--out", out, "--levels", "0")
    assert proc.returncode in (0, 3), proc.stderr
    assert json.loads((out / "report.json").read_text())["status"] == "done"
    fresh = tmp_path / "never"                       # refused input leaves no folder made for the lock
    assert one_error_line(batch("adapt", "--scan", scan, "--landmarks", tmp_path / "none.json", "--out",
                                fresh / "a" / "b"))
    assert not fresh.exists()


def test_folder_discovery_skips_hidden_files_and_finds_landmarks_in_any_case(tmp_path):
    """macOS's "._NAME.ply" forks counted as failed scans; NAME.JSON was not found beside NAME.ply."""
    from headadapt_addon.batch import find_pairs

    for name in ("a.ply", "a.JSON", "._a.ply", ".b.obj", "c.STL", "c.pp", "c.json", "d.obj", "Kim.ply", "Kim.json",
                 "kim.ply", "kim.json", "e.ply"):
        (tmp_path / name).write_bytes(b"")
    (tmp_path / "dir.ply").mkdir()
    os.mkfifo(tmp_path / "e.json")          # a named pipe is no landmark file (its scan would hang on it)
    assert [(s.name, m.name if m else None) for s, m in find_pairs(tmp_path)] == [
        ("Kim.ply", "Kim.json"), ("a.ply", "a.JSON"), ("c.STL", "c.json"), ("d.obj", None), ("e.ply", None),
        ("kim.ply", "kim.json")]


def test_a_killed_write_s_leftovers_are_removed_and_nothing_else(tmp_path):
    from headadapt_addon.batch import remove_temporaries

    for name in (".adapted_head.obj.k2j3", ".report.json.x9", ".head.a1b2.blend", "keep.txt", ".keep",
                 "adapted_head.obj"):
        (tmp_path / name).write_text("x")
    (tmp_path / ".preview.q1").mkdir()
    (tmp_path / ".preview.q1" / "front.png").write_text("x")
    remove_temporaries([tmp_path / "adapted_head.obj", tmp_path / "report.json", tmp_path / "head.blend",
                        tmp_path / "preview.png"])
    assert sorted(p.name for p in tmp_path.iterdir()) == [".keep", "adapted_head.obj", "keep.txt"]


def test_a_dask_run_gives_its_workers_absolute_paths_and_an_unreachable_scheduler_writes_nothing(
        tmp_path, inputs, monkeypatch):
    """Relative --folder and --out reached a worker running in another folder as its own paths (every
    scan "no such file", reports written under the worker's folder); an unreachable scheduler left a
    summary.json that refused the same command next time."""
    from headadapt_addon import batch as b
    from headadapt_addon.core.exceptions import HeadAdaptError

    scan, marks = inputs
    marks.rename(scan.with_suffix(".json"))           # folder mode's pairing: NAME.ply with NAME.json
    monkeypatch.chdir(tmp_path)
    given = []
    monkeypatch.setattr(b, "_dask_client", lambda scheduler: object())
    monkeypatch.setattr(b, "_run_dask", lambda client, work, record: given.extend(work))
    b.run_folder("in", "out", scheduler="tcp://nowhere:1", levels=0, log=lambda *_: None)
    assert given and all(os.path.isabs(job[k]) for job in given for k in ("scan", "landmarks", "out_dir"))
    assert given[0]["out_dir"] == str(tmp_path / "out" / "scan")

    def unreachable(scheduler):
        raise HeadAdaptError(f"cannot reach the Dask scheduler {scheduler}")

    monkeypatch.setattr(b, "_dask_client", unreachable)
    with pytest.raises(HeadAdaptError, match="cannot reach"):
        b.run_folder("in", "out2", scheduler="tcp://nowhere:1", levels=0, log=lambda *_: None)
    assert not (tmp_path / "out2").exists()


def test_a_reader_gone_or_an_encoding_without_the_name_never_stops_the_log():
    """A monitor's `| grep -m1 FAIL` ended a folder run with BrokenPipeError (exit 1, the summary out of
    step); a latin-1 stdout failed a scan named 张伟.ply and then the run."""
    code = ("import io, sys\n"
            "from headadapt_addon.batch import _say\n"
            "class Gone(io.StringIO):\n"
            "    def write(self, s): raise BrokenPipeError\n"
            "    def fileno(self): return sys.stdout.fileno()\n"
            "_say('one', Gone())\n"
            "latin = io.TextIOWrapper(io.BytesIO(), encoding='latin-1')\n"
            "_say('scan 张伟.ply done', latin)\n"
            "latin.seek(0)\n"
            "print('ok', repr(latin.buffer.getvalue().decode('latin-1')), file=sys.stderr)\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout == "" and "ok 'scan \\\\u5f20\\\\u4f1f.ply done\\n'" in proc.stderr


def test_folder_mode_names_landmark_files_without_a_scan_and_results_of_no_scan_of_the_run(tmp_path):
    """A landmark file whose scan was renamed went unused without a word, and the result folder of a
    scan gone (or renamed NAME_ply when a twin NAME.obj arrived) stayed beside the run's, unnamed."""
    from headadapt_addon.batch import find_pairs, folder_notes, output_names

    src, out = tmp_path / "scans", tmp_path / "out"
    src.mkdir()
    for name in ("actor.ply", "actor.obj", "actor.json", "gone.json", "old.pp", "._x.json"):
        (src / name).write_bytes(b"")
    for folder in ("actor", "actor_ply", "misc"):
        (out / folder).mkdir(parents=True)
    (out / "actor" / "report.json").write_text("{}")
    (out / "actor_ply" / "report.json").write_text("{}")
    pairs = find_pairs(src)
    names = output_names([s for s, _ in pairs])
    assert names == ["actor_obj", "actor_ply"]
    assert folder_notes(src, out, pairs, names) == [
        f"2 landmark files with no scan of that name beside them in {src}, not used: gone.json, old.pp",
        f"1 result folder in {out} of no scan of this run, left as it is: actor"]
    assert len(folder_notes(src, tmp_path / "new", pairs, names)) == 1      # no --out yet: no results to name
    (src / "summary.json").write_text("{}")                                 # --out is the folder: its own
    (src / "gone.json").unlink()                                             # summary is no landmark file
    assert folder_notes(src, src, pairs, names)[0].endswith("not used: old.pp")


_BLAS_THREADS = r"""
import ctypes, os, runpy, sys
sys.argv = ["batch"] + sys.argv[1:]
try:
    runpy.run_module("headadapt_addon.batch", run_name="__main__", alter_sys=True)
except SystemExit as exc:
    assert exc.code in (None, 0, 3), exc.code     # 3: level 0 alone ends far from the scan
counts = []
for path in sorted({line.split()[-1] for line in open("/proc/self/maps") if "openblas" in line.lower()}):
    lib = ctypes.CDLL(path)
    for name in ("openblas_get_num_threads64_", "scipy_openblas_get_num_threads64_",
                 "scipy_openblas_get_num_threads", "openblas_get_num_threads"):
        if hasattr(lib, name):
            counts.append(getattr(lib, name)())
            break
print(counts)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc/self/maps")
@pytest.mark.parametrize("given, threads", [(None, 1), ("2", 2)])
def test_the_batch_runs_blas_on_one_thread_unless_the_user_says(tmp_path, inputs, given, threads):
    """OpenBLAS's own threads spun beside the core's worker threads (0.4 s of system time in a 31k-vertex
    command): the batch sets one before numpy loads it, numpy's and scipy's alike; a user's
    OPENBLAS_NUM_THREADS wins."""
    scan, marks = inputs
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
    if given:
        env["OPENBLAS_NUM_THREADS"] = given
    proc = subprocess.run([sys.executable, "-c", _BLAS_THREADS, "adapt", "--scan", str(scan), "--landmarks", str(marks),
                           "--out", str(tmp_path / "out"), "--levels", "0"],
                          capture_output=True, text=True, cwd=ROOT, env=env, timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    counts = json.loads(proc.stdout.strip().splitlines()[-1])
    assert counts and all(c == threads for c in counts), counts
