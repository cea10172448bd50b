"""Benchmark: HeadAdapt vs two peers on scan-like generated heads, with people's clicks. Prints figures.

    ./ha bench adapt [--seeds 100-107] [--clicks 8,11] [--no-nricp] [--big] [--style legacy]
    ./ha bench adapt --real            # the real scans in ../shared/scans, clicks in headless_tests/data
    ./ha bench adapt --oracle          # the floor: maps that know the truth, and HeadAdapt given part of it
    ./ha bench adapt --seeds 0-3 --identity 0 --targets 0   # heads whose truth is the template itself
    ./ha bench adapt --seeds 0,3 --regions   # where the error lies: along the skin by region, level by level
    ./ha bench adapt --seeds 500-515 --neck-tilt 8   # the heads turned on their necks (a nod of 8 deg std)
    ./ha bench adapt --seeds 600-615 --coarse        # a phone's scan: about 4,000 vertices
    ./ha bench adapt --seeds 600-615 --noise-mm 1    # a noisier scanner (std along the normal, mm)
    ./ha bench adapt --seeds 600-615 --click-noise-mm 4   # sloppier people (and 1.5x that along lid and lip lines)
    ./ha bench adapt --seeds 0-11 --clicks 8 --per-marker   # each held-out FDP's error, and the RMS without it
    ./ha bench adapt --seeds 0-11 --clicks 8,8+   # the 8 clicks, then with every suggestion accepted
    ./ha bench adapt --seeds 0-11 --clicks 8 --common   # the error every head shares against each head's own

Seeds 100-107 are the REPORTING set (the default): figures quoted anywhere come from them. Seeds
0-49 may be used for tuning (parameters, thresholds, ideas); never tune on 100-107, or the figures
stop meaning anything. Heads: tools/testheads.py, style "scan" (what a ring of scanners sees,
holes under the chin, in a cheek and at the back of the head, noise, random pose and unit, a
realistic spread of identities; --style legacy runs the suite's old heads, to compare). Each head
is adapted from its CLICKS_8 and from its CLICKS_11 (mpeg4), clicked as people click: the true
point plus about 2 mm of disagreement (3 mm along lid and lip lines), snapped to the scan.

Methods, from the same clicks and the same calibration (HeadAdapt's similarity, handed to both
peers, which do not calibrate), in one run:
  headadapt     adapt.adapt(tpl, scan, clicks, markers=held-out FDPs at their true positions)
  rbf_clicks    scipy RBFInterpolator (thin-plate) on the clicks' displacements alone
  nricp_amberg  trimesh's nricp_amberg with the clicks as landmarks
HeadAdapt is given the held-out markers (adapt's E_m, which weighs into its choice of level); the
peers are not. Every figure is in mm of the true head (the scan's unit divided out):
  corr RMS / p95  distance of each template vertex from its true position, over the SEEN FACE: the
                  face regions' vertices whose true position lies on the scan (not in a hole, not
                  hidden from every scanner)
  surf RMS        distance of the same vertices from the scan's surface (printed beside it: the true
                  skin's own, which is not 0: the scan's noise, and the scan is the head Catmull-Clark
                  subdivided while the template's vertices are the control points; a fit laid onto
                  the scan, as HeadAdapt's last step lays it, lies nearer)
  marker RMS      the held-out FDPs (the template's face + barycentrics on the adapted vertices)
                  against their true positions
  s               seconds of the method (peers: without the shared calibration)
A peer that raises on a head counts as failed there (inf), and the run goes on.
--real has no ground truth: surface RMS over the face vertices that every method puts on the
scan's inside (closest point on no border triangle), in the template's mm, and seconds.
"""
import argparse
import contextlib
import json
import os
import pathlib
import sys
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from headadapt_addon.batch import spatial_backend
from headadapt_addon.core import adapt, meshio, mpeg4
from headadapt_addon.core.adapt import level0, suggest
from headadapt_addon.core.mesh import geometry, spatial
from headadapt_addon.core.template import load_template
from tools import testheads

