"""Benchmark: HeadAdapt vs two peers on generated heads (same inputs, same process). Prints figures.

    ./ha bench adapt [--heads 5] [--big]

Peers: scipy's RBFInterpolator (thin-plate) on the FDPs alone, and trimesh's nricp_amberg with
the same FDPs as landmarks. All three start from the same calibration (ours), since neither peer
calibrates. Errors in mm: true correspondence on the face (RMS, 95th percentile), surface distance
RMS over covered vertices, FDP error RMS; and seconds.
"""
import argparse
import pathlib
import sys
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from headadapt_addon.core import adapt, calibration, geometry, spatial  # noqa: E402
from headadapt_addon.core.template import load_template  # noqa: E402
from tools import testheads  # noqa: E402

FACE = ("forehead", "brow_l", "brow_r", "eyelid_l", "eyelid_r", "nose", "cheek_l", "cheek_r",
        "upper_lip", "lower_lip", "chin_jaw")


def measure(tpl, head, verts_scan, face):
    """Figures (mm) of an adapted skin given in the scan frame."""
    s = head.similarity[0]
    d = np.linalg.norm(verts_scan - head.true_template, axis=1) / s * 1000
    q = spatial.MeshQuery(head.scan_verts, head.scan_tris)
    _, f, dist = q.closest_points(verts_scan)
    covered = (dist / s < 0.005) & ~geometry.boundary_faces(head.scan_tris)[f] & (tpl.region_weights[tpl.region] > 0)
    fdp = []
    for name, ref in tpl.meta["fdps"].items():
        if ref["part"] == "skin" and name in head.true_fdps:
            fdp.append(np.linalg.norm(np.asarray(ref["bary"]) @ verts_scan[tpl.skin.tris[ref["face"]]]
                                      - head.true_fdps[name]) / s * 1000)
    return {"corr_rms": np.sqrt(np.mean(d[face] ** 2)), "corr_p95": np.percentile(d[face], 95),
            "surf_rms": np.sqrt(np.mean((dist[covered] / s * 1000) ** 2)), "fdp_rms": np.sqrt(np.mean(np.square(fdp)))}


def peer_rbf(tpl, head):
    from scipy.interpolate import RBFInterpolator

    t0 = time.perf_counter()
    tp = {k: p for k, p in tpl.fdp_points().items() if k in head.fdp_clicks}
    sim, _ = calibration.calibrate(head.fdp_clicks, tp)
    names = list(tp)
    P = np.array([tp[k] for k in names])
    Q = sim.apply(np.array([head.fdp_clicks[k] for k in names]))
    f = RBFInterpolator(P, Q - P, kernel="thin_plate_spline")
    v = tpl.skin.verts + f(tpl.skin.verts)
    return sim.inverse().apply(v), time.perf_counter() - t0


def peer_nricp(tpl, head):
    import trimesh
    from trimesh.registration import nricp_amberg

    t0 = time.perf_counter()
    tp = {k: p for k, p in tpl.fdp_points().items() if k in head.fdp_clicks and tpl.meta["fdps"][k]["part"] == "skin"}
    sim, _ = calibration.calibrate(head.fdp_clicks, tp)
    names = list(tp)
    src = trimesh.Trimesh(tpl.skin.verts, tpl.skin.tris, process=False)
    tgt = trimesh.Trimesh(sim.apply(head.scan_verts), head.scan_tris, process=False)
    faces = np.array([tpl.meta["fdps"][k]["face"] for k in names])
    bary = np.array([tpl.meta["fdps"][k]["bary"] for k in names])
    target = sim.apply(np.array([head.fdp_clicks[k] for k in names]))
    v = nricp_amberg(src, tgt, source_landmarks=(faces, bary), target_positions=target, distance_threshold=0.02)
    return sim.inverse().apply(v), time.perf_counter() - t0


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--heads", type=int, default=5)
    parser.add_argument("--big", action="store_true", help="also time a ~200k-vertex head")
    parser.add_argument("--no-nricp", action="store_true")
    args = parser.parse_args()
    tpl = load_template()
    face = np.isin(tpl.region, [tpl.region_names.index(r) for r in FACE])
    if args.big:   # timed first, before the peers load the machine
        head = testheads.make_head(7, subdiv=3, decimate=0.95)
        times = []
        for _ in range(3):
            t0 = time.perf_counter()
            res = adapt.adapt(tpl, head.scan_verts, head.scan_tris, head.fdp_clicks)
            times.append(time.perf_counter() - t0)
        print(f"\nbig head: {len(head.scan_verts):,} vertices, {len(head.scan_tris):,} triangles: whole adaptation "
              f"best {min(times):.2f} s, median {np.median(times):.2f} s of 3 (levels: "
              + ", ".join(f"{lv.level}:{lv.seconds:.2f}s" for lv in res.levels) + ")")

    rows = {"headadapt": [], "rbf_fdps": [], "nricp_amberg": []}
    for seed in range(100, 100 + args.heads):
        head = testheads.make_head(seed)
        t0 = time.perf_counter()
        res = adapt.adapt(tpl, head.scan_verts, head.scan_tris, head.fdp_clicks)
        ours = time.perf_counter() - t0
        rows["headadapt"].append({**measure(tpl, head, res.verts_scan, face), "seconds": ours})
        v, sec = peer_rbf(tpl, head)
        rows["rbf_fdps"].append({**measure(tpl, head, v, face), "seconds": sec})
        if not args.no_nricp:
            v, sec = peer_nricp(tpl, head)
            rows["nricp_amberg"].append({**measure(tpl, head, v, face), "seconds": sec})
        print(f"head {seed}: {len(head.scan_verts):,} vertices; " + "; ".join(
            f"{k} corr {r[-1]['corr_rms']:.2f} mm surf {r[-1]['surf_rms']:.2f} mm {r[-1]['seconds']:.2f} s"
            for k, r in rows.items() if r), flush=True)
    print(f"\n{'method':14s} {'corr RMS':>9s} {'corr p95':>9s} {'surf RMS':>9s} {'FDP RMS':>8s} {'seconds':>8s}   (mm, mean over {args.heads} heads)")
    for k, r in rows.items():
        if r:
            m = {key: np.mean([x[key] for x in r]) for key in r[0]}
            print(f"{k:14s} {m['corr_rms']:9.3f} {m['corr_p95']:9.3f} {m['surf_rms']:9.3f} {m['fdp_rms']:8.3f} {m['seconds']:8.2f}")
    if rows["nricp_amberg"]:
        print(f"speed ratio nricp_amberg / headadapt: "
              f"{np.mean([x['seconds'] for x in rows['nricp_amberg']]) / np.mean([x['seconds'] for x in rows['headadapt']]):.1f}x")


if __name__ == "__main__":
    main()
