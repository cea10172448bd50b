"""Benchmark: anatomy transfer, old (brute-force inside tests) against new, in one run. Prints figures.

    ./ha bench transfer [--reps 3] [--seeds 100-103] [--real]
    ./ha bench transfer --eyes 300-319 [--clicks 11]

The heads: the bundled sample scan adapted as `./ha demo` adapts it (its clicks and markers) and
from the 8 clicks the panel asks for, the scan-like test heads of --seeds (tools/testheads, style
"scan", their 8 clicks); --real adds the CT and the two busts of ../shared/scans, or
$HEADADAPT_SCANS. On each adapted head anatomy.transfer runs `reps` times each way, alternating,
and the fastest run of each counts (the machine is shared):

  old   the transfer as it was before core/winding.py: every inside test the brute-force sum
        over all triangles (inside.winding_numbers), the skin near the bone by MeshQuery's
        closest point for every visible skin vertex, the template's skin anchors of the bone
        found anew (the same code with those three put back)
  new   anatomy.transfer as it is: FastWinding (exact, built once per transfer), _within, the
        anchors found once per process, the skull's cap terms kept between its inside tests
        (FastWinding(remember=True)); "cold" is the first transfer of a process, which finds the
        anchors; "forget" is new with every inside test summing the skull's caps afresh

Printed per head, slowest first: seconds old and new (wall clock; and the process's CPU seconds,
less disturbed by other work on a shared machine), their ratio, cold and forget, and the largest
difference of any vertex of any part between old and new, and between forget and new (0:
bit-identical). Then where the time goes, per stage of the transfer (exclusive seconds of the
fastest run) and in all inside tests together.

--eyes SEEDS: where the transfer puts the eyes on scan-like test heads (style "scan", adapted from
their 8 or 11 clicks), against the generator's own eyeballs, mm of the true head: each eye's radius
and the generator's (the mean distance of its vertices from their centre; the generator's two are
alike), the error of its front along the gaze (its most forward point against the generator's eye's,
+: too far forward), of its centre along the gaze and across it, and how much farther apart the two
centres are than the generator's; then the medians.
"""
import argparse
import contextlib
import os
import pathlib
import sys
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from bench_adapt import parse_seeds

from headadapt_addon.core import adapt, anatomy, meshio, mpeg4
from headadapt_addon.core.mesh import geometry, winding
from headadapt_addon.core.mesh.inside import winding_numbers
from headadapt_addon.core.mesh.spatial import MeshQuery
from headadapt_addon.core.template import load_template

STAGES = (  # (label, module, function name): timed exclusive of each other
    ("rest: maps, FDPs, muscles, checks", None, None),
    ("seat the eyes in the orbits", anatomy.pipeline, "seat_orbits"),
    ("keep the bone inside the skin", anatomy.pipeline, "keep_inside"),
    ("relax the pressed bone's folds", geometry, "unfold"),
    ("clear the visible skin", anatomy.pipeline, "clear_visible_skin"),
    ("unrelax under the skin (check)", anatomy.pipeline, "unrelax_under_skin"),
)


class BruteWinding:
    """The old inside test behind FastWinding's interface: every triangle summed at every point."""

    def __init__(self, verts, tris, slack=None, remember=None):
        self.verts, self.tris = np.asarray(verts, dtype=np.float64), tris

    def refit(self, verts):
        self.verts = np.asarray(verts, dtype=np.float64)
        return self

    def __call__(self, points):
        return winding_numbers(points, self.verts, self.tris)


def old_within(points, verts, tris, reach):
    """The old selection of skin points near the bone: the closest point for every one."""
    return MeshQuery(verts, tris, backend="numpy").closest_points(points)[2] < reach


@contextlib.contextmanager
def patched(module, **attrs):
    saved = {k: getattr(module, k) for k in attrs}
    for k, v in attrs.items():
        setattr(module, k, v)
    try:
        yield
    finally:
        for k, v in saved.items():
            setattr(module, k, v)


class Clock:
    """Exclusive seconds per stage: a wrapped function's time less that of wrapped calls inside it."""

    def __init__(self):
        self.seconds, self.stack = {}, []

    def wrap(self, label, fn):
        def timed(*a, **k):
            t0 = time.perf_counter()
            self.stack.append(0.0)
            try:
                return fn(*a, **k)
            finally:
                inner = self.stack.pop()
                dt = time.perf_counter() - t0
                self.seconds[label] = self.seconds.get(label, 0.0) + dt - inner
                if self.stack:
                    self.stack[-1] += dt
        return timed


