"""bridge.mesh_arrays reads a mesh as Blender's own loop triangles say, whichever way it reads it."""
import numpy as np

from headadapt_addon.batch import SAMPLE_DIR
from headadapt_addon.core import meshio


def _object(name, verts, faces):
    import bpy

    from headadapt_addon.blender import bridge

    obj = bpy.data.objects.new(name, bridge.new_mesh(name, verts, faces))
    bpy.context.scene.collection.objects.link(obj)
    return obj


def _loop_triangles(mesh):
    """The reference: vertex positions through MeshVertex.co, triangles through loop_triangles."""
    co = np.empty(len(mesh.vertices) * 3, np.float32)
    mesh.vertices.foreach_get("co", co)
    mesh.calc_loop_triangles()
    tris = np.empty(len(mesh.loop_triangles) * 3, np.int32)
    mesh.loop_triangles.foreach_get("vertices", tris)
    return co.reshape(-1, 3).astype(np.float64), tris.reshape(-1, 3).astype(np.int64)


def test_triangles_quads_and_a_modifiers_result_read_as_their_loop_triangles():
    import bpy

    from headadapt_addon.blender import bridge

    v, t = meshio.read_mesh(SAMPLE_DIR / "scan.ply")
    scan = _object("scan", v, t)
    verts, tris = bridge.mesh_arrays(scan, world=False)
    ref_v, ref_t = _loop_triangles(scan.data)
    assert len(tris) == len(t) > 60000
    assert np.array_equal(verts, ref_v) and np.array_equal(tris, ref_t)
    assert np.array_equal(tris, t)                       # in the file's order, each its corners' order

    # quads: four corners a face, so its loop triangles are read
    grid = np.array([[x, y, 0.0] for y in range(3) for x in range(3)])
    quads = np.array([[0, 1, 4, 3], [1, 2, 5, 4], [3, 4, 7, 6]])
    mixed = _object("mixed", grid, quads)
    verts, tris = bridge.mesh_arrays(mixed, world=False)
    ref_v, ref_t = _loop_triangles(mixed.data)
    assert tris.shape == (6, 3) and np.array_equal(tris, ref_t) and np.array_equal(verts, ref_v)

    # a modifier's result (the depsgraph's mesh, its quads triangulated) is read the same way; the
    # object is not changed
    sub = mixed.modifiers.new("sub", "SUBSURF")
    sub.levels = 2
    mixed.modifiers.new("tri", "TRIANGULATE")
    deps = bpy.context.evaluated_depsgraph_get()
    verts, tris = bridge.mesh_arrays(mixed, world=False, depsgraph=deps)
    evaluated = mixed.evaluated_get(deps)
    ref_v, ref_t = _loop_triangles(evaluated.to_mesh())
    evaluated.to_mesh_clear()
    assert len(tris) == 96 and np.array_equal(verts, ref_v) and np.array_equal(tris, ref_t)
    assert len(mixed.data.vertices) == 9 and len(mixed.data.polygons) == 3


def test_a_scan_in_edit_mode_is_read_as_edited():
    """An artist trims the scan in Edit Mode and presses Calibrate without leaving it: the buttons read
    the trimmed scan (before, the mesh as it was when Edit Mode began)."""
    import bmesh
    import bpy

    from headadapt_addon.blender import bridge

    v, t = meshio.read_mesh(SAMPLE_DIR / "scan.ply")
    scan = _object("scan", v, t)
    bpy.context.view_layer.objects.active = scan
    scan.select_set(True)
    bpy.ops.object.mode_set(mode="EDIT")
    try:
        bm = bmesh.from_edit_mesh(scan.data)
        cut = np.percentile(v[:, 2], 80)
        bmesh.ops.delete(bm, geom=[p for p in bm.verts if p.co.z > cut], context="VERTS")
        bmesh.update_edit_mesh(scan.data)
        kept = len(bm.verts)
        verts, tris = bridge.mesh_arrays(scan, world=False)
        assert len(verts) == kept < 0.85 * len(v) and verts[:, 2].max() <= cut and tris.max() < kept
        assert scan.mode == "EDIT"                            # still editing
    finally:
        bpy.ops.object.mode_set(mode="OBJECT")
