"""Benchmark: HeadAdapt against trimesh's nricp_amberg on scan-like heads of growing size, in one run.

    ./ha bench scale [--sizes 50k,200k,1M] [--command 30k] [--nricp-timeout 300] [--repeat 3] [--profile]
    ./ha bench scale --accuracy [--sizes ...]

Heads: tools/testheads.make_head(7, style="scan") remeshed finer (Catmull-Clark levels, collapse
decimation) and topped up to the exact vertex count by splitting the largest triangles at their
centres (the surface does not change, so the clicks stay on it); made once and kept in
$HEADADAPT_CACHE (~/.cache/headadapt)/scale/. Each is written as a binary PLY with its 11 clicks.

Every run is its own process (python -m headadapt_addon.batch, or a child that runs nricp_amberg),
timed from outside (wall seconds from process start to exit) with the peak resident memory the
kernel reports for that process (wait4's ru_maxrss). Per size (HeadAdapt run --repeat times, the
run of median wall time shown and every run's time listed; nricp once):
  headadapt   the batch command: read the scan, adapt, write adapted_head.obj and report.json; its
              report's adapt seconds (adapt.adapt only) and stage seconds (where the time goes)
  nricp       read the scan, calibrate by the clicks (HeadAdapt's calibration), nricp_amberg from the
              template skin with the clicks as landmarks (as bench adapt runs it), write the OBJ;
              killed after --nricp-timeout seconds (then the ratio is a lower bound: ">")
and the ratio nricp / headadapt of the whole commands, and of nricp's own seconds over adapt's.
--command SIZE adds the command-line comparison on a head of that size (default 30k: a scanner's
typical mesh): the same two processes, --repeat times each, alternately, median ratio.
--profile: cProfile of one in-process adaptation of the largest size: the top functions.
--accuracy: what clustering a dense scan (AdaptOptions.scan_cell, mesh/simplify.py) costs in accuracy:
each size adapted in this process as the command does and with clustering off (scan_cell 0), measured
as bench adapt measures (mm of the true head on the seen face: correspondence, surface RMS against the
whole scan, markers), the head's truth made again by tools/testheads.
"""
import argparse
import compileall
import cProfile
import json
import os
import pathlib
import pstats
import subprocess
import sys
import tempfile
import threading
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from headadapt_addon.core import meshio

CACHE = pathlib.Path(os.environ.get("HEADADAPT_CACHE", pathlib.Path.home() / ".cache" / "headadapt")) / "scale"
SEED = 7
# (Catmull-Clark levels, decimation ratio) that give a head just under each size; the rest by splitting
REMESH = ((35_000, (2, 0.6)), (60_000, (2, 0.9)), (250_000, (3, 0.95)), (2_000_000, (4, 1.0)))

NRICP_CHILD = r"""
import json, sys, time
import numpy as np
sys.path.insert(0, {root!r})
t0 = time.perf_counter()
import trimesh
from trimesh.registration import nricp_amberg
from headadapt_addon.core import meshio
from headadapt_addon.core.adapt import calibration
from headadapt_addon.core.template import load_template
verts, tris = meshio.read_mesh({scan!r})[:2]
clicks = meshio.read_landmarks({marks!r})
tpl = load_template()
fdps = tpl.fdp_points()
names = [k for k in clicks if k in tpl.meta["fdps"] and tpl.meta["fdps"][k]["part"] == "skin"]
sim, _ = calibration.calibrate({{k: clicks[k] for k in names}}, {{k: fdps[k] for k in names}})
t1 = time.perf_counter()
src = trimesh.Trimesh(tpl.skin.verts, tpl.skin.tris, process=False)
tgt = trimesh.Trimesh(sim.apply(verts), tris, process=False)
faces = np.array([tpl.meta["fdps"][k]["face"] for k in names])
bary = np.array([tpl.meta["fdps"][k]["bary"] for k in names])
v = nricp_amberg(src, tgt, source_landmarks=(faces, bary), target_positions=sim.apply(np.array([clicks[k] for k in names])),
                 distance_threshold=0.02)
seconds = time.perf_counter() - t1
meshio.write_obj({out!r}, sim.inverse().apply(v), tpl.skin.tris)
print(json.dumps({{"nricp_seconds": seconds, "read_seconds": t1 - t0}}))
"""