REPORTING_SEEDS = tuple(range(100, 108))
TUNING_SEEDS = tuple(range(50))
METHODS = ("headadapt", "rbf_clicks", "nricp_amberg")
CLICK_SETS = {"8": mpeg4.CLICKS_8, "11": mpeg4.CLICKS_11}


def set_clicks(tpl, head, name):
    """The clicks of a set on a head: "8" or "11" as people click them; "8+" or "11+" those and every
    FDP Suggest the Rest proposes from them, accepted whole (as an artist may)."""
    clicks = {k: head.fdp_clicks[k] for k in CLICK_SETS[name.rstrip("+")] if k in head.fdp_clicks}
    if name.endswith("+"):
        clicks.update(suggest.suggest_fdps(tpl, head.scan_verts, head.scan_tris, clicks,
                                           options=adapt.AdaptOptions(backend=spatial_backend())))
    return clicks


def skin_fdp(tpl, verts, name):
    """An FDP on a skin given as template-indexed verts (its face + barycentrics)."""
    ref = tpl.meta["fdps"][name]
    return np.asarray(ref["bary"]) @ verts[tpl.skin.tris[ref["face"]]]


def measure(tpl, head, verts_scan, seen_face, query):
    """Figures (mm of the true head) of an adapted skin given in the scan frame."""
    if verts_scan is None:            # the method failed
        return {"corr_rms": np.inf, "corr_p95": np.inf, "surf_rms": np.inf, "marker_rms": np.inf, "markers": {}}
    s = head.similarity[0]
    d = np.linalg.norm(verts_scan[seen_face] - head.true_template[seen_face], axis=1) / s * 1000
    surf = query.closest_points(verts_scan[seen_face])[2] / s * 1000
    each = {k: float(np.linalg.norm(skin_fdp(tpl, verts_scan, k) - p) / s * 1000) for k, p in head.markers.items()
            if tpl.meta["fdps"][k]["part"] == "skin"}
    mk = list(each.values())
    return {"corr_rms": float(np.sqrt(np.mean(d ** 2))), "corr_p95": float(np.percentile(d, 95)),
            "surf_rms": float(np.sqrt(np.mean(surf ** 2))),
            "marker_rms": float(np.sqrt(np.mean(np.square(mk)))) if mk else float("nan"), "markers": each}


def peer_rbf(tpl, clicks, sim):
    """Thin-plate RBF on the clicks' displacements (template frame), mapped back to the scan frame."""
    from scipy.interpolate import RBFInterpolator

    t0 = time.perf_counter()
    tp = tpl.fdp_points()
    names = [k for k in clicks if k in tp]
    P = np.array([tp[k] for k in names])
    Q = sim.apply(np.array([clicks[k] for k in names]))
    f = RBFInterpolator(P, Q - P, kernel="thin_plate_spline")
    v = tpl.skin.verts + f(tpl.skin.verts)
    return sim.inverse().apply(v), time.perf_counter() - t0


def peer_nricp(tpl, scan_verts, scan_tris, clicks, sim):
    """trimesh's nricp_amberg, template skin onto the scan (template frame), clicks as landmarks."""
    import trimesh
    from trimesh.registration import nricp_amberg

    t0 = time.perf_counter()
    names = [k for k in clicks if k in tpl.meta["fdps"] and tpl.meta["fdps"][k]["part"] == "skin"]
    src = trimesh.Trimesh(tpl.skin.verts, tpl.skin.tris, process=False)
    tgt = trimesh.Trimesh(sim.apply(scan_verts), scan_tris, process=False)
    faces = np.array([tpl.meta["fdps"][k]["face"] for k in names])
    bary = np.array([tpl.meta["fdps"][k]["bary"] for k in names])
    target = sim.apply(np.array([clicks[k] for k in names]))
    v = nricp_amberg(src, tgt, source_landmarks=(faces, bary), target_positions=target, distance_threshold=0.02)
    return sim.inverse().apply(v), time.perf_counter() - t0


