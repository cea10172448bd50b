"""The bundled template head: load assets/template/ (template.npz + template.json) into arrays.

Frame: Blender's, metres, Z up, the face looks toward -Y, the person's left is +X.
Format: assets/template/README.md. Never imports bpy.
"""

import dataclasses
import functools
import hashlib
import json
import pathlib

import numpy as np

from .exceptions import FileFormatError

TEMPLATE_DIR = pathlib.Path(__file__).resolve().parents[2] / "assets" / "template"
RIGID_PARTS = ("eye_l", "eye_r", "teeth_upper", "teeth_lower", "tongue")
BONES = ("cranium", "mandible")
# skin no range scanner sees: the mouth bag and the eye sockets' lining (a scan never has it)
HIDDEN_REGIONS = ("mouth_interior", "eye_socket_l", "eye_socket_r")


def quads_to_tris(quads: np.ndarray) -> np.ndarray:
    """Split quads (k,4) into triangles (2k,3): quad q gives triangles 2q (0,1,2) and 2q+1 (0,2,3)."""
    quads = np.asarray(quads)
    return np.stack([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]], axis=1).reshape(-1, 3)


def content_hash(arrays, meta):
    """SHA-256 over the arrays (sorted by name, dtype, shape, bytes) and the canonical JSON."""
    h = hashlib.sha256()
    for name in sorted(arrays):
        a = np.ascontiguousarray(arrays[name])
        h.update(f"{name}|{a.dtype.str}|{a.shape}|".encode())
        h.update(a.tobytes())
    meta = {k: v for k, v in meta.items() if k != "content_sha256"}
    h.update(json.dumps(meta, sort_keys=True, separators=(",", ":")).encode())
    return h.hexdigest()


@dataclasses.dataclass(frozen=True)
class PartMesh:
    """One mesh of the template: verts (n,3) metres, quads (k,4), tris (2k,3), hm08 index (n,)."""
    name: str
    verts: np.ndarray
    quads: np.ndarray
    hm08: np.ndarray

    @functools.cached_property
    def tris(self):
        """Triangles (2k,3) of the quads, in the order face indices refer to (computed once)."""
        return quads_to_tris(self.quads)


@dataclasses.dataclass(frozen=True)
class Template:
    """The anatomical template: meshes, landmarks, regions, muscles, FAPUs (template frame, m)."""
    parts: dict          # name -> PartMesh: skin, cranium, mandible, eye_l/r, teeth_upper/lower, tongue
    region: np.ndarray   # (n_skin,) region index per skin vertex
    region_names: tuple
    region_weights: np.ndarray
    skin_mirror: np.ndarray   # (n_skin,) index of each skin vertex's left/right partner
    meta: dict           # the whole template.json
    bone_skin_index: dict = dataclasses.field(default_factory=dict)   # bone -> (n_bone,) skin vertex it was offset from
    arkit: dict = dataclasses.field(default_factory=dict)   # arkit.json: the ARKit units' fitted activations
    directory: str | None = None   # the folder it was loaded from (a bake's helper process loads it there)

    @property
    def skin(self):
        """The skin mesh."""
        return self.parts["skin"]

    @property
    def skull_tris(self):
        """Triangles (k,3) of the whole skull, for its vertices stacked cranium then mandible."""
        return np.vstack([self.parts["cranium"].tris, self.parts["mandible"].tris + len(self.parts["cranium"].verts)])

    def surface_point(self, ref):
        """Point (3,) of a {"part", "face", "bary"} reference on its part, metres."""
        part = self.parts[ref["part"]]
        tri = part.tris[ref["face"]]
        return np.asarray(ref["bary"]) @ part.verts[tri]

    def fdp_points(self):
        """{FDP id: (3,) point} of every FDP on the template, metres."""
        return {k: self.surface_point(r) for k, r in self.meta["fdps"].items()}

    def click_points(self):
        """{FDP id: (3,) point} where a person clicks each FDP on a picture of the face, metres: the
        FDP itself, except where the anatomy puts it out of sight or off the corner people see
        (meta "clicks": the eye corners at the canthi, lid centres on the lids, lip corners at
        the commissure; assets/template/README.md)."""
        clicks = self.meta.get("clicks", {})
        return {k: self.surface_point(clicks.get(k, r)) for k, r in self.meta["fdps"].items()}

    def marker_points(self):
        """{marker name: (3,) point} of the held-out markers, metres."""
        return {k: self.surface_point(r) for k, r in self.meta["markers"].items()}

    def region_mask(self, *names):
        """Boolean mask (n_skin,) of the skin vertices in any of the named regions."""
        return np.isin(self.region, [self.region_names.index(r) for r in names])

    @functools.cached_property
    def derived(self):
        """Scratch space for data made from the template alone (the fit's level bases: see
        adapt.fit.template_side), kept for the life of this template object."""
        return {}

    @functools.cached_property
    def hidden(self):
        """Boolean mask (n_skin,) of the skin no scanner sees (HIDDEN_REGIONS)."""
        return self.region_mask(*HIDDEN_REGIONS)


@functools.cache
def bundled_template() -> Template:
    """The template shipped in assets/template, loaded once per process (it is never changed)."""
    return load_template()


def load_template(directory: str | pathlib.Path | None = None) -> Template:
    """Load the template from assets/template (or `directory`); FileFormatError names the file."""
    directory = pathlib.Path(directory or TEMPLATE_DIR)
    npz_path, json_path = directory / "template.npz", directory / "template.json"
    try:
        meta = json.loads(json_path.read_text())
        with np.load(npz_path) as data:
            arrays = {k: data[k] for k in data.files}
    except (OSError, ValueError) as exc:
        raise FileFormatError(f"cannot read the template in {directory}: {exc}") from exc
    parts = {}
    for name in ("skin", *BONES, *RIGID_PARTS):
        try:
            parts[name] = PartMesh(name, arrays[f"{name}_verts"], arrays[f"{name}_quads"],
                                   arrays[f"{name}_hm08"])
        except KeyError as exc:
            raise FileFormatError(f"{npz_path} has no array {exc.args[0]!r}") from exc
    regions = meta["regions"]
    arkit_path = directory / "arkit.json"          # fitted on the built template by tools/fit_arkit.py
    try:
        arkit = json.loads(arkit_path.read_text()) if arkit_path.exists() else {}
    except (OSError, ValueError) as exc:
        raise FileFormatError(f"cannot read {arkit_path}: {exc}") from exc
    return Template(parts=parts, region=arrays["skin_region"],
                    region_names=tuple(r["name"] for r in regions),
                    region_weights=np.array([r["weight"] for r in regions]),
                    skin_mirror=arrays["skin_mirror"], meta=meta,
                    bone_skin_index={b: arrays[f"{b}_skin_index"] for b in BONES if f"{b}_skin_index" in arrays},
                    arkit=arkit, directory=str(directory))