def timed_transfer(tpl, result, old, cold=False, forget=False):
    """(Anatomy, total seconds, {stage: exclusive seconds}, seconds in inside tests, CPU seconds)."""
    clock = Clock()
    inside = {"s": 0.0}
    base = BruteWinding if old else winding.FastWinding

    class Counted(base):
        def __init__(self, *a, **k):
            t0 = time.perf_counter()
            if forget:
                k["remember"] = False
            super().__init__(*a, **k)
            inside["s"] += time.perf_counter() - t0

        def __call__(self, points):
            t0 = time.perf_counter()
            try:
                return super().__call__(points)
            finally:
                inside["s"] += time.perf_counter() - t0

    with contextlib.ExitStack() as stack:
        stack.enter_context(patched(winding, FastWinding=Counted))
        if old:
            stack.enter_context(patched(anatomy.bone, _within=old_within))
        if old or cold:
            stack.enter_context(patched(anatomy.bone, _ANCHORS={}))
        for label, module, name in STAGES[1:]:
            stack.enter_context(patched(module, **{name: clock.wrap(label, getattr(module, name))}))
        t0, c0 = time.perf_counter(), time.process_time()
        ana = clock.wrap(STAGES[0][0], anatomy.transfer)(tpl, result)
        total, cpu = time.perf_counter() - t0, time.process_time() - c0
    return ana, total, clock.seconds, inside["s"], cpu


def heads(tpl, seeds, real):
    """[(name, AdaptResult)] of the heads the docstring names."""
    from tools import testheads

    sample = ROOT / "assets" / "sample_scan"
    verts, tris = meshio.read_mesh(sample / "scan.ply")[:2]
    points, meta = meshio.read_landmark_file(sample / "landmarks.json")
    markers = meta.get("markers")
    out = [("sample, demo", adapt.adapt(tpl, verts, tris, points, adapt.AdaptOptions(max_levels=4), markers=markers)),
           ("sample, 8 clicks", adapt.adapt(tpl, verts, tris, {k: points[k] for k in mpeg4.CLICKS_8}))]
    for seed in seeds:
        h = testheads.make_head(seed, style="scan")
        clicks = {k: h.fdp_clicks[k] for k in mpeg4.CLICKS_8 if k in h.fdp_clicks}
        out.append((f"test head {seed}", adapt.adapt(tpl, h.scan_verts, h.scan_tris, clicks)))
    if real:
        scans = pathlib.Path(os.environ.get("HEADADAPT_SCANS", ROOT.parent / "shared" / "scans"))
        if not scans.is_dir():
            sys.exit(f"bench transfer --real: no scans at {scans} (set HEADADAPT_SCANS)")
        from tools import realct

        skin_v, skin_t, _, _, clicks = realct.load_ct(scans)
        out.append(("headsq CT", adapt.adapt(tpl, skin_v, skin_t, clicks)))
        for name, path in (("nefertiti", "nefertiti/nefertiti-lowres.obj"),
                           ("demosthenes", "demosthenes/demosthenes-low-res.obj")):
            verts, tris = meshio.read_mesh(scans / path)[:2]
            clicks = meshio.read_landmarks(ROOT / "headless_tests" / "data" / f"{name}_fdps.json")
            out.append((name, adapt.adapt(tpl, verts, tris, clicks)))
    return out