def run_methods(tpl, scan_verts, scan_tris, clicks, markers=None, nricp=True):
    """{method: (verts in the scan frame, seconds)} and HeadAdapt's result, from the same clicks.
    HeadAdapt runs with the batch command's spatial backend (batch.spatial_backend(): Embree's rays
    where embreex is installed, as requirements.txt has it; else the numpy tree)."""
    t0 = time.perf_counter()
    res = adapt.adapt(tpl, scan_verts, scan_tris, clicks, adapt.AdaptOptions(backend=spatial_backend()),
                      markers=markers)
    out = {"headadapt": (res.verts_scan, time.perf_counter() - t0)}
    peers = [("rbf_clicks", lambda: peer_rbf(tpl, clicks, res.similarity))]
    if nricp:
        peers.append(("nricp_amberg", lambda: peer_nricp(tpl, scan_verts, scan_tris, clicks, res.similarity)))
    for name, run in peers:
        t0 = time.perf_counter()
        try:
            out[name] = run()
        except Exception as exc:      # a peer that fails on a scan fails that scan (None), the run goes on
            print(f"  {name} failed: {type(exc).__name__}: {exc}")
            out[name] = (None, time.perf_counter() - t0)
    return out, res


def parse_seeds(text):
    """'100-107' or '1,2,5' or '0-3,9' -> [seeds]."""
    seeds = []
    for part in text.split(","):
        a, _, b = part.partition("-")
        seeds += list(range(int(a), int(b) + 1)) if b else [int(a)]
    return seeds


def _fmt(r):
    return (f"{r['corr_rms']:5.2f} {r['corr_p95']:5.2f} {r['surf_rms']:5.2f} {r['marker_rms']:5.2f} "
            f"{r['seconds']:5.1f}")


def report(rows, methods, set_name, per_marker=False):
    """Print the per-head table (worst HeadAdapt correspondence first), medians and head counts."""
    print(f"\n== {set_name} clicks ({', '.join(CLICK_SETS[set_name.rstrip('+')])}"
          f"{' and every suggestion' if set_name.endswith('+') else ''}); mm of the true head, seen face; "
          f"HeadAdapt's spatial backend {spatial_backend()} ==")
    head = f"{'seed':>4s} {'unit':>4s} {'noise':>5s} {'clk':>3s} {'mk':>3s} "
    sub = "corr   p95  surf  mark     s"
    print(head + " | ".join(f"{m:^29s}" for m in methods))
    print(" " * len(head) + " | ".join(f"{sub:^29s}" for _ in methods))
    for r in sorted(rows, key=lambda r: -r["headadapt"]["corr_rms"]):
        print(f"{r['seed']:4d} {r['unit']:>4s} {r['noise']:5.2f} {r['clicks']:3d} {r['markers']:3d} "
              + " | ".join(f"{_fmt(r[m]):^29s}" for m in methods))
    med = {m: {k: float(np.median([r[m][k] for r in rows])) for k in rows[0][m] if k != "markers"} for m in methods}
    print(f"{'median':>21s}    " + " | ".join(f"{_fmt(med[m]):^29s}" for m in methods))
    floor = np.array([r["true_surf"] for r in rows])
    print(f"the true skin itself lies {np.median(floor):.2f} mm RMS from the scan on the seen face (median; "
          f"{floor.min():.2f} to {floor.max():.2f}): the scan's noise, and its vertices are the control points "
          f"of the subdivided surface the scan is")
    if "nricp_amberg" in methods:
        n = len(rows)
        corr = sum(r["headadapt"]["corr_rms"] < r["nricp_amberg"]["corr_rms"] for r in rows)
        surf = sum(r["headadapt"]["surf_rms"] < r["nricp_amberg"]["surf_rms"] for r in rows)
        speed = np.median([r["nricp_amberg"]["seconds"] / r["headadapt"]["seconds"] for r in rows])
        print(f"HeadAdapt beats nricp_amberg on correspondence on {corr}/{n} heads, on surface on {surf}/{n}; "
              f"speed ratio nricp/HeadAdapt {speed:.1f}x (median per head)")
    if per_marker:
        marker_table(rows, methods)
    return med