def parse_size(text):
    text = text.strip().lower()
    mult = {"k": 1_000, "m": 1_000_000}.get(text[-1], 1)
    return int(float(text.rstrip("km")) * mult)


def upsample(verts, tris, n):
    """Split the largest triangles at their centres (1 -> 3, the surface unchanged) until n vertices."""
    extra = n - len(verts)
    if extra <= 0:
        return verts, tris
    a, b, c = (verts[tris[:, j]] for j in range(3))
    area = np.linalg.norm(np.cross(b - a, c - a), axis=1)
    split = np.argsort(-area, kind="stable")[:extra]
    centre = np.arange(len(verts), len(verts) + len(split))
    t = tris[split]
    new = np.concatenate([np.c_[t[:, 0], t[:, 1], centre], np.c_[t[:, 1], t[:, 2], centre], np.c_[t[:, 2], t[:, 0], centre]])
    keep = np.ones(len(tris), bool)
    keep[split] = False
    return np.vstack([verts, (a + b + c)[split] / 3.0]), np.vstack([tris[keep], new])


def scale_head(n):
    """(scan.ply, landmarks.json) of the seed-7 scan-like head at n vertices (made once, cached; in a
    child process, so that this one stays small: a child forked from it starts with its memory)."""
    folder = CACHE / f"head{SEED}_{n}"
    scan, marks = folder / "scan.ply", folder / "landmarks.json"
    if not (scan.is_file() and marks.is_file()):
        subprocess.run([sys.executable, __file__, "--make", str(n)], check=True, cwd=ROOT)
    return scan, marks


def vertex_count(scan):
    """The vertex count in a PLY's header."""
    head = pathlib.Path(scan).read_bytes()[:1000].split(b"end_header")[0].decode()
    return int(head.split("element vertex")[1].split()[0])


def make_head(n):
    from tools import testheads

    folder = CACHE / f"head{SEED}_{n}"
    scan, marks = folder / "scan.ply", folder / "landmarks.json"

    subdiv, ratio = next(r for limit, r in REMESH if n <= limit)
    t0 = time.perf_counter()
    head = testheads.make_head(SEED, style="scan", subdiv=subdiv, decimate=ratio)
    verts, tris = upsample(head.scan_verts, head.scan_tris, n)
    folder.mkdir(parents=True, exist_ok=True)
    testheads.write_ply(scan, verts, tris)
    meshio.write_atomic(marks, meshio.landmarks_json(head.clicks_11, unit=head.meta["unit"],
                                                     source=f"bench scale, test head {SEED}"))
    print(f"  made the {n:,}-vertex head ({len(head.scan_verts):,} remeshed + {len(verts) - len(head.scan_verts):,} "
          f"split) in {time.perf_counter() - t0:.1f} s", flush=True)
    return scan, marks


def run_process(argv, timeout):
    """(wall seconds, peak resident MB, stdout, exit code or None if killed at the timeout, stderr) of a
    child process, reaped by wait4 so its own peak memory (ru_maxrss) is read."""
    with tempfile.TemporaryFile("w+") as out, tempfile.TemporaryFile("w+") as err:
        t0 = time.perf_counter()
        proc = subprocess.Popen(argv, stdout=out, stderr=err, text=True, cwd=ROOT)
        timer = threading.Timer(timeout, proc.kill)
        timer.start()
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t0
        killed = not timer.is_alive()
        timer.cancel()
        proc.returncode = os.waitstatus_to_exitcode(status)
        out.seek(0)
        err.seek(0)
        return wall, usage.ru_maxrss / 1024.0, out.read(), (None if killed else proc.returncode), err.read()


def headadapt_run(scan, marks, out, timeout):
    argv = [sys.executable, "-m", "headadapt_addon.batch", "adapt", "--scan", str(scan), "--landmarks", str(marks),
            "--out", str(out), "--overwrite"]
    wall, peak, _, code, err = run_process(argv, timeout)
    if code not in (0, 3):
        raise RuntimeError(f"headadapt failed ({code}): {err[-2000:]}")
    report = json.loads((pathlib.Path(out) / "report.json").read_text())
    return {"wall": wall, "peak": peak, "adapt": report["seconds"], "stages": report["stage_seconds"],
            "total": report["total_seconds"]}


