"""Ray casts by Intel Embree (the embreex package: Embree 4's C BVH, float32, robust mode), for the
spatial backend "embree" of spatial.MeshQuery.

Embree finds each ray's nearest hit forward and, where asked, backward; the hit is then measured
again in float64 on the face Embree found (triangles.ray_choice, the numpy tree's own measure and
range test), so t, the point and the barycentrics are the numpy backend's numbers. They can differ
only in which face answers where a ray meets an edge or a vertex of the mesh (two faces, one point),
and where float32 misses a hit the numpy tree would find within ~1e-7 of the mesh's size of a
triangle's edge. A face Embree found that the float64 test rejects (an edge, the range's end) is
asked of the numpy tree instead. Closest points are the numpy tree's (embreex has no point query).
"""

from __future__ import annotations

import functools
import sys

import numpy as np

from .triangles import ray_choice


def inside_blender_executable() -> bool:
    """Whether this Python runs inside a Blender executable (not the bpy module, which has none). The
    executable links its own Embree (Cycles) and TBB into the process's global symbols, and
    embreex's calls reach those: Debian's Blender 3.4 crashed (segmentation fault) at the first ray
    with embreex 4.4 on its Python's path, where the same Python outside Blender and the bpy module
    (which loads its libraries privately) cast the rays right. bpy is not imported here."""
    bpy = sys.modules.get("bpy")
    origin = str(getattr(getattr(bpy, "__spec__", None), "origin", None) or "")
    module = origin.endswith((".so", ".pyd"))        # the bpy module: site-packages/bpy/__init__.so
    return bool(getattr(getattr(bpy, "app", None), "binary_path", "")) and not module


def available() -> bool:
    """Whether Embree can be used here: the embreex package importable (it is not bundled in the
    Blender extension), outside a Blender executable (inside_blender_executable)."""
    if inside_blender_executable():
        return False
    try:
        import embreex.rtcore_scene  # noqa: F401
    except ImportError:
        return False
    return True


class EmbreeRays:
    """Nearest ray hits on one triangle mesh by Embree, checked in float64 (see the module)."""

    def __init__(self, verts: np.ndarray, tris: np.ndarray, tree):
        if inside_blender_executable():
            raise RuntimeError("the embree spatial backend cannot run inside a Blender executable (Blender's "
                               "own Embree takes its calls and crashes); use the numpy backend")
        from embreex import rtcore_scene  # noqa: F401  (refused here, not at the first ray, if missing)

        self.verts, self.tris, self.tree = verts, tris, tree     # tree: the numpy TriangleBVH (fallback)
        # coordinates about the mesh's corner, so float32 keeps ~1e-7 of its size wherever it lies
        self.origin = verts.min(axis=0) if len(verts) else np.zeros(3)

    def build(self):
        """Build the scene now (a scan's, on the worker thread that prepares it); returns self."""
        _ = self.scene
        return self

    @functools.cached_property
    def scene(self):
        """The Embree scene of the mesh (None without triangles), made at the first ray: a query used
        for closest points only (the deformed skin's, each level) never builds it."""
        from embreex import rtcore_scene
        from embreex.mesh_construction import TriangleMesh

        if not len(self.tris):
            return None
        scene = rtcore_scene.EmbreeScene(robust=True)
        TriangleMesh(scene, (self.verts - self.origin).astype(np.float32), self.tris.astype(np.int32))
        # Embree builds its tree at the scene's first ray: one now, so a scan's tree is built where the
        # scan is prepared (a worker thread, beside the normals), not in level 0
        scene.run(np.zeros((1, 3), np.float32), np.ones((1, 3), np.float32), output=1)
        return scene

    def nearest(self, o, d, lo, hi):
        """(t (nan: none), face, bary) of each ray o + t d (d unit), the nearest hit by |t| with
        lo <= t <= hi, as TriangleBVH.ray_nearest answers (see the module for where they can differ)."""
        n = len(o)
        t_out, f_out, bary_out = np.full(n, np.nan), np.zeros(n, np.int64), np.zeros((n, 3))
        if not n or self.scene is None:
            return t_out, f_out, bary_out
        finite = np.isfinite(o).all(axis=1) & np.isfinite(d).all(axis=1)
        unsure = np.zeros(n, bool)
        for sign, reach in ((1.0, hi), (-1.0, -lo)):
            rays = np.flatnonzero(finite & (reach > 0))
            if not len(rays):
                continue
            # a little farther than asked (float32): the float64 range test below has the last word
            far = (reach[rays] + self.tree.pad).astype(np.float32)
            found = self.scene.run((o[rays] - self.origin).astype(np.float32), (sign * d[rays]).astype(np.float32),
                                   dists=far, output=1)["primID"]
            rays, face = rays[found >= 0], found[found >= 0].astype(np.int64)
            who, t, face, bary = ray_choice(o, d, lo, hi, rays, face, self.verts, self.tris)
            unsure[np.setdiff1d(rays, who, assume_unique=True)] = True
            nearer = ~(np.abs(t_out[who]) <= np.abs(t))           # nan (none yet) or farther
            who, t, face, bary = who[nearer], t[nearer], face[nearer], bary[nearer]
            t_out[who], f_out[who], bary_out[who] = t, face, bary
        if unsure.any():
            # the tree's exact answer where Embree's face failed the float64 test (at an edge, the end)
            k = np.flatnonzero(unsure)
            t_out[k], f_out[k], bary_out[k] = self.tree.ray_nearest(o[k], d[k], lo[k], hi[k])
        return t_out, f_out, bary_out