def marker_table(rows, methods):
    """Each held-out FDP's error, RMS over the heads that hold it out, per method (worst for HeadAdapt
    first), and each method's marker RMS without each FDP in turn: which FDPs the marker RMS is made of."""
    names = sorted({k for r in rows for k in r["headadapt"]["markers"]})
    rms = {m: {k: float(np.sqrt(np.mean([r[m]["markers"][k] ** 2 for r in rows if k in r[m]["markers"]])))
               for k in names} for m in methods}
    print("\nper held-out FDP: RMS over the heads (mm); then the median marker RMS without that FDP")
    print(f"{'FDP':>6s} {'heads':>5s} " + " ".join(f"{m:>12s}" for m in methods) + "   without it: "
          + " ".join(f"{m:>12s}" for m in methods))
    for k in sorted(names, key=lambda k: -rms["headadapt"][k]):
        n = sum(k in r["headadapt"]["markers"] for r in rows)
        without = [float(np.median([np.sqrt(np.mean([v ** 2 for j, v in r[m]["markers"].items() if j != k]))
                                    for r in rows if r[m]["markers"]])) for m in methods]
        print(f"{k:>6s} {n:5d} " + " ".join(f"{rms[m][k]:12.2f}" for m in methods) + "   without it: "
              + " ".join(f"{w:12.2f}" for w in without))


def synthetic(args):
    tpl = load_template()
    face = testheads.face_mask(tpl)
    methods = [m for m in METHODS if m != "nricp_amberg" or not args.no_nricp]
    sets = args.clicks.split(",")
    rows = {k: [] for k in sets}
    tuning = [s for s in args.seeds if s in TUNING_SEEDS]
    if tuning and set(args.seeds) & set(REPORTING_SEEDS):
        print("note: mixing tuning seeds (0-49) with reporting seeds (100-107)")
    for seed in args.seeds:
        t0 = time.perf_counter()
        head = testheads.make_head(seed, style=args.style, **_head_args(args))
        made = time.perf_counter() - t0
        seen = face & head.true_on_scan
        query = spatial.MeshQuery(head.scan_verts, head.scan_tris, backend=testheads.BACKEND)
        # the true skin's own distance from the scan (the module's "surf RMS")
        true_surf = measure(tpl, head, head.true_template, seen, query)["surf_rms"]
        for name in sets:
            clicks = set_clicks(tpl, head, name)
            out, res = run_methods(tpl, head.scan_verts, head.scan_tris, clicks, markers=head.markers,
                                   nricp=not args.no_nricp)
            row = {"seed": seed, "unit": head.meta["unit"], "noise": head.meta["noise_mm"], "clicks": len(clicks),
                   "markers": len(head.markers), "true_surf": true_surf}
            for m, (v, sec) in out.items():
                row[m] = {**measure(tpl, head, v, seen, query), "seconds": sec}
            rows[name].append(row)
            print(f"head {seed} ({len(head.scan_verts):,} vertices, made in {made:.1f} s, seen face "
                  f"{seen.sum()} of {face.sum()} vertices), {name} clicks: " + "; ".join(
                      f"{m} corr {row[m]['corr_rms']:.2f} surf {row[m]['surf_rms']:.2f} mk {row[m]['marker_rms']:.2f} "
                      f"{row[m]['seconds']:.1f} s" for m in methods)
                  + f"; the true skin's own surface {true_surf:.2f}"
                  + (f"; flagged {sorted(res.flagged)}" if res.flagged else ""), flush=True)
    for name in sets:
        report(rows[name], methods, name, getattr(args, "per_marker", False))