def nricp_run(scan, marks, out, timeout):
    code = NRICP_CHILD.format(root=str(ROOT), scan=str(scan), marks=str(marks), out=str(pathlib.Path(out) / "nricp.obj"))
    wall, peak, stdout, rc, err = run_process([sys.executable, "-c", code], timeout)
    if rc is None:
        return {"wall": wall, "peak": peak, "fit": None, "killed": True}
    if rc != 0:
        raise RuntimeError(f"nricp failed ({rc}): {err[-2000:]}")
    return {"wall": wall, "peak": peak, "fit": json.loads(stdout.strip().splitlines()[-1])["nricp_seconds"],
            "killed": False}


def fmt_ratio(a, b, killed):
    return f"{'>' if killed else ''}{a / b:.1f}x"


def profile(scan, marks, top=25):
    """cProfile of one in-process adaptation (after reading the scan): the top functions by own time."""
    from headadapt_addon.core.adapt import adapt
    from headadapt_addon.core.template import load_template

    verts, tris = meshio.read_mesh(scan)[:2]
    clicks = meshio.read_landmarks(marks)
    tpl = load_template()
    prof = cProfile.Profile()
    prof.enable()
    res = adapt(tpl, verts, tris, clicks)
    prof.disable()
    print(f"\nprofile of adapt on {len(verts):,} vertices ({res.seconds:.2f} s; stages "
          + ", ".join(f"{k} {v:.2f}" for k, v in res.stages.items()) + "):")
    pstats.Stats(prof).sort_stats("tottime").print_stats(top)


