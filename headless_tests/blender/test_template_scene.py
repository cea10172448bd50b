"""The template loads into Blender (bpy module) as objects under one root."""
import numpy as np


def test_template_loads_as_objects_under_one_root(clean_scene, tpl):
    import bpy

    from headadapt_addon.blender import bridge, scene

    root = scene.add_template(tpl)
    objs = scene.template_objects(root)
    for part in ("skin", "cranium", "mandible", "eye_l", "eye_r", "teeth_upper", "teeth_lower", "tongue"):
        obj = objs[part]
        assert obj.type == "MESH", part
        verts, tris = bridge.mesh_arrays(obj)
        # world positions equal the asset's, whatever parenting (the mandible hangs on the jaw pivot)
        np.testing.assert_allclose(verts, tpl.parts[part].verts, atol=1e-6, err_msg=part)
        assert len(tris) == len(tpl.parts[part].tris), part
    assert all(o in root.children_recursive for o in bpy.context.scene.objects if o is not root)

    fdps = [o for o in root.children_recursive if "headadapt_fdp" in o]
    assert sorted(o["headadapt_fdp"] for o in fdps) == sorted(tpl.meta["fdps"])
    points = tpl.fdp_points()
    for o in fdps:
        np.testing.assert_allclose(o.matrix_world.translation, points[o["headadapt_fdp"]], atol=1e-6)
        assert o["headadapt_label"] == tpl.meta["fdps"][o["headadapt_fdp"]]["label"]
    assert len([o for o in root.children_recursive if "headadapt_marker" in o]) == len(tpl.meta["markers"])

    muscles = {o["headadapt_muscle"]: o for o in root.children_recursive if "headadapt_muscle" in o}
    assert len(muscles) == len(tpl.meta["muscles"]) + len(tpl.meta["sphincters"])
    for m in tpl.meta["muscles"]:
        spline = muscles[m["name"]].data.splines[0]
        ends = np.array([p.co[:3] for p in spline.points])
        np.testing.assert_allclose(ends, [tpl.surface_point(m["attachment"]), tpl.surface_point(m["insertion"])],
                                   atol=1e-6)

    skin = objs["skin"]
    regions = np.empty(len(skin.data.vertices), dtype=np.int32)
    skin.data.attributes["ha_region"].data.foreach_get("value", regions)
    np.testing.assert_array_equal(regions, tpl.region)
    assert len(skin.vertex_groups) == len(tpl.region_names)


def test_rotating_the_jaw_pivot_opens_the_mouth(clean_scene, tpl):
    import bpy

    from headadapt_addon.blender import bridge, scene

    root = scene.add_template(tpl)
    objs = scene.template_objects(root)
    chin = tpl.parts["mandible"].verts[:, 2].argmin()
    objs["jaw_pivot"].rotation_euler[0] = np.radians(15)
    bpy.context.view_layer.update()
    verts, _ = bridge.mesh_arrays(objs["mandible"])
    assert verts[chin, 2] < tpl.parts["mandible"].verts[chin, 2] - 0.005  # the chin drops by > 5 mm
    pivot = np.asarray(tpl.meta["jaw"]["pivot"])
    np.testing.assert_allclose(np.linalg.norm(verts - pivot, axis=1),
                               np.linalg.norm(tpl.parts["mandible"].verts - pivot, axis=1), atol=1e-6)