def real(args):
    """The real scans: surface RMS on the face every method puts on the scan's inside, and seconds."""
    tpl = load_template()
    face = testheads.face_mask(tpl)
    methods = [m for m in METHODS if m != "nricp_amberg" or not args.no_nricp]
    scans = pathlib.Path(os.environ.get("HEADADAPT_SCANS", ROOT.parent / "shared" / "scans"))
    files = sorted((ROOT / "headless_tests" / "data").glob("*_fdps.json"))
    print(f"\n== real scans ({scans}); surface RMS in the template's mm over the face vertices that every "
          f"method puts inside the scan; seconds ==")
    print(f"{'scan':14s} {'clk':>3s} {'verts':>5s} " + " | ".join(f"{m:^14s}" for m in methods))
    for path in files:
        meta = json.loads(path.read_text())
        scan = (ROOT / meta["scan"]).resolve()
        if not scan.is_file():
            scan = scans / pathlib.Path(meta["scan"]).relative_to("../shared/scans")
        if not scan.is_file():
            print(f"{path.stem}: scan {meta['scan']} not found, skipped")
            continue
        verts, tris = meshio.read_mesh(scan)[:2]
        clicks = meshio.read_landmarks(path)
        out, res = run_methods(tpl, verts, tris, clicks, nricp=not args.no_nricp)
        query = spatial.MeshQuery(verts, tris, backend=testheads.BACKEND)
        border = geometry.boundary_faces(np.asarray(tris))
        inside = face.copy()
        dist = {}
        for m, (v, _) in out.items():
            if v is None:
                continue
            _, f, d = query.closest_points(v)
            inside &= ~border[f]
            dist[m] = d * res.similarity.scale * 1000
        cells = [f"{np.sqrt(np.mean(dist[m][inside] ** 2)):5.2f} mm {out[m][1]:5.1f}s" if m in dist
                 else f"failed {out[m][1]:5.1f}s" for m in methods]
        print(f"{path.stem.replace('_fdps', ''):14s} {len(clicks):3d} {inside.sum():5d} " + " | ".join(
            f"{c:^14s}" for c in cells), flush=True)