def accuracy(heads):
    """Per size: HeadAdapt's figures with the scan clustered (the default) and whole (scan_cell 0)."""
    sys.path.insert(0, str(ROOT / "headless_tests" / "bench"))
    import bench_adapt

    from headadapt_addon.core.adapt import AdaptOptions, adapt
    from headadapt_addon.core.mesh import spatial
    from headadapt_addon.core.template import load_template
    from tools import testheads

    tpl = load_template()
    face = testheads.face_mask(tpl)
    print("\nclustering's cost in accuracy (mm of the true head, seen face; bench adapt's measures):")
    print(f"{'verts':>9s} {'scan':>22s} {'corr':>6s} {'p95':>6s} {'surf':>6s} {'mk':>6s} {'adapt s':>7s} level")
    for n, (scan, marks) in heads.items():
        subdiv, ratio = next(r for limit, r in REMESH if n <= limit)
        head = testheads.make_head(SEED, style="scan", subdiv=subdiv, decimate=ratio)
        verts, tris = meshio.read_mesh(scan)[:2]
        clicks = meshio.read_landmarks(marks)
        query = spatial.MeshQuery(verts, tris)
        seen = face & head.true_on_scan
        for cell in (AdaptOptions().scan_cell, 0.0):
            res = adapt(tpl, verts, tris, clicks, AdaptOptions(scan_cell=cell), markers=head.markers)
            m = bench_adapt.measure(tpl, head, res.verts_scan, seen, query)
            kept = res.calibration_info.get("scan_clustered")
            what = f"clustered to {kept['kept']:,}" if kept else "whole"
            print(f"{len(verts):9,d} {what:>22s} {m['corr_rms']:6.2f} {m['corr_p95']:6.2f} {m['surf_rms']:6.3f} "
                  f"{m['marker_rms']:6.2f} {res.seconds:7.2f} {res.best_level}", flush=True)
            if not kept:                # not dense: clustering off gives the same fit
                break


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", default="50k,200k,1M", help="scan vertex counts, e.g. 50k,200k,1M")
    parser.add_argument("--command", default="30k", help="size of the command-line comparison ('' for none)")
    parser.add_argument("--repeat", type=int, default=3, help="HeadAdapt's runs per size, and each command's in the command comparison")
    parser.add_argument("--nricp-timeout", type=float, default=300.0, help="seconds before nricp is killed")
    parser.add_argument("--no-nricp", action="store_true", help="HeadAdapt only")
    parser.add_argument("--profile", action="store_true", help="cProfile one adaptation of the largest size")
    parser.add_argument("--accuracy", action="store_true", help="clustered against whole scans, in this process")
    parser.add_argument("--make", type=int, help=argparse.SUPPRESS)      # the child that makes one head
    args = parser.parse_args(argv)
    if args.make:
        make_head(args.make)
        return
    sizes = [parse_size(s) for s in args.sizes.split(",") if s]
    heads = {n: scale_head(n) for n in sizes + ([parse_size(args.command)] if args.command else [])}
    if args.profile:
        profile(*heads[max(sizes)])
        return
    if args.accuracy:
        accuracy({n: heads[n] for n in sizes})
        return
    # the package's bytecode made first, as Python keeps it on a machine that does not set
    # PYTHONDONTWRITEBYTECODE (this one's sandbox does): each timed process imports it, nricp's child too
    compileall.compile_dir(str(ROOT / "headadapt_addon"), quiet=1)
    work = pathlib.Path(tempfile.mkdtemp(prefix="headadapt-scale-"))
    print(f"\n{'verts':>9s} | {'headadapt: cmd s':>16s} {'adapt s':>7s} {'peak MB':>7s} | "
          f"{'nricp: cmd s':>12s} {'fit s':>7s} {'peak MB':>7s} | {'ratio cmd':>9s} {'fit/adapt':>9s}")
    for n in sizes:
        scan, marks = heads[n]
        runs = sorted((headadapt_run(scan, marks, work / f"h{n}", timeout=1800) for _ in range(max(args.repeat, 1))),
                      key=lambda run: run["wall"])
        h = runs[len(runs) // 2]
        nv = vertex_count(scan)
        if args.no_nricp:
            print(f"{nv:9,d} | {h['wall']:16.2f} {h['adapt']:7.2f} {h['peak']:7.0f} |", flush=True)
        else:
            r = nricp_run(scan, marks, work / f"h{n}", timeout=args.nricp_timeout)
            fit = f"{r['fit']:7.1f}" if r["fit"] is not None else f"{'killed':>7s}"
            print(f"{nv:9,d} | {h['wall']:16.2f} {h['adapt']:7.2f} {h['peak']:7.0f} | {r['wall']:12.1f} {fit} "
                  f"{r['peak']:7.0f} | {fmt_ratio(r['wall'], h['wall'], r['killed']):>9s} "
                  f"{fmt_ratio(r['fit'] or r['wall'], h['adapt'], r['killed']):>9s}", flush=True)
        print(f"{'':9s}   where HeadAdapt's time goes (s): " + ", ".join(f"{k} {v:.2f}" for k, v in h["stages"].items())
              + f"; process start to files written {h['wall']:.2f} (its {len(runs)} runs: "
              + ", ".join(f"{run['wall']:.2f}" for run in runs) + ")", flush=True)
        if r.get("killed") if not args.no_nricp else False:
            print(f"{'':9s}   nricp_amberg killed after {args.nricp_timeout:.0f} s (--nricp-timeout): the ratios are lower bounds")
    if args.command and not args.no_nricp:
        n = parse_size(args.command)
        scan, marks = heads[n]
        ratios, hs, rs = [], [], []
        for _ in range(args.repeat):           # alternately, so a drift of the machine's speed hits both
            h = headadapt_run(scan, marks, work / f"c{n}", timeout=600)
            r = nricp_run(scan, marks, work / f"c{n}", timeout=args.nricp_timeout)
            hs.append(h["wall"])
            rs.append(r["wall"])
            ratios.append(r["wall"] / h["wall"])
        print(f"\ncommand on a {vertex_count(scan):,}-vertex head, process start to files written, {args.repeat} runs each "
              f"alternately: headadapt median {np.median(hs):.2f} s, nricp_amberg median {np.median(rs):.1f} s, "
              f"ratio nricp/headadapt median {np.median(ratios):.1f}x (min {min(ratios):.1f}, max {max(ratios):.1f})")


if __name__ == "__main__":
    main()
