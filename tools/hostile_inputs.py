"""Build a directory of hostile inputs and check the batch job against each (issue 18's "done when").

    python tools/hostile_inputs.py [--dir DIR] [--no-folder]

Scans (truncated, huge or negative counts, NaN, non-UTF-8, 0-byte, a Blender-exported binary PLY of
quads and triangles, truncated), landmark files (NaN, deep JSON, XML entity bombs, non-UTF-8, 0-byte)
landmark files that read but do not fit the scan (another unit, another scan's, too few, one spot
clicked twice, a typed 1e300) and .fap files (an 18-byte file declaring 10^8 frames, huge numbers). Each hostile file goes through
``batch adapt`` (a .fap through read_fap, as Import .fap calls it) in its own process: it must exit 2
with one stderr line naming the file, within 5 s and 1 GB peak resident memory; each valid scan
must adapt (exit 0 or 3). Then folder mode over good, corrupt and hanging scans must finish the good
ones, name the others in summary.json and exit 4, locally and on a Dask LocalCluster (when
dask.distributed is installed) with the same statuses. Prints one line per check; exit 1 if any fails.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import shutil
import subprocess
import sys
import tempfile
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from headadapt_addon.batch import SAMPLE_DIR  # noqa: E402
from headadapt_addon.core import meshio  # noqa: E402

MAX_SECONDS, MAX_RSS_MB = 5.0, 1024.0
PLY_HEAD = ("ply\nformat {fmt} 1.0\nelement vertex {nv}\nproperty float x\nproperty float y\nproperty float z\n"
            "element face {nf}\nproperty list {ct} {it} vertex_indices\nend_header\n")
MASK = " ".join("1" if i == 3 else "0" for i in range(1, 69))


def blender_mixed_ply(path: pathlib.Path) -> None:
    """The sample scan through Blender 5: imported, triangles joined into quads where they can be,
    exported as binary PLY (quads and triangles in one face list)."""
    code = (
        "import bpy, sys\n"
        "bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)\n"
        f"bpy.ops.wm.ply_import(filepath={str(SAMPLE_DIR / 'scan.ply')!r})\n"
        "obj = bpy.context.selected_objects[0]\n"
        "bpy.context.view_layer.objects.active = obj\n"
        "bpy.ops.object.mode_set(mode='EDIT')\n"
        "bpy.ops.mesh.select_all(action='SELECT')\n"
        "bpy.ops.mesh.tris_convert_to_quads()\n"
        "bpy.ops.object.mode_set(mode='OBJECT')\n"
        "sizes = sorted({len(p.vertices) for p in obj.data.polygons})\n"
        "assert sizes == [3, 4], sizes\n"
        f"bpy.ops.wm.ply_export(filepath={str(path)!r}, ascii_format=False, export_normals=False, "
        "export_uv=False, export_colors='NONE')\n")
    subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, cwd=ROOT, timeout=300)


def clicks_that_do_not_fit(scan_verts: np.ndarray) -> dict[str, tuple[bytes, str]]:
    """Landmark files of the sample scan's own clicks, changed the ways a person's mix-ups change them."""
    points = json.loads((SAMPLE_DIR / "landmarks.json").read_text())["points"]
    p = {k: np.asarray(x, dtype=np.float64) for k, x in points.items()}
    size = float(np.linalg.norm(np.ptp(scan_verts, axis=0)))
    names = list(p)

    def dump(q):
        return json.dumps({"points": {k: [float(c) for c in x] for k, x in q.items()}}).encode()

    return {
        "clicks_1000x.json": (dump({k: 1000 * x for k, x in p.items()}), "the clicks in a unit 1000 times smaller"),
        "clicks_0.001x.json": (dump({k: x / 1000 for k, x in p.items()}), "the clicks in a unit 1000 times larger"),
        "clicks_elsewhere.json": (dump({k: x + 2 * size for k, x in p.items()}), "another scan's clicks, 2 scans away"),
        "clicks_3.json": (dump({k: p[k] for k in names[:3]}), "3 clicks"),
        "clicked_twice.json": (dump({**p, names[1]: p[names[0]]}), "two FDPs at one spot"),
        "clicks_typo.json": (dump({**p, names[2]: np.array([1e300, 0.0, 0.0])}), "one coordinate typed 1e300"),
        "clicks_1e150x.json": (dump({k: 1e150 * x for k, x in p.items()}), "the clicks 1e150 times the scan"),
    }


def build(d: pathlib.Path) -> tuple[dict[str, bytes], dict[str, bytes]]:
    """Write the hostile and the valid files into d; return ({name: what it is}, {name: what it is})."""
    d.mkdir(parents=True, exist_ok=True)
    sample = (SAMPLE_DIR / "scan.ply").read_bytes()
    v, t = meshio.read_mesh(SAMPLE_DIR / "scan.ply")
    valid = {
        "sample_binary.ply": "the bundled sample, binary PLY",
        "sample.obj": "the sample as OBJ",
        "sample_ascii.ply": "the sample as ASCII PLY",
        "sample_binary.stl": "the sample as binary STL",
        "blender_mixed.ply": "Blender 5 binary PLY export, quads and triangles",
    }
    (d / "sample_binary.ply").write_bytes(sample)
    meshio.write_obj(d / "sample.obj", v, t)
    (d / "sample_ascii.ply").write_text(
        PLY_HEAD.format(fmt="ascii", nv=len(v), nf=len(t), ct="uchar", it="int")
        + "".join(f"{a:.9g} {b:.9g} {c:.9g}\n" for a, b, c in v) + "".join(f"3 {a} {b} {c}\n" for a, b, c in t))
    rec = np.zeros(len(t), dtype=[("n", "<f4", 3), ("v", "<f4", (3, 3)), ("a", "<u2")])
    rec["v"] = v[t]
    (d / "sample_binary.stl").write_bytes(b"\0" * 80 + np.uint32(len(t)).tobytes() + rec.tobytes())
    blender_mixed_ply(d / "blender_mixed.ply")
    blender = (d / "blender_mixed.ply").read_bytes()

    head = PLY_HEAD.format(fmt="ascii", nv=3, nf=1, ct="uchar", it="int")
    hostile = {
        # scans
        "truncated_binary.ply": (sample[:len(sample) // 2], "binary PLY cut in half"),
        "truncated_blender.ply": (blender[:len(blender) - 1000], "Blender's mixed binary PLY, last 1000 bytes cut"),
        "truncated_ascii.ply": ((d / "sample_ascii.ply").read_bytes()[:300_000], "ASCII PLY cut short"),
        "huge_count.ply": (PLY_HEAD.format(fmt="binary_little_endian", nv=4_000_000_000, nf=1, ct="uchar",
                                           it="int").encode() + b"\0" * 64, "4e9 vertices declared, 64 bytes"),
        "count_vs_size.ply": (PLY_HEAD.format(fmt="binary_little_endian", nv=1_000_000, nf=1_000_000, ct="uchar",
                                              it="int").encode() + b"\0" * 40_000, "1e6 vertices and faces, 40 KB"),
        "negative_list.ply": ((head + "0 0 0\n1 0 0\n0 1 0\n-5 0 1 2\n").encode(), "face list of -5 entries"),
        "negative_count.ply": (PLY_HEAD.format(fmt="ascii", nv=-3, nf=1, ct="uchar", it="int").encode(),
                               "-3 vertices declared"),
        "huge_list.ply": (PLY_HEAD.format(fmt="binary_little_endian", nv=3, nf=1, ct="uint", it="int").encode()
                          + np.zeros(9, "<f4").tobytes() + np.uint32(4_000_000_000).tobytes() + b"\0" * 40_000,
                          "a face list of 4e9 indices in 40 KB"),
        "nan.ply": ((head + "0 0 nan\n1 0 0\n0 1 0\n3 0 1 2\n").encode(), "a NaN coordinate"),
        "big_index.ply": ((head + "0 0 0\n1 0 0\n0 1 0\n3 0 1 99999999999999999999\n").encode(), "index 1e20"),
        "non_utf8_header.ply": (b"ply\nformat ascii 1.0\ncomment \xff\xfe\xfd\n" + head.encode()[19:]
                                + b"0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n", "bytes not UTF-8 in the header"),
        "empty.ply": (b"", "0 bytes"),
        "nan.obj": (b"v 0 0 nan\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", "a NaN coordinate"),
        "inf.obj": (b"v 0 0 1e999\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", "an infinite coordinate"),
        "big_index.obj": (b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 99999999999999999999\n", "index 1e20"),
        "zero_index.obj": (b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n", "index 0"),
        "binary_junk.obj": (bytes(range(256)) * 40, "bytes, not text"),
        "points_only.obj": (b"v 0 0 0\nv 1 0 0\nv 0 1 0\n", "vertices, no faces"),
        "empty.obj": (b"", "0 bytes"),
        "huge_count.stl": (b"\0" * 80 + np.uint32(4_000_000_000).tobytes() + b"\0" * 100, "4e9 triangles declared"),
        "truncated_ascii.stl": (b"solid s\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1 0 0\n",
                                "ASCII STL cut inside a facet"),
        "empty.stl": (b"", "0 bytes"),
        # landmark files (with the valid sample scan)
        "nan.json": (b'{"points": {"3.7": [NaN, 0, 0]}}', "NaN"),
        "huge_int.json": (b'{"points": {"3.7": [1' + b"0" * 400 + b', 0, 0]}}', "a 400-digit integer"),
        "deep.json": (b"[" * 200_000 + b"]" * 200_000, "JSON nested 200,000 deep"),
        "odd.json": (b'{"points": {"3.7": {"x": 1}}, "markers": [1]}', "points not [x, y, z]"),
        "non_utf8.json": (b'{"points": {"3.7": [0, 0, 0]}, "who": "Ren\xe9"}', "Latin-1, not UTF-8"),
        "empty.json": (b"", "0 bytes"),
        "billion_laughs.pp": (("<?xml version='1.0'?>\n<!DOCTYPE PickedPoints [\n <!ENTITY a 'aaaaaaaaaa'>\n"
                               + "".join(f" <!ENTITY {c} '{('&' + p + ';') * 10}'>\n"
                                         for p, c in zip("abcdefgh", "bcdefghi"))
                               + "]>\n<PickedPoints><point name='&i;' x='0' y='0' z='0'/></PickedPoints>\n"
                               ).encode(), "XML billion laughs"),
        "external_entity.pp": (b"<?xml version='1.0'?>\n<!DOCTYPE PickedPoints [<!ENTITY x SYSTEM 'file:///etc/passwd'>]>"
                               b"\n<PickedPoints><point name='&x;' x='0' y='0' z='0'/></PickedPoints>\n",
                               "XML external entity"),
        "truncated.pp": (b"<!DOCTYPE PickedPoints>\n<PickedPoints><point name='3.7' x='0'", "cut short"),
        # landmark files that read but do not fit the sample scan (its clicks, changed)
        **clicks_that_do_not_fit(v),
        # .fap files (read_fap, as Import .fap calls it)
        "huge_frames.fap": (b"2.1 x 25 100000000\n", "18 bytes declaring 1e8 frames"),
        "huge_frame_number.fap": (f"2.1 x 25 1\n{MASK}\n1e300 5\n".encode(), "frame number 1e300"),
        "long_number.fap": (f"2.1 x 25 1\n{MASK}\n0 1{'0' * 5000}\n".encode(), "a 5000-digit value"),
        "non_utf8.fap": (b"2.1 \xff\xfe 25 1\n" + MASK.encode() + b"\n0 \xff\n", "bytes not UTF-8"),
        "empty.fap": (b"", "0 bytes"),
        "truncated.fap": (f"2.1 x 25 3\n{MASK}\n0 5\n{MASK}\n".encode(), "3 frames declared, 1 given"),
    }
    for name, (data, _) in hostile.items():
        (d / name).write_bytes(data)
    shutil.copy(SAMPLE_DIR / "landmarks.json", d / "landmarks.json")
    return {n: w for n, (_, w) in hostile.items()}, valid


def run_measured(cmd: list[str], timeout: float = 60.0) -> tuple[int, float, float, str, str]:
    """(exit code, seconds, peak resident MB, stdout, stderr) of cmd in its own process."""
    with tempfile.TemporaryFile() as out, tempfile.TemporaryFile() as err:
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=out, stderr=err, cwd=ROOT)
        deadline = t0 + timeout
        while True:
            pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
            if pid:
                break
            if time.perf_counter() > deadline:
                proc.kill()
                pid, status, usage = os.wait4(proc.pid, 0)
                break
            time.sleep(0.01)
        seconds = time.perf_counter() - t0
        proc.returncode = os.waitstatus_to_exitcode(status)
        out.seek(0)
        err.seek(0)
        return proc.returncode, seconds, usage.ru_maxrss / 1024.0, out.read().decode(), err.read().decode()


FAP_CHILD = ("import sys\nfrom headadapt_addon.core.exceptions import HeadAdaptError\n"
             "from headadapt_addon.core.fapfile import read_fap\n"
             "try:\n    read_fap(sys.argv[1])\nexcept HeadAdaptError as exc:\n"
             "    print(f'headadapt: error: {exc}', file=sys.stderr)\n    sys.exit(2)\n")


def command(d: pathlib.Path, name: str, out: pathlib.Path) -> list[str]:
    batch = [sys.executable, "-m", "headadapt_addon.batch", "adapt", "--levels", "1", "--out", str(out)]
    if name.endswith(".fap"):
        return [sys.executable, "-c", FAP_CHILD, str(d / name)]
    if name.endswith((".json", ".pp")):
        return batch + ["--scan", str(SAMPLE_DIR / "scan.ply"), "--landmarks", str(d / name)]
    return batch + ["--scan", str(d / name), "--landmarks", str(d / "landmarks.json")]


def check_files(d: pathlib.Path, hostile: dict, valid: dict, say) -> int:
    failures = 0
    say(f"{'file':26s} {'exit':>4s} {'s':>5s} {'MB':>6s}  message")
    for name, what in [*hostile.items(), *valid.items()]:
        out = d / "out" / name
        code, seconds, rss, stdout, stderr = run_measured(command(d, name, out))
        lines = stderr.strip().splitlines()
        if name in hostile:
            ok = (code == 2 and len(lines) == 1 and str(d / name) in lines[0] and "Traceback" not in stderr
                  and seconds < MAX_SECONDS and rss < MAX_RSS_MB)
            shown = lines[0].removeprefix("headadapt: error: ").replace(str(d) + "/", "") if lines else stderr[-200:]
        else:
            ok = code in (0, 3) and (out / "adapted_head.obj").is_file()
            shown = f"adapted ({what}): " + next((s.removeprefix("headadapt: ") for s in stdout.splitlines()
                                                        if s.startswith("headadapt: best level")), stderr[-200:])
        failures += not ok
        say(f"{name:26s} {code:4d} {seconds:5.2f} {rss:6.0f}  {'' if ok else 'FAILED: '}{shown}")
    return failures


def check_folder(d: pathlib.Path, say) -> int:
    """Folder mode over good, corrupt and hanging scans, locally and on a Dask LocalCluster."""
    src = d / "folder"
    src.mkdir()
    for name in ("good_a.ply", "good_b.obj"):
        shutil.copy(d / ("sample_binary.ply" if name.endswith(".ply") else "sample.obj"), src / name)
    shutil.copy(d / "truncated_binary.ply", src / "corrupt.ply")
    os.mkfifo(src / "hanging.obj")
    for scan in src.iterdir():
        shutil.copy(SAMPLE_DIR / "landmarks.json", scan.with_suffix(".json"))
    try:
        import distributed
    except ImportError:
        say("folder mode on Dask: dask.distributed not installed, not run")
        distributed = None
    failures, statuses = 0, {}
    for mode in ("local", "dask") if distributed else ("local",):
        out = d / f"folder_out_{mode}"
        cmd = [sys.executable, "-m", "headadapt_addon.batch", "folder", "--folder", str(src), "--out", str(out),
               "--levels", "1", "--timeout", "15"]
        t0 = time.perf_counter()
        if mode == "dask":
            with distributed.LocalCluster(n_workers=1, threads_per_worker=2, processes=False, protocol="tcp://",
                                          dashboard_address=None) as cluster:
                proc = subprocess.run(cmd + ["--scheduler", cluster.scheduler_address], capture_output=True,
                                      text=True, cwd=ROOT, timeout=600)
        else:
            proc = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, timeout=600)
        summary = json.loads((out / "summary.json").read_text())
        statuses[mode] = {pathlib.Path(s["scan"]).name: s["status"] for s in summary["scans"]}
        ok = proc.returncode == 4 and statuses[mode] == {"corrupt.ply": "failed", "good_a.ply": "done",
                                                         "good_b.obj": "done", "hanging.obj": "timeout"}
        failures += not ok
        say(f"folder mode ({mode}): exit {proc.returncode} in {time.perf_counter() - t0:.1f} s, "
            f"{summary['done']} done, {summary['failed']} failed: "
            + ", ".join(f"{n} {s}" for n, s in statuses[mode].items()) + ("" if ok else "  FAILED"))
    if distributed and statuses["dask"] != statuses["local"]:
        failures += 1
        say("FAILED: the Dask run's statuses differ from the local run's")
    return failures


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--dir", type=pathlib.Path, help="where to build the directory (default: a new temp folder)")
    parser.add_argument("--no-folder", action="store_true", help="skip the folder-mode checks")
    args = parser.parse_args(argv)
    d = (args.dir or pathlib.Path(tempfile.mkdtemp(prefix="headadapt-hostile-"))).resolve()
    if d.exists() and any(d.iterdir()):
        parser.error(f"{d} is not empty")
    hostile, valid = build(d)
    print(f"{len(hostile)} hostile and {len(valid)} valid inputs in {d}", flush=True)
    failures = check_files(d, hostile, valid, lambda s: print(s, flush=True))
    if not args.no_folder:
        failures += check_folder(d, lambda s: print(s, flush=True))
    print(f"{'all checks passed' if not failures else f'{failures} checks FAILED'}")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