def oracle(args):
    """The floor of any fit from a smooth map plus the scan's surface: maps that know the truth.
    affine  the best affine map of the template onto its true positions (least squares over the seen
            face), each vertex then moved to its closest point on the scan
    tps     a thin-plate RBF through every skin FDP at its exact true position (50-72 points, against
            the 8-11 clicks a person gives), then the closest point on the scan
    exact   HeadAdapt from the 11 clicks' exact true places (no disagreement between people)
    eyes    HeadAdapt from the 11 people's clicks but the four eye corners at their exact true places
            (their FDPs lie on the lid margin behind the lids; people click the nearest skin they see)
    level0  HeadAdapt from the 11 people's clicks with its level 0 (the whole-skin affine map) replaced
            by the affine map of the `affine` column: how much of the error level 0 decides
    What is left is tangential: where on a featureless cheek or forehead a vertex belongs, which the
    surface cannot say. Printed beside HeadAdapt's figure from 11 people's clicks."""
    from scipy.interpolate import RBFInterpolator

    tpl = load_template()
    face = testheads.face_mask(tpl)
    fdps = tpl.fdp_points()
    print("\n== the floor: maps that know the truth, projected onto the scan; corr RMS, mm of the true head ==")
    print(f"{'seed':>4s} {'affine':>7s} {'tps':>7s} {'fdps':>4s} {'exact(11)':>10s} {'eyes(11)':>9s} "
          f"{'level0(11)':>11s} {'headadapt(11)':>14s}")
    rows = []
    for seed in args.seeds:
        head = testheads.make_head(seed, style=args.style, **_head_args(args))
        seen = face & head.true_on_scan
        query = spatial.MeshQuery(head.scan_verts, head.scan_tris, backend=testheads.BACKEND)
        V, T = tpl.skin.verts, head.true_template
        X = np.c_[V, np.ones(len(V))]
        A = np.linalg.lstsq(X[seen], T[seen], rcond=None)[0]
        affine = query.closest_points(X @ A)[0]
        skin = [k for k in head.true_fdps if tpl.meta["fdps"][k]["part"] == "skin"]
        f = RBFInterpolator(np.array([fdps[k] for k in skin]), np.array([head.true_fdps[k] for k in skin])
                            - np.array([fdps[k] for k in skin]) @ A[:3] - A[3], kernel="thin_plate_spline")
        tps = query.closest_points(X @ A + f(V))[0]
        clicks = {k: head.fdp_clicks[k] for k in mpeg4.CLICKS_11 if k in head.fdp_clicks}
        exact = {k: head.true_fdps[k] for k in clicks}
        eyes = {k: head.true_fdps[k] if k in EYE_CORNERS else p for k, p in clicks.items()}
        people = adapt.adapt(tpl, head.scan_verts, head.scan_tris, clicks, markers=head.markers)
        fits = [adapt.adapt(tpl, head.scan_verts, head.scan_tris, c, markers=head.markers).verts_scan
                for c in (exact, eyes)]
        # the affine column's map (template -> scan frame) in the fit's calibrated frame, as level 0
        sim = people.similarity
        shift = sim.apply(A[3][None])[0]
        matrix = sim.apply(A[:3] + A[3]).T - shift[:, None]
        with _level0_as(level0.AffineMap(matrix, shift)):
            fits.append(adapt.adapt(tpl, head.scan_verts, head.scan_tris, clicks, markers=head.markers).verts_scan)
        r = [measure(tpl, head, v, seen, query)["corr_rms"] for v in (affine, tps, *fits, people.verts_scan)]
        rows.append(r)
        print(f"{seed:4d} {r[0]:7.2f} {r[1]:7.2f} {len(skin):4d} {r[2]:10.2f} {r[3]:9.2f} {r[4]:11.2f} {r[5]:14.2f}",
              flush=True)
    med = np.median(rows, axis=0)
    print(f"{'median':>4s} {med[0]:7.2f} {med[1]:7.2f} {'':4s} {med[2]:10.2f} {med[3]:9.2f} {med[4]:11.2f} {med[5]:14.2f}")


EYE_CORNERS = ("3.7", "3.8", "3.11", "3.12")


@contextlib.contextmanager
def _level0_as(affine):
    """Within: adapt's level 0 is the given affine map (the oracle column level0), not a fit."""
    fitted = level0.global_affine

    def given(fit, *_args, **_kwargs):
        fit.functions = [affine]
        return affine

    level0.global_affine = given
    try:
        yield
    finally:
        level0.global_affine = fitted


REGIONS = ("forehead", "brow_l", "brow_r", "nose", "cheek_l", "cheek_r", "upper_lip", "lower_lip", "chin_jaw")


def _along_by_region(tpl, head, verts_scan, normal, seen):
    """The error's part tangent to the true surface (normal: its vertex normals), RMS by REGIONS, mm."""
    e = (verts_scan - head.true_template) / head.similarity[0] * 1000
    e -= np.einsum("ij,ij->i", e, normal)[:, None] * normal
    return " ".join(f"{np.sqrt(np.mean(np.sum(e[seen & tpl.region_mask(r)] ** 2, axis=1))):9.2f}" for r in REGIONS)


