"""Folder mode for unattended runs: each scan in its own process (timeout, memory limit), distinct
outputs for scans that share a stem, progress with count and ETA, summary.json always written
(after Ctrl-C and SIGTERM too, naming what did not finish), exit 4 when a scan failed, --blend and
--preview as flags, the same summary on a Dask cluster; kill -9 leaves complete results only and no scan running."""
import json
import os
import pathlib
import re
import shutil
import signal
import subprocess
import sys
import time

import pytest

from headadapt_addon.batch import ROOT, SAMPLE_DIR
from headadapt_addon.core import meshio
from headadapt_addon.core.template import load_template

pytestmark = pytest.mark.slow     # processes per scan, timeouts: 10 s to a minute each

BAD_PLY = (b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
           b"element face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n-5 0 1 2\n")


def batch_cmd(*args):
    return [sys.executable, "-m", "headadapt_addon.batch", *map(str, args)]


def add_scan(folder, name, scan=None):
    """folder/name (the sample scan, or these bytes) with the sample's landmarks as folder/STEM.json."""
    folder.mkdir(exist_ok=True)
    if scan is None:
        shutil.copy(SAMPLE_DIR / "scan.ply", folder / name)
    else:
        (folder / name).write_bytes(scan)
    shutil.copy(SAMPLE_DIR / "landmarks.json", (folder / name).with_suffix(".json"))


def add_hanging_scan(folder, name):
    """A scan whose reading never ends: a named pipe no one writes to (a stalled network mount, say)."""
    folder.mkdir(exist_ok=True)
    os.mkfifo(folder / name)
    shutil.copy(SAMPLE_DIR / "landmarks.json", (folder / name).with_suffix(".json"))
    return folder / name


def scan_processes(scan):
    """Process ids whose command line names this scan (the scan processes folder mode started for it)."""
    pids = []
    for cmdline in pathlib.Path("/proc").glob("[0-9]*/cmdline"):
        try:
            if str(scan).encode() in cmdline.read_bytes() and b"_scan" in cmdline.read_bytes():
                pids.append(int(cmdline.parent.name))
        except OSError:
            pass                           # ended meanwhile
    return pids


@pytest.fixture
def mixed_folder(tmp_path):
    """Good scans (two share the stem "head"), a corrupt one, one without landmarks, a hanging one."""
    src = tmp_path / "scans"
    add_scan(src, "head.ply")
    add_scan(src, "good.ply")
    meshio.write_obj(src / "head.obj", *meshio.read_mesh(SAMPLE_DIR / "scan.ply"))
    add_scan(src, "corrupt.ply", BAD_PLY)
    (src / "nomarks.stl").write_bytes(b"solid x\nendsolid x\n")
    add_hanging_scan(src, "stuck.obj")
    return src


def summary_by_name(out):
    summary = json.loads((out / "summary.json").read_text())
    return summary, {pathlib.Path(s["scan"]).name: s for s in summary["scans"]}


def check_mixed_summary(out, proc):
    assert proc.returncode == 4, proc.stdout + proc.stderr
    summary, scans = summary_by_name(out)
    assert (summary["done"], summary["failed"], summary["not_finished"], summary["interrupted"]) == (3, 3, 0, False)
    assert {n: s["status"] for n, s in scans.items()} == {
        "corrupt.ply": "failed", "good.ply": "done", "head.obj": "done", "head.ply": "done",
        "nomarks.stl": "failed", "stuck.obj": "timeout"}
    assert "cannot read as PLY" in scans["corrupt.ply"]["error"] and "corrupt.ply" in scans["corrupt.ply"]["error"]
    assert "no landmark file nomarks.json or nomarks.pp" in scans["nomarks.stl"]["error"]
    assert "stuck.obj: no result after 12 s; its process was killed" in scans["stuck.obj"]["error"]
    # head.obj and head.ply: two results, each in its own folder, each from its own scan
    tpl = load_template()
    for name, folder in (("head.obj", "head_obj"), ("head.ply", "head_ply"), ("good.ply", "good")):
        assert scans[name]["out"] == str(out / folder)
        v, t = meshio.read_mesh(out / folder / "adapted_head.obj")
        assert v.shape == tpl.skin.verts.shape
        report = json.loads((out / folder / "report.json").read_text())
        assert report["status"] == "done" and report["scan"].endswith(name)
    for name in ("corrupt", "stuck", "nomarks"):
        assert json.loads((out / name / "report.json").read_text())["status"] == "failed"
        assert not (out / name / "adapted_head.obj").exists()
    return scans


