"""The HeadAdapt method on numpy arrays (Chen & Prakash 2007): adapt/ (the adaptation), mesh/
(geometry, spatial queries, inside tests), skin/ (the skin simulation), anatomy (the transfer),
template, mpeg4 (the standard's tables), meshio, readers, fapfile (files), limits, tol, exceptions.

No module here imports bpy; only the spatial backend "bvh" (mesh.spatial.MeshQuery, chosen by the
caller) loads Blender's mathutils, when asked for.
"""

__version__ = "0.1.0"        # HeadAdapt's, as blender_manifest.toml gives it (report.json records it)