def regions(args):
    """Per head and click set: the correspondence error ALONG the skin (its part tangent to the true
    surface), RMS by face region over the seen face, of HeadAdapt's map after level 0, 1, .. (the
    template's vertices moved by the levels so far, not yet put on the scan) and of nricp_amberg's."""
    tpl = load_template()
    face = testheads.face_mask(tpl)
    print(f"\n== error along the skin by region, mm of the true head, seen face ==\n{'seed':>4s} {'clk':>3s} "
          f"{'after':>9s} " + " ".join(f"{r:>9s}" for r in REGIONS))
    for seed in args.seeds:
        head = testheads.make_head(seed, style=args.style, **_head_args(args))
        seen = face & head.true_on_scan
        normal = geometry.vertex_normals(head.true_template, tpl.skin.tris)
        for name in args.clicks.split(","):
            clicks = set_clicks(tpl, head, name)
            out, res = run_methods(tpl, head.scan_verts, head.scan_tris, clicks, markers=head.markers,
                                   nricp=not args.no_nricp)
            moved = tpl.skin.verts.copy()
            for k, f in enumerate(res.functions):          # the levels so far, one added at a time
                moved += f(tpl.skin.verts)
                print(f"{seed:4d} {name:>3s} {'level ' + str(k):>9s} "
                      + _along_by_region(tpl, head, res.to_scan(moved), normal, seen))
            if out.get("nricp_amberg", (None,))[0] is not None:
                print(f"{seed:4d} {name:>3s} {'nricp':>9s} "
                      + _along_by_region(tpl, head, out["nricp_amberg"][0], normal, seen), flush=True)


