"""Benchmark: baking every key on adapted heads, on one core and on two; the bone's inside test fast
against brute force; in one run.

    ./ha bench bake [--reps 2] [--seeds 100-103]

Heads, each adapted and its anatomy transferred as the batch does: the bundled sample scan with the
clicks and markers of its landmarks.json (as `./ha demo` adapts it), the sample with the 8 clicks
the panel asks for (as an artist adapts it: no markers), and the scan-like test heads of --seeds
(tools/testheads, style "scan", their 8 clicks). On each, the 76 MPEG-4 keys (expressions, visemes,
FAP keys) and all 128 (with ARKit's 52), timed (wall seconds, fastest of --reps):
  one core   bake.bake(..., helper=False): every equilibrium in this process
  two cores  bake.bake(...): a helper process bakes keys from the same queue (core/skin/parallel.py)
the ratio, and whether the keys are the same to the bit. Heads printed slowest first.
Then, on the sample head (one core both ways), the skin's inside-the-bone test:
  brute  summed over every bone triangle (inside.winding_numbers), as the bake did before
  fast   as it is: core/mesh/winding.py's exact fast winding numbers, the bone closed once per skin
         model and refit as the jaw moves
Printed: seconds of the whole bake each way (fastest run; and the process's CPU seconds of it), the
model's build, ms per key, the ratio brute / fast, and the largest difference of any vertex of any
key between the two (the winding numbers agree to rounding; a point exactly at 1/2 could differ).
"""
import argparse
import pathlib
import sys
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from bench_adapt import parse_seeds

from headadapt_addon.batch import SAMPLE_DIR
from headadapt_addon.core import meshio, mpeg4
from headadapt_addon.core.adapt import adapt
from headadapt_addon.core.anatomy import transfer
from headadapt_addon.core.mesh.inside import winding_numbers
from headadapt_addon.core.skin import bake, contact
from headadapt_addon.core.template import load_template
from tools import testheads


def brute_winding(self, pts, rot, t):
    _, _, v_cr, v_md, bone_t = self.bone
    return winding_numbers(pts, np.vstack([v_cr, self.on_jaw(v_md, rot, t)]), bone_t)


MPEG4_KINDS = ("expression", "viseme", "fap")


def run(tpl, ana, way):
    fast = contact.ContactMixin._winding
    if way == "brute":
        contact.ContactMixin._winding = brute_winding
    try:
        t0, c0 = time.perf_counter(), time.process_time()
        keys, timing = bake.bake(tpl, ana, helper=False)     # this process's winding test for every key
        return keys, timing, time.perf_counter() - t0, time.process_time() - c0
    finally:
        contact.ContactMixin._winding = fast


def heads(tpl, seeds):
    """[(name, Anatomy)] of the heads the docstring names."""
    verts, tris = meshio.read_mesh(SAMPLE_DIR / "scan.ply")[:2]
    points, meta = meshio.read_landmark_file(SAMPLE_DIR / "landmarks.json")
    out = [("sample, ./ha demo's clicks and markers", transfer(tpl, adapt(tpl, verts, tris, points, markers=meta.get("markers")))),
           ("sample, the 8 clicks", transfer(tpl, adapt(tpl, verts, tris, {k: points[k] for k in mpeg4.CLICKS_8})))]
    for seed in seeds:
        h = testheads.make_head(seed, style="scan")
        clicks = {k: h.fdp_clicks[k] for k in mpeg4.CLICKS_8 if k in h.fdp_clicks}
        out.append((f"test head {seed}, 8 clicks", transfer(tpl, adapt(tpl, h.scan_verts, h.scan_tris, clicks))))
    return out


def same_keys(a, b):
    return [k.name for k in a] == [k.name for k in b] and all(
        x.moved.keys() == y.moved.keys() and all(np.array_equal(x.moved[p], y.moved[p]) for p in x.moved)
        for x, y in zip(a, b))


def cores(tpl, named, reps):
    """Per head: 76 keys on one core and two, all 128 on one and two (fastest of reps), same keys."""
    rows = []
    for name, ana in named:
        best, keys = {}, {}
        for _ in range(reps):
            for kinds in (MPEG4_KINDS, None):
                for helper in (False, True):
                    t0 = time.perf_counter()
                    got, timing = bake.bake(tpl, ana, helper=helper, **({"kinds": kinds} if kinds else {}))
                    wall = time.perf_counter() - t0
                    key = (kinds is None, helper)
                    best[key] = min(best.get(key, np.inf), wall)
                    keys[key] = got
        same = same_keys(keys[(False, False)], keys[(False, True)]) and same_keys(keys[(True, False)], keys[(True, True)])
        rows.append((name, len(keys[(False, True)]), best[(False, False)], best[(False, True)],
                     len(keys[(True, True)]), best[(True, False)], best[(True, True)], same))
        print(f"  {name}: done", flush=True)
    rows.sort(key=lambda r: -r[3])
    print(f"\nkeys baked on adapted heads, wall seconds (fastest of {reps}), slowest first:")
    print(f"  {'head':40s} {'keys':>4s} {'1 core':>7s} {'2 cores':>7s} {'ratio':>6s} | {'keys':>4s} {'1 core':>7s} "
          f"{'2 cores':>7s} {'ratio':>6s} | same keys")
    for name, n76, a, b, n128, c, d, same in rows:
        print(f"  {name:40s} {n76:4d} {a:7.2f} {b:7.2f} {a / b:5.2f}x | {n128:4d} {c:7.2f} {d:7.2f} {c / d:5.2f}x | "
              f"{'yes' if same else 'NO'}")
    print(f"  slowest: the {rows[0][1]} MPEG-4 keys in {rows[0][3]:.2f} s on two cores ({rows[0][2]:.2f} s on one), "
          f"all {rows[0][4]} in {max(r[6] for r in rows):.2f} s at most")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--reps", type=int, default=2)
    parser.add_argument("--seeds", default="100-103", help="scan-like test heads (tools/testheads), '' for none")
    args = parser.parse_args(argv)
    tpl = load_template()
    seeds = parse_seeds(args.seeds) if args.seeds else []
    named = heads(tpl, seeds)
    cores(tpl, named, args.reps)
    ana = named[0][1]
    best = {}
    for _ in range(args.reps):
        for way in ("brute", "fast"):
            keys, timing, wall, cpu = run(tpl, ana, way)
            if way not in best or wall < best[way][2]:
                best[way] = (keys, timing, wall, cpu)
    print(f"\nall {len(best['fast'][0])} keys baked on the sample head's adapted skin on one core (fastest of {args.reps}):")
    for way in ("brute", "fast"):
        keys, timing, wall, cpu = best[way]
        print(f"  {way:5s} {wall:6.2f} s (cpu {cpu:6.2f} s): model build {timing['build_s']:.2f} s, "
              f"{timing['per_key_s'] * 1e3:6.1f} ms per key")
    diff = max((float(np.abs(a.moved[p] - b.moved[p]).max()) for a, b in zip(best["brute"][0], best["fast"][0])
                for p in a.moved), default=0.0)
    print(f"  ratio brute / fast {best['brute'][2] / best['fast'][2]:.2f}x; largest vertex difference of any key "
          f"{diff:.2e} m")


if __name__ == "__main__":
    main()