def eyes(tpl, seeds, click_set):
    """The --eyes table (module docstring)."""
    from tools import testheads

    print(f"eyes on scan-like heads, {click_set} clicks, mm of the true head (along: + too far forward)")
    print(f"{'head':>5s} {'radius L':>8s} {'R':>6s} {'true':>6s} {'front L':>8s} {'R':>6s} {'along L':>8s} {'R':>6s} "
          f"{'across L':>8s} {'R':>6s} {'apart':>6s}")
    cols = {k: [] for k in ("dr", "lr", "front", "along", "across", "apart")}
    for seed in seeds:
        head = testheads.make_head(seed, style="scan")
        clicks = head.clicks_11 if click_set == "11" else head.clicks_8
        res = adapt.adapt(tpl, head.scan_verts, head.scan_tris, clicks)
        ana = anatomy.transfer(tpl, res)
        to_scan, mm = res.similarity.inverse(), 1000.0 / head.similarity[0]
        row, centres = {}, {}
        for eye in ("eye_l", "eye_r"):
            v, true = to_scan.apply(ana.parts[eye]), head.true_parts[eye]
            c, tc = v.mean(axis=0), true.mean(axis=0)
            gaze = to_scan.rotation @ ana.rigid[eye].rotation @ np.asarray(tpl.meta["eyes"][eye]["gaze"])
            gaze /= np.linalg.norm(gaze)
            d = (c - tc) * mm
            row[eye] = (np.linalg.norm(v - c, axis=1).mean() * mm, np.linalg.norm(true - tc, axis=1).mean() * mm,
                        d @ gaze, np.linalg.norm(d - (d @ gaze) * gaze), ((v @ gaze).max() - (true @ gaze).max()) * mm)
            cols["front"].append(row[eye][4])
            centres[eye] = (c, tc)
            cols["dr"].append(row[eye][0] - row[eye][1])
            cols["along"].append(row[eye][2])
            cols["across"].append(row[eye][3])
        (cl, tl), (cr, tr) = centres["eye_l"], centres["eye_r"]
        apart = (np.linalg.norm(cl - cr) - np.linalg.norm(tl - tr)) * mm
        cols["apart"].append(apart)
        cols["lr"].append(abs(row["eye_l"][0] - row["eye_r"][0]))
        (rl, tl_r, al, xl, fl), (rr, _, ar, xr, fr) = row["eye_l"], row["eye_r"]
        print(f"{seed:5d} {rl:8.2f} {rr:6.2f} {tl_r:6.2f} {fl:8.2f} {fr:6.2f} {al:8.2f} {ar:6.2f} {xl:8.2f} {xr:6.2f} "
              f"{apart:6.2f}", flush=True)
    c = {k: np.asarray(v) for k, v in cols.items()}
    print(f"radius minus the generator's: mean {c['dr'].mean():.2f}, mean |.| {np.abs(c['dr']).mean():.2f}, largest "
          f"|.| {np.abs(c['dr']).max():.2f}; the two eyes' radii differ by a median {np.median(c['lr']):.2f}, at most "
          f"{c['lr'].max():.2f}")
    print(f"front along the gaze: mean {c['front'].mean():.2f}, mean |.| {np.abs(c['front']).mean():.2f}, largest |.| "
          f"{np.abs(c['front']).max():.2f}")
    print(f"centre along the gaze: mean {c['along'].mean():.2f}, median {np.median(c['along']):.2f}, largest |.| "
          f"{np.abs(c['along']).max():.2f}; across: median {np.median(c['across']):.2f}, largest "
          f"{c['across'].max():.2f}; the centres farther apart than the generator's by a median "
          f"{np.median(c['apart']):.2f}")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--reps", type=int, default=3, help="runs each way per head (the fastest counts)")
    parser.add_argument("--seeds", default="100-103", help="scan-like test heads (tools/testheads), '' for none")
    parser.add_argument("--real", action="store_true", help="also the CT and the busts in ../shared/scans")
    parser.add_argument("--eyes", metavar="SEEDS", help="only where the eyes go on these scan-like heads (docstring)")
    parser.add_argument("--clicks", choices=("8", "11"), default="11", help="the click set of --eyes")
    args = parser.parse_args(argv)
    tpl = load_template()
    if args.eyes:
        return eyes(tpl, parse_seeds(args.eyes), args.clicks)
    rows = []
    kinds = ("old", "cold", "forget", "new")
    for name, result in heads(tpl, parse_seeds(args.seeds) if args.seeds else [], args.real):
        best = {}
        for _ in range(args.reps):
            for key in kinds:
                run = timed_transfer(tpl, result, key == "old", key == "cold", key == "forget")
                if key not in best or run[1] < best[key][1]:
                    best[key] = run

        def largest(a, b):
            diff = {p: float(np.abs(a.parts[p] - b.parts[p]).max()) for p in a.parts}
            worst = max(diff, key=diff.get)
            return f"{diff[worst]:.1e} m" + ("" if diff[worst] == 0 else f" ({worst})")

        rows.append((name, best, largest(best["old"][0], best["new"][0]), largest(best["forget"][0], best["new"][0])))
    rows.sort(key=lambda row: -row[1]["new"][1])
    print(f"anatomy transfer, fastest of {args.reps} runs each way in one process, slowest first "
          "(old: brute-force inside tests, as before core/winding.py)")
    print(f"{'head':16s} {'old s':>7s} {'new s':>7s} {'ratio':>7s} {'cold s':>7s} {'forget s':>8s}  "
          f"{'CPU s old':>9s} {'new':>6s}  largest vertex difference: old-new, forget-new")
    for name, best, d_old, d_forget in rows:
        old, new, cold, forget = (best[k][1] for k in ("old", "new", "cold", "forget"))
        print(f"{name:16s} {old:7.3f} {new:7.3f} {old / new:6.1f}x {cold:7.3f} {forget:8.3f}  "
              f"{best['old'][4]:9.3f} {best['new'][4]:6.3f}  {d_old}, {d_forget}")
    for name, best, _, _ in rows:
        print()
        print(f"where the time goes, {name} (exclusive seconds of the fastest run):")
        print(f"  {'stage':36s} " + " ".join(f"{k:>7s}" for k in kinds))
        for label, _, _ in STAGES:
            print(f"  {label:36s} " + " ".join(f"{best[k][2].get(label, 0.0):7.3f}" for k in kinds))
        print(f"  {'total':36s} " + " ".join(f"{best[k][1]:7.3f}" for k in kinds))
        print(f"  {'of it in inside tests (all stages)':36s} " + " ".join(f"{best[k][3]:7.3f}" for k in kinds))


if __name__ == "__main__":
    main()