def common(args):
    """How much of the correspondence error is the same on every head: per method and click set, each
    seen-face vertex's error (template frame, mm) averaged over the heads that see it (the field they
    share) against what is left of each head's own, RMS over the seen face; and the shared field by
    region (its RMS and mean vector). A field every method shares, and that heads whose truth is the
    template itself (--identity 0) do not have, is the heads' identities moving skin along itself the
    same way on average: what no surface shows."""
    tpl = load_template()
    face = testheads.face_mask(tpl)
    for name in args.clicks.split(","):
        errs, seen_all = {}, []
        for seed in args.seeds:
            head = testheads.make_head(seed, style=args.style, **_head_args(args))
            clicks = set_clicks(tpl, head, name)
            out, _res = run_methods(tpl, head.scan_verts, head.scan_tris, clicks, markers=head.markers,
                                    nricp=not args.no_nricp)
            scale, rot, _t = head.similarity
            for method in ("headadapt", "nricp_amberg"):
                if out.get(method, (None,))[0] is not None:
                    errs.setdefault(method, []).append((out[method][0] - head.true_template) @ rot / scale * 1000)
            seen_all.append(face & head.true_on_scan)
        seen = np.array(seen_all)
        count = seen.sum(axis=0)
        often = count >= max(3, len(args.seeds) // 2)          # the shared field where enough heads see it
        print(f"\n== {name} clicks, seeds {args.seeds[0]}-{args.seeds[-1]} ({len(args.seeds)} heads): the error every "
              f"head shares, mm of the true head, seen face, template frame (x left, y back, z up) ==")
        for method, per_head in errs.items():
            if len(per_head) != len(args.seeds):
                print(f"{method}: failed on a head, left out")
                continue
            e = np.array(per_head)
            shared = (e * seen[..., None]).sum(axis=0) / np.maximum(count, 1)[:, None]
            total = np.sqrt((np.sum(e ** 2, axis=2) * seen).sum() / seen.sum())
            own = np.sqrt((np.sum((e - shared) ** 2, axis=2) * seen).sum() / seen.sum())
            # the mean over n heads keeps about own / sqrt(n - 1) of their own errors: said beside it
            print(f"{method}: correspondence RMS {total:.2f}; shared by every head {np.sqrt(np.mean(np.sum(shared[often] ** 2, axis=1))):.2f} "
                  f"(of it about {own / np.sqrt(max(len(args.seeds) - 1, 1)):.2f} the heads' own, not averaged away); "
                  f"each head's own {own:.2f}")
            for region in REGIONS:
                sel = often & tpl.region_mask(region)
                vec = shared[sel].mean(axis=0)
                print(f"   {region:>9s} shared {np.sqrt(np.mean(np.sum(shared[sel] ** 2, axis=1))):5.2f}, on average "
                      f"({vec[0]:+.2f}, {vec[1]:+.2f}, {vec[2]:+.2f})")


def big():
    """Time HeadAdapt on a ~200k-vertex head (first, before the peers load the machine)."""
    tpl = load_template()
    head = testheads.make_head(7, style="scan", subdiv=3, decimate=0.95)
    times = []
    for _ in range(3):
        t0 = time.perf_counter()
        res = adapt.adapt(tpl, head.scan_verts, head.scan_tris, head.clicks_11)
        times.append(time.perf_counter() - t0)
    print(f"\nbig head: {len(head.scan_verts):,} vertices, {len(head.scan_tris):,} triangles, 11 clicks: whole "
          f"adaptation best {min(times):.2f} s, median {np.median(times):.2f} s of 3 (levels: "
          + ", ".join(f"{lv.level}:{lv.seconds:.2f}s" for lv in res.levels) + ")")


def _head_args(args):
    """make_head's head arguments asked for on the command line (--identity, --targets, --neck-tilt,
    --coarse, --noise-mm, --click-noise-mm), if any."""
    given = {"identity": getattr(args, "identity", None), "n_targets": getattr(args, "targets", None),
             "neck_tilt": getattr(args, "neck_tilt", None), "noise_mm": getattr(args, "noise_mm", None),
             "click_noise_mm": getattr(args, "click_noise_mm", None)}
    if getattr(args, "coarse", False):
        given.update(testheads.PHONE_SCAN)
    return {k: v for k, v in given.items() if v is not None}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=parse_seeds, default=list(REPORTING_SEEDS),
                        help="heads to run, e.g. 100-107 (the reporting set, default) or 0-9 (tuning)")
    parser.add_argument("--clicks", default="8,11",
                        help="click sets: 8, 11 or 8,11; 8+ or 11+: those and Suggest the Rest's proposals, all accepted")
    parser.add_argument("--style", choices=("scan", "legacy"), default="scan",
                        help="scan-like heads (default) or the legacy ones the suite's tests use, to compare")
    parser.add_argument("--real", action="store_true", help="the real scans in ../shared/scans instead")
    parser.add_argument("--big", action="store_true", help="also time a ~200k-vertex head")
    parser.add_argument("--oracle", action="store_true", help="the floor: maps that know the truth (no peers)")
    parser.add_argument("--regions", action="store_true",
                        help="where the error lies: along the skin by face region, after each level (and nricp's)")
    parser.add_argument("--no-nricp", action="store_true")
    parser.add_argument("--common", action="store_true",
                        help="how much of the error every head shares (the mean field over the heads), by region")
    parser.add_argument("--per-marker", action="store_true",
                        help="also each held-out FDP's error per method, and the marker RMS without it")
    parser.add_argument("--identity", type=float, default=None,
                        help="scale of the heads' identity morph (scan style; 0: the truth is the template itself)")
    parser.add_argument("--targets", type=int, default=None,
                        help="modifier targets per head (scan style; default 12-20 at random, 0: only race, "
                             "gender, age and one body target)")
    parser.add_argument("--neck-tilt", type=float, default=None,
                        help="scan style: each head turned on its neck, its nod's std in degrees (testheads."
                             "articulate_neck; default none)")
    parser.add_argument("--coarse", action="store_true",
                        help="scan style: a coarse scan, about 4,000 vertices (a phone's; default about 31,000)")
    parser.add_argument("--noise-mm", type=float, default=None,
                        help="scan style: the scan's noise, std along the normal in mm (default 0.1-0.5 at random)")
    parser.add_argument("--click-noise-mm", type=float, default=None,
                        help="scan style: people's disagreement, std per tangent axis in mm (default 2; along "
                             "the lid and lip lines 1.5x this, default 3)")
    args = parser.parse_args(argv)
    if args.big:
        big()
    if args.oracle:
        oracle(args)
    elif args.real:
        real(args)
    elif args.regions:
        regions(args)
    elif args.common:
        common(args)
    else:
        synthetic(args)


if __name__ == "__main__":
    main()