def test_folder_mode_finishes_the_good_scans_names_the_others_and_exits_4(tmp_path, mixed_folder):
    out = tmp_path / "out"
    t0 = time.monotonic()
    proc = subprocess.run(batch_cmd("folder", "--folder", mixed_folder, "--out", out, "--levels", "1", "--jobs", "2",
                                    "--timeout", "12"), capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert time.monotonic() - t0 < 120
    check_mixed_summary(out, proc)
    assert not scan_processes(mixed_folder / "stuck.obj")
    # one progress line per scan, with the count and an ETA
    progress = [s for s in proc.stdout.splitlines() if s.startswith("[")]
    assert [int(re.match(r"\[(\d)/6\]", s).group(1)) for s in progress] == [1, 2, 3, 4, 5, 6], proc.stdout
    assert all(re.search(r"ETA \d+:\d\d:\d\d$", s) for s in progress), progress
    # a rerun refuses to replace these results
    again = subprocess.run(batch_cmd("folder", "--folder", mixed_folder, "--out", out), capture_output=True, text=True,
                           timeout=120, cwd=ROOT)
    assert again.returncode == 2 and "refusing to replace" in again.stderr and "--overwrite" in again.stderr


def test_a_dask_local_cluster_gives_the_same_summary(tmp_path, mixed_folder):
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=1, threads_per_worker=2, processes=False, protocol="tcp://",
                                  dashboard_address=None) as cluster:
        proc = subprocess.run(batch_cmd("folder", "--folder", mixed_folder, "--out", tmp_path / "out", "--levels", "1",
                                        "--timeout", "12", "--scheduler", cluster.scheduler_address),
                              capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert f"Dask scheduler {cluster.scheduler_address}" in proc.stdout
    scans = check_mixed_summary(tmp_path / "out", proc)
    assert json.loads((tmp_path / "out" / "summary.json").read_text())["scheduler"] == cluster.scheduler_address
    for s in scans.values():
        s.pop("seconds", None)
    assert all(s["ok"] == (s["status"] == "done") for s in scans.values())


def test_a_scan_over_its_memory_limit_fails_alone(tmp_path):
    """The sample scan needs about 0.25 GB of address space (one BLAS thread: folder mode's scan processes
    run with one; with two, OpenBLAS's second thread spun without end at the limit, never failing)."""
    src = tmp_path / "scans"
    add_scan(src, "a.ply")
    proc = subprocess.run(batch_cmd("folder", "--folder", src, "--out", tmp_path / "out", "--levels", "1",
                                    "--memory-gb", "0.15"), capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert proc.returncode == 4, proc.stdout + proc.stderr
    _, scans = summary_by_name(tmp_path / "out")
    assert scans["a.ply"]["status"] == "failed" and scans["a.ply"]["error"].endswith("a.ply: out of memory")
    assert "--memory-gb" in (tmp_path / "out" / "a" / "log.txt").read_text()


def test_blend_and_preview_are_flags_writing_one_of_each_per_scan(tmp_path):
    import struct

    src = tmp_path / "scans"
    add_scan(src, "a.ply")
    proc = subprocess.run(batch_cmd("folder", "--folder", src, "--out", tmp_path / "out", "--levels", "1", "--blend",
                                    "--preview"), capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert (tmp_path / "out" / "a" / "a.blend").stat().st_size > 100_000
    png = (tmp_path / "out" / "a" / "preview.png").read_bytes()[:24]
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and struct.unpack(">II", png[16:24]) == (1280, 1280)
    stages = json.loads((tmp_path / "out" / "a" / "report.json").read_text())["stage_seconds"]
    assert {"read", "calibrate", "prepare", "level_0", "level_1", "unfold", "transfer", "preview", "bake",
            "blend"} <= set(stages)
    report = json.loads((tmp_path / "out" / "a" / "report.json").read_text())
    assert all(s > 0 for s in stages.values()) and sum(stages.values()) <= report["total_seconds"]   # each once
    # --overwrite without them removes the earlier .blend and preview (they stayed, beside a report that
    # no longer listed them); a log reader gone at once (a monitor's `| head`) does not stop the run
    again = subprocess.Popen(batch_cmd("folder", "--folder", src, "--out", tmp_path / "out", "--levels", "0",
                                       "--overwrite"), stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=ROOT)
    again.stdout.close()
    err = again.stderr.read().decode()
    assert again.wait(timeout=300) in (0, 3) and "Traceback" not in err, err
    assert sorted(p.name for p in (tmp_path / "out" / "a").iterdir()) == ["adapted_head.obj", "log.txt", "report.json"]
    assert json.loads((tmp_path / "out" / "summary.json").read_text())["done"] == 1


def test_the_blend_writer_is_imported_only_to_write_a_blend(tmp_path):
    """Nor bpy itself: the batch's spatial backend is Embree's or numpy's, never Blender's, wherever the
    bpy module is installed."""
    code = ("import sys\nfrom headadapt_addon.batch import main\n"
            f"code = main(['adapt', '--scan', {str(SAMPLE_DIR / 'scan.ply')!r}, '--landmarks', "
            f"{str(SAMPLE_DIR / 'landmarks.json')!r}, '--out', {str(tmp_path)!r}, '--levels', '0'])\n"
            "print(code in (0, 3), 'headadapt_addon.blender.blendout' in sys.modules, 'bpy' in sys.modules)\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert proc.stdout.split()[-3:] == ["True", "False", "False"], proc.stdout + proc.stderr


def test_a_bug_in_one_scan_is_caught_logged_with_its_traceback_and_the_others_go_on(tmp_path):
    """A scan whose adaptation raises an unexpected exception (a sitecustomize in the scan processes
    breaks adapt for scans named bug*): exit 4, the traceback in its log and report, the other done."""
    src = tmp_path / "scans"
    add_scan(src, "bug.ply")
    add_scan(src, "fine.ply")
    hook = tmp_path / "hook"
    hook.mkdir()
    (hook / "sitecustomize.py").write_text(
        "import sys\n"
        "if '_scan' in sys.argv and 'bug.ply' in sys.argv[-1]:\n"
        "    import headadapt_addon.core.adapt as core_adapt\n"
        "    def broken(*args, **kwargs):\n"
        "        raise ZeroDivisionError('a bug')\n"
        "    core_adapt.adapt = broken\n")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(hook), str(ROOT)]))
    proc = subprocess.run(batch_cmd("folder", "--folder", src, "--out", tmp_path / "out", "--levels", "1"),
                          capture_output=True, text=True, timeout=300, cwd=ROOT, env=env)
    assert proc.returncode == 4, proc.stdout + proc.stderr
    _, scans = summary_by_name(tmp_path / "out")
    assert scans["fine.ply"]["status"] == "done"
    assert scans["bug.ply"]["status"] == "failed"
    assert scans["bug.ply"]["error"] == f"{src / 'bug.ply'}: internal error: ZeroDivisionError: a bug"
    log = (tmp_path / "out" / "bug" / "log.txt").read_text()
    assert "Traceback" in log and f"internal error while adapting {src / 'bug.ply'}" in log
    assert "ZeroDivisionError" in json.loads((tmp_path / "out" / "bug" / "report.json").read_text())["traceback"]


def _start(src, out, *extra):
    # Ctrl-C's default disposition for the child: a test run started in the background by a shell
    # without job control inherits SIGINT ignored, and Python then installs no handler for it (the
    # SIGINT case timed out so on a CI run started as `(bash .ci/run &)`)
    return subprocess.Popen(batch_cmd("folder", "--folder", src, "--out", out, "--levels", "1", "--jobs", "1", *extra),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))


