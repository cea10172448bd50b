"""The template adapted onto a real head CT, measured against that person's own skull.

The VTK "headsq" CT (../shared/scans/headsq_ct, BSD-3) gives the skin AND the bone of one real
person. We click 15 FDPs on its skin (headless_tests/data/headsq_ct_fdps.json), adapt, transfer
the anatomy, and compare the transferred skull and eyes with the CT's bone. Shared by
headless_tests/test_real_scans.py and headless_tests/bench/bench_ct.py.
"""
import dataclasses
import pathlib
import sys
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from headadapt_addon.core import adapt, anatomy, meshio  # noqa: E402
from headadapt_addon.core.mesh.spatial import MeshQuery  # noqa: E402

CLICKS = ROOT / "headless_tests" / "data" / "headsq_ct_fdps.json"


@dataclasses.dataclass
class CTCase:
    """One adaptation onto the CT; every array in the template frame (metres) unless named."""
    tpl: object
    result: object                 # AdaptResult
    anatomy: object                # Anatomy
    seconds: float                 # adapt + transfer
    ct_bone: np.ndarray            # (n,3) CT bone surface, template frame
    ct_bone_tris: np.ndarray
    ct_skin: np.ndarray            # (n,3) CT skin surface, template frame
    ct_skin_tris: np.ndarray
    mm: float                      # template metres -> the CT's millimetres

    def bone_query(self):
        """Closest-point queries on the CT's bone (template frame)."""
        return MeshQuery(self.ct_bone, self.ct_bone_tris, backend="numpy")

    def scanned_bone(self):
        """(k,) indices into cranium+mandible of bone points under visible skin the scan covers."""
        tpl = self.tpl
        idx = np.r_[tpl.bone_skin_index["cranium"], tpl.bone_skin_index["mandible"]]
        unseen = tpl.hidden[idx]
        return np.flatnonzero(np.isfinite(self.result.distances[idx]) & ~unseen)

    def bone_distance_mm(self, bone):
        """Distance (k,) in the CT's mm from the scanned bone points of `bone` (cranium+mandible
        stacked, template frame) to the CT's bone surface."""
        return self.bone_query().closest_points(bone[self.scanned_bone()])[2] * self.mm

    def transferred_bone(self):
        """Cranium and mandible after transfer, stacked (template frame)."""
        return np.vstack([self.anatomy.parts["cranium"], self.anatomy.parts["mandible"]])

    def template_bone(self):
        """The template's own cranium and mandible (calibration only, no transfer), stacked."""
        return np.vstack([self.tpl.parts["cranium"].verts, self.tpl.parts["mandible"].verts])


def load_ct(scans_dir):
    """(skin verts, skin tris, bone verts, bone tris, FDP clicks) of the headsq CT, its frame, mm."""
    folder = pathlib.Path(scans_dir) / "headsq_ct"
    skin_v, skin_t = meshio.read_mesh(folder / "headsq_skin.obj")[:2]
    bone_v, bone_t = meshio.read_mesh(folder / "headsq_bone.obj")[:2]
    return skin_v, skin_t, bone_v, bone_t, meshio.read_landmarks(CLICKS)


def run(tpl, scans_dir):
    """Adapt the template onto the CT skin from the clicks and transfer the anatomy: a CTCase."""
    skin_v, skin_t, bone_v, bone_t, clicks = load_ct(scans_dir)
    t0 = time.perf_counter()
    result = adapt.adapt(tpl, skin_v, skin_t, clicks)
    ana = anatomy.transfer(tpl, result)
    seconds = time.perf_counter() - t0
    sim = result.similarity
    return CTCase(tpl=tpl, result=result, anatomy=ana, seconds=seconds,
                  ct_bone=sim.apply(bone_v), ct_bone_tris=bone_t,
                  ct_skin=sim.apply(skin_v), ct_skin_tris=skin_t, mm=1.0 / sim.scale)


def tissue_depths(case):
    """[(landmark, table mm, CT mm, transferred skull mm)] at the template's depth landmarks that
    the CT covers: along the adapted skin's inward normal, from the CT's skin point nearest the
    landmark to the CT's bone, and from the adapted skin to the transferred skull (NaN: no hit
    within 40 mm, e.g. through the thin nasal bones the CT misses)."""
    from headadapt_addon.core.mesh.geometry import vertex_normals

    tpl, res = case.tpl, case.result
    normals = vertex_normals(res.verts, tpl.skin.tris)
    skin_q = MeshQuery(case.ct_skin, case.ct_skin_tris, backend="numpy")
    ct_q = case.bone_query()
    ours_q = MeshQuery(case.transferred_bone(), tpl.skull_tris, backend="numpy")
    reach = 40.0 / case.mm
    rows = []
    for lm in tpl.meta["tissue_depths"]:
        i = lm["vertex"]
        if not np.isfinite(res.distances[i]):
            continue
        p, inward = res.verts[i][None], -normals[i][None]
        ct_skin_pt = skin_q.closest_points(p)[0]
        ct = ct_q.ray_cast(ct_skin_pt, inward, reach, both_ways=False).t[0] * case.mm
        ours = ours_q.ray_cast(p, inward, reach, both_ways=False).t[0] * case.mm
        rows.append((lm["name"], lm["table_mm"], ct, ours))
    return rows
