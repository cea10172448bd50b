"""Benchmark: baking all keys on an adapted head, the bone's inside test fast against brute force, in one run.

    ./ha bench bake [--reps 2]

The head: the bundled sample scan adapted as `./ha demo` adapts it, its anatomy transferred. Then
bake.bake(tpl, anatomy) (every expression, viseme and FAP key) `reps` times each way, alternately:
  brute  the skin's inside-the-bone test summed over every bone triangle (inside.winding_numbers),
         as the bake did before
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

from headadapt_addon.batch import SAMPLE_DIR
from headadapt_addon.core import meshio
from headadapt_addon.core.adapt import adapt
from headadapt_addon.core.anatomy import transfer
from headadapt_addon.core.mesh.inside import winding_numbers
from headadapt_addon.core.skin import bake, contact
from headadapt_addon.core.template import load_template


def brute_winding(self, pts, rot, t):
    _, _, v_cr, v_md, bone_t = self.bone
    return winding_numbers(pts, np.vstack([v_cr, self.on_jaw(v_md, rot, t)]), bone_t)


def run(tpl, ana, way):
    fast = contact.ContactMixin._winding
    if way == "brute":
        contact.ContactMixin._winding = brute_winding
    try:
        t0, c0 = time.perf_counter(), time.process_time()
        keys, timing = bake.bake(tpl, ana)
        return keys, timing, time.perf_counter() - t0, time.process_time() - c0
    finally:
        contact.ContactMixin._winding = fast


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--reps", type=int, default=2)
    args = parser.parse_args(argv)
    tpl = load_template()
    verts, tris = meshio.read_mesh(SAMPLE_DIR / "scan.ply")[:2]
    points, meta = meshio.read_landmark_file(SAMPLE_DIR / "landmarks.json")
    ana = transfer(tpl, adapt(tpl, verts, tris, points, markers=meta.get("markers")))
    best = {}
    for _ in range(args.reps):
        for way in ("brute", "fast"):
            keys, timing, wall, cpu = run(tpl, ana, way)
            if way not in best or wall < best[way][2]:
                best[way] = (keys, timing, wall, cpu)
    print(f"\nall {len(best['fast'][0])} keys baked on the sample head's adapted skin (fastest of {args.reps}):")
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