def _wait_for(condition, seconds):
    end = time.monotonic() + seconds
    while not condition():
        assert time.monotonic() < end, "timed out waiting"
        time.sleep(0.2)


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_an_interrupt_writes_the_summary_naming_what_did_not_finish(tmp_path, sig):
    src, out = tmp_path / "scans", tmp_path / "out"
    stuck = add_hanging_scan(src, "a_stuck.obj")
    add_scan(src, "b_good.ply")
    proc = _start(src, out)
    _wait_for(lambda: scan_processes(stuck), 60)      # a_stuck's process has started
    time.sleep(1.0)                                   # and waits on the pipe
    proc.send_signal(sig)
    stdout, stderr = proc.communicate(timeout=30)
    assert proc.returncode == 130, stdout + stderr
    summary, scans = summary_by_name(out)
    assert summary["interrupted"] is True and summary["not_finished"] == 2 and summary["done"] == 0
    assert {s["status"] for s in scans.values()} == {"not finished"}
    assert "interrupted: 2 scans not finished" in stdout
    assert not scan_processes(stuck)                  # its process was killed


def test_kill_9_leaves_only_complete_results_and_no_scan_running(tmp_path):
    src, out = tmp_path / "scans", tmp_path / "out"
    add_scan(src, "a_good.ply")
    stuck = add_hanging_scan(src, "b_stuck.obj")
    proc = _start(src, out)
    _wait_for(lambda: scan_processes(stuck), 120)     # a_good is done, b_stuck's process started
    time.sleep(1.0)
    proc.kill()
    proc.communicate(timeout=30)
    _wait_for(lambda: not scan_processes(stuck), 10)  # the scan process ended with its parent
    # the summary, rewritten atomically after each scan, says what was done and what was not
    summary, scans = summary_by_name(out)
    assert scans["a_good.ply"]["status"] == "done" and scans["b_stuck.obj"]["status"] == "not finished"
    v, _ = meshio.read_mesh(out / "a_good" / "adapted_head.obj")
    assert v.shape == load_template().skin.verts.shape
    assert not (out / "b_stuck" / "adapted_head.obj").exists()
    results = [p for p in out.rglob("*") if p.is_file() and not p.name.startswith(".")]
    assert sorted(p.relative_to(out).as_posix() for p in results) == [
        "a_good/adapted_head.obj", "a_good/log.txt", "a_good/report.json", "b_stuck/log.txt", "summary.json"]
    # the stuck scan fixed, a rerun with --resume keeps a_good as it is and adapts b_stuck
    stuck.unlink()
    add_scan(src, "b_stuck.obj", (out / "a_good" / "adapted_head.obj").read_bytes())
    before = {p.name: (p.read_bytes(), p.stat().st_mtime_ns) for p in (out / "a_good").iterdir()}
    rerun = subprocess.run(batch_cmd("folder", "--folder", src, "--out", out, "--levels", "1", "--resume"),
                           capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert rerun.returncode in (0, 3), rerun.stdout + rerun.stderr
    assert "2 scans in" in rerun.stdout and "1 done by an earlier run, kept (--resume); 1 to adapt" in rerun.stdout
    summary, scans = summary_by_name(out)
    assert {s["status"] for s in scans.values()} == {"done"} and summary["done"] == 2
    assert scans["a_good.ply"]["kept"] and "kept" not in scans["b_stuck.obj"]
    assert {p.name: (p.read_bytes(), p.stat().st_mtime_ns) for p in (out / "a_good").iterdir()} == before


def test_resume_keeps_only_results_of_the_same_inputs_and_options(tmp_path):
    """A rerun into the same folder is refused, pointing to --resume; --resume runs again a scan whose
    landmark file changed, whose result lost a file, or every scan when the options differ."""
    src, out = tmp_path / "scans", tmp_path / "out"
    for name in ("a.ply", "b.ply", "c.ply"):
        add_scan(src, name)

    def run(*extra):
        return subprocess.run(batch_cmd("folder", "--folder", src, "--out", out, "--levels", "1", "--jobs", "1", *extra),
                              capture_output=True, text=True, timeout=300, cwd=ROOT)

    def runs():
        return {n: json.loads((out / n[0] / "report.json").read_text())["run"] for n in ("a.ply", "b.ply", "c.ply")}

    assert run().returncode == 0
    first = runs()
    again = run()
    assert again.returncode == 2 and "--resume runs the scans it did not finish" in again.stderr
    with open(src / "b.json", "a") as fh:
        fh.write("\n")                                 # the same clicks, but not the same file
    (out / "c" / "adapted_head.obj").unlink()
    resumed = run("--resume")
    assert resumed.returncode == 0, resumed.stdout + resumed.stderr
    second = runs()
    assert second["a.ply"] == first["a.ply"] and second["b.ply"] != first["b.ply"] != second["c.ply"]
    _, scans = summary_by_name(out)
    assert scans["a.ply"]["kept"] == first["a.ply"] and scans["a.ply"]["status"] == "done"
    assert [s for s in scans if "kept" in scans[s]] == ["a.ply"]
    # other options: nothing kept
    other = run("--resume", "--calibration", "paper")
    assert "0 done by an earlier run" in other.stdout and len(set(runs().values()) & set(second.values())) == 0
    both = run("--resume", "--overwrite")
    assert both.returncode == 2 and "give one" in both.stderr
