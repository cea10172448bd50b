"""The calibrated scan as the levels query it (ScanSide): its spatial tree, normals, border and curvature.

The spatial side (the numpy backend's tree of every triangle, the median edge, the vertices' kd-tree)
is built on a worker thread (begun by calibrate before its winding check) while this one makes the
winding check, the normals and the border and the caller the curvature: numpy and scipy release the
GIL on large arrays, so on a 2-core machine a 1M-vertex scan is prepared in about the time of the
longer of the two. Whatever needs the tree waits for it there.
"""

from __future__ import annotations

import time

import numpy as np
from scipy.spatial import cKDTree

from .. import threads
from ..mesh import curvature, geometry, spatial

BORDER_WIDTH = 0.5     # a scan point this many median edges from the border is on it (metrics.distance_error)


def start_spatial(verts, tris, options):
    """The scan's spatial side (see ScanSide._ready): a future of the pool for the numpy and embree
    backends (made on a worker thread), made here for Blender's tree (backend "bvh": on the calling thread)."""
    make = lambda: _spatial_side(verts, tris, options.backend, options.dense_spacing)
    return make() if options.backend == "bvh" else threads.pool().submit(make)


def _spatial_side(verts, tris, backend, dense_spacing):
    """(the MeshQuery, the median edge, coarse, the vertices' kd-tree or None)."""
    query = spatial.MeshQuery(verts, tris, backend=backend)
    if backend == "embree":
        query.rays.build()                  # Embree's tree of the scan, built here on the worker too
    # the median of the triangles' first edges; the numpy tree has their lengths (the same numbers)
    tree = getattr(query, "tree", None)
    median_edge = tree.median_edge() if tree is not None else \
        float(np.median(np.linalg.norm(verts[tris[:, 0]] - verts[tris[:, 1]], axis=1)))
    coarse = median_edge > dense_spacing
    # the tangent planes (a dense scan's pairs, level 0's on any scan): the numpy tree's own kd-tree of
    # the vertices (its closest points' bound) when it holds them all, built once for both; else one
    # built alike (unbalanced, loose: see bvh.vertex_tree)
    vtree = tree.vertex_tree() if tree is not None else None
    if vtree is None or vtree.n != len(verts):
        vtree = cKDTree(verts, balanced_tree=False, compact_nodes=False)
    return query, median_edge, coarse, vtree


class FaceNormals:
    """The scan's unit face normals, indexed like an (k,3) array but made for the faces asked only (from
    the triangles' cross products; the same numbers as geometry.face_normals): a dense scan's levels
    look up a few thousand of its 2M triangles."""

    def __init__(self, fc):
        self.fc = fc

    def __getitem__(self, faces):
        return geometry.face_normals(None, None, self.fc[faces])

    def __len__(self):
        return len(self.fc)


