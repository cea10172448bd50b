"""Benchmark: more right clicks than the panel's 11. Prints figures (HeadAdapt alone).

    ./ha bench clicks [--seeds 0-23] [--reps 3]      # the 11, the 11 and random sets of more, every FDP
    ./ha bench clicks --seeds 0-7 --one              # the 11 and one more FDP at a time

Per scan-like head (tools/testheads.py, people's clicks): the fit from the panel's 11 clicks, then from
the 11 with `--reps` random sets of 4 to 19 more of the head's other skin FDPs (drawn with the seed's
own numpy generator, so every tree gets the same sets), then with every FDP. Prints the correspondence RMS on the seen face (mm of the true head) and its change
against the 11 alone, the clicks dropped as wrong ("D"), and a summary: mean and worst change over the
random sets, how many came out worse than the 11 alone, and the same for every FDP. Right clicks should
not make the face worse (docs/MEASUREMENTS.md, stop 59). As in ./ha bench adapt, the head's held-out
markers are given (their E_m helps choose the level).
"""

import argparse
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from bench_adapt import load_template, measure, parse_seeds

from headadapt_addon.batch import spatial_backend
from headadapt_addon.core import adapt, mpeg4
from headadapt_addon.core.mesh import spatial
from tools import testheads


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", default="0-23", type=parse_seeds)
    parser.add_argument("--reps", type=int, default=3, help="random sets of more clicks per head")
    parser.add_argument("--one", action="store_true", help="instead: the 11 and each other FDP alone")
    args = parser.parse_args(argv)
    tpl = load_template()
    face = testheads.face_mask(tpl)
    skin = {k for k, m in tpl.meta["fdps"].items() if m["part"] == "skin"}
    options = adapt.AdaptOptions(backend=spatial_backend())
    changes, every = [], []
    for seed in args.seeds:
        head = testheads.make_head(seed, style="scan")
        query = spatial.MeshQuery(head.scan_verts, head.scan_tris, backend=testheads.BACKEND)
        seen = face & head.true_on_scan
        base = {k: head.fdp_clicks[k] for k in mpeg4.CLICKS_11 if k in head.fdp_clicks}
        others = sorted(k for k in head.fdp_clicks if k in skin and k not in base)
        if args.one:
            sets = [("11", [])] + [(k, [k]) for k in others]
        else:
            rng = np.random.default_rng(seed)
            sets = [("11", [])] + [(f"r{r}", list(rng.choice(others, size=rng.integers(4, 20), replace=False)))
                                   for r in range(args.reps)] + [("all", others)]
        out = []
        for name, extra in sets:
            clicks = dict(base, **{k: head.fdp_clicks[k] for k in extra})
            res = adapt.adapt(tpl, head.scan_verts, head.scan_tris, clicks, options, markers=head.markers)
            corr = measure(tpl, head, res.verts_scan, seen, query)["corr_rms"]
            out.append((name, len(clicks), corr, sorted(res.dropped)))
        alone = out[0][2]
        for name, _, corr, _ in out[1:]:
            (every if name == "all" else changes).append(corr - alone)
        print(seed, " ".join(f"{n}:{c}:{x:.3f}({x - alone:+.2f}){'D' + ','.join(d) if d else ''}"
                             for n, c, x, d in out), flush=True)
    for what, d in (("one more FDP" if args.one else "random sets", changes), ("every FDP", every)):
        if d:
            d = np.array(d)
            print(f"{what}: correspondence against the 11 alone, mean {d.mean():+.3f} mm, worst {d.max():+.2f}, "
                  f"worse on {int((d > 0).sum())} of {len(d)}")


if __name__ == "__main__":
    main()