class ScanSide:
    """The calibrated scan with its queries, normals, boundary and curvature (computed once)."""

    def __init__(self, verts, tris, options, fc=None, sums=None, spatial=None, border=None):
        """fc, sums: the triangles' geometry.face_cross and vertex_sums if the caller has them (calibrate
        does: the winding check needs them too); the normals come from them, computed once. spatial:
        start_spatial(verts, tris, options) if the caller began it (on these very triangles). border: the
        border's edges (e,2) if not the edges one triangle uses (a clustered scan's: its original's)."""
        t0 = time.perf_counter()
        self.verts, self.tris = verts, tris
        self.seconds = {"build": 0.0, "curvature": 0.0}        # the stages' report: this thread's seconds
        self._spatial = start_spatial(verts, tris, options) if spatial is None else spatial
        fc = geometry.face_cross(verts, tris) if fc is None else fc
        self.face_normals = FaceNormals(fc)
        self.vertex_normals = geometry.vertex_normals(verts, tris, geometry.vertex_sums(tris, fc, len(verts))
                                                      if sums is None else sums)
        self.border_edges = geometry.boundary_edges(tris) if border is None else border   # found once: faces, vertices, on_border
        on = np.zeros(len(verts), bool)
        on[self.border_edges.ravel()] = True
        self.boundary_faces = geometry.any_corner(on, tris)          # as geometry.boundary_faces
        self.boundary_verts = np.zeros(len(verts), bool)
        self.boundary_verts[tris[self.boundary_faces].ravel()] = True
        self._curv = None
        self._border = None
        self.seconds["build"] += time.perf_counter() - t0

    def _ready(self):
        """The spatial side, once built (the wait counts to the scan's preparation)."""
        if not isinstance(self._spatial, tuple):
            t0 = time.perf_counter()
            self._spatial = self._spatial.result()
            self.seconds["build"] += time.perf_counter() - t0
        return self._spatial

    query = property(lambda self: self._ready()[0], doc="The scan's MeshQuery (closest points, rays).")
    median_edge = property(lambda self: self._ready()[1], doc="The median of the triangles' first edges.")
    coarse = property(lambda self: self._ready()[2], doc="Whether the median edge exceeds dense_spacing.")
    vertex_tree = property(lambda self: self._ready()[3], doc="The vertices' kd-tree.")

    def nearest_on_plane(self, points, exact_if_coarse=True):
        """(point, normal, distance, on a hole's border) per query point for ICP pairs: on a dense scan
        the nearest scan vertex's tangent plane (a fast stand-in for the closest surface point: off
        by curvature x spacing^2 / 2, under 0.1 mm at 2.5 mm spacing where the skin curves no tighter
        than a 3 cm radius), else the closest point with its face's normal, on the border if that face
        touches it. At a tie (a point on a vertex or edge) the face is the spatial backend's choice
        (numpy's: spatial.py's rule); the report judges the point itself (metrics.distance_error), so
        its verdict does not hang on that choice.
        (Judging the pairs that way too, normal_at and on_border, moved the CT's pressed skull 1 mm
        off in depth at half an edge's border and its skin's p95 from 1.90 to 2.24 mm at one edge.)
        exact_if_coarse False: the tangent plane on any scan (level 0's affine map: off by curvature x
        spacing^2 / 2, 0.15 mm at 3 mm spacing, far below what an affine map fits; a tenth the time)."""
        if self.coarse and exact_if_coarse:
            q, f, d = self.query.closest_points(points)
            return q, self.face_normals[f], d, self.boundary_faces[f]
        _, i = self.vertex_tree.query(points, workers=-1)
        n = self.vertex_normals[i]
        q = points - np.einsum("ij,ij->i", points - self.verts[i], n)[:, None] * n
        return q, n, np.linalg.norm(q - points, axis=1), self.boundary_verts[i]

    def normal_at(self, points, faces):
        """The scan's normal (k,3) at points on faces: the vertex normals interpolated (barycentric), so
        a point on a vertex or edge gets one normal whichever face it was found on."""
        a, b, c = (self.verts[self.tris[faces, j]] for j in range(3))
        bary = np.clip(spatial.barycentric(points, a, b, c), 0.0, 1.0)
        return np.einsum("kj,kjd->kd", bary, self.vertex_normals[self.tris[faces]])

    def on_border(self, points, width=None):
        """Whether points on the scan (k,3) lie on a hole's (or the outer) border: within `width` (default
        BORDER_WIDTH x the median edge) of an edge only one triangle uses, measured from the point
        itself (exact closest points on those edges), whichever face it was found on."""
        if self._border is None:
            e = self.border_edges
            if len(e):
                longest = float(np.linalg.norm(self.verts[e[:, 0]] - self.verts[e[:, 1]], axis=1).max())
                self._border = (spatial.MeshQuery(self.verts, np.c_[e, e[:, 1]]), cKDTree(self.verts[np.unique(e)]),
                                longest)
            else:
                self._border = (None, None, 0.0)
        query, ends, longest = self._border
        out = np.zeros(len(points), bool)
        if query is None:
            return out
        width = BORDER_WIDTH * self.median_edge if width is None else width
        # a point on a border edge is within half its length of an end: only points that near a border
        # vertex can be within width of the border, and only those are measured exactly
        near = ends.query(points, distance_upper_bound=width + 0.5 * longest)[0] < np.inf
        out[near] = query.closest_points(points[near])[2] <= width
        return out

    def curvature(self, region=None):
        """(H, valid) per scan vertex; with a vertex mask, computed on the triangles inside it only
        (the cut's border counts as boundary, so its vertices are not valid)."""
        if self._curv is None:
            t0 = time.perf_counter()
            tris = self.tris if region is None else self.tris[geometry.all_corners(region, self.tris)]
            self._curv = curvature.mean_curvature(self.verts, tris, self.vertex_normals)
            self.seconds["curvature"] = time.perf_counter() - t0
        return self._curv
