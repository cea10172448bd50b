"""Render the README pictures of the template (Workbench, headless): docs/img/*.jpg.

    ./ha python tools/render_pictures.py [--out docs/img]

template_front_side.jpg: front and side views, FDPs as blue dots with their ids.
template_anatomy.jpg: see-through skin over the skull, mandible, eyes, teeth, tongue and muscles.
demo_result.jpg: the bundled sample scan beside the template adapted onto it.
real_ct.jpg: the template adapted onto the real headsq CT, with its transferred skull, beside the
CT's own skin and bone (front, then side; needs ../shared/scans or $HEADADAPT_SCANS).
bench_head.jpg: a benchmark head (bench adapt's scan-like head, --bench-seed, 8 clicks): its scan,
HeadAdapt's fit and nricp_amberg's, each vertex coloured by its distance from its true place
(blue 0, red 10 mm and more; grey where the scan does not show it), front, then side.
--only NAME renders that picture alone (demo, ct, bench).
"""
import argparse
import math
import pathlib
import sys
import tempfile

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import bpy  # noqa: E402

from headadapt_addon.blender import scene  # noqa: E402
from headadapt_addon.core.template import load_template  # noqa: E402

VIEW_SIZE = (720, 820)


def _setup(engine_scene):
    r = engine_scene.render
    r.engine = "BLENDER_WORKBENCH"
    r.resolution_x, r.resolution_y = VIEW_SIZE
    r.resolution_percentage = 100
    r.film_transparent = False
    r.image_settings.file_format = "PNG"
    r.image_settings.color_mode = "RGB"
    r.image_settings.compression = 100
    sh = engine_scene.display.shading
    sh.light = "STUDIO"
    sh.color_type = "MATERIAL"
    sh.show_cavity = True
    sh.cavity_type = "WORLD"
    engine_scene.world = engine_scene.world or bpy.data.worlds.new("World")
    engine_scene.world.color = (1, 1, 1)
    engine_scene.view_settings.view_transform = "Standard"


def _camera(engine_scene, centre, direction, ortho_scale):
    cam = bpy.data.cameras.new("cam")
    cam.type = "ORTHO"
    cam.ortho_scale = ortho_scale
    obj = bpy.data.objects.new("cam", cam)
    engine_scene.collection.objects.link(obj)
    d = np.asarray(direction, float)
    obj.location = np.asarray(centre) - 1.0 * d
    obj.rotation_euler = (math.pi / 2, 0, math.atan2(-d[0], d[1]))
    engine_scene.camera = obj
    return obj


def _label(text, location, collection, size=0.0052, colour=(0.0, 0.1, 0.55, 1), facing=(0, -1, 0)):
    data = bpy.data.curves.new(f"label {text}", "FONT")
    data.body = text
    data.size = size
    data.align_x = "LEFT"
    mat = bpy.data.materials.new(f"label {text}")
    mat.diffuse_color = colour
    data.materials.append(mat)
    obj = bpy.data.objects.new(f"label {text}", data)
    obj.location = location
    obj.rotation_euler = (math.pi / 2, 0, math.atan2(-facing[0], -facing[1]) if facing[1] else
                          (math.pi / 2 if facing[0] > 0 else -math.pi / 2))
    collection.objects.link(obj)
    return obj


def _dots(points, collection, colour, radius=0.0012, name="dots"):
    mesh = bpy.data.meshes.new(name)
    import bmesh
    bm = bmesh.new()
    for p in points:
        bmesh.ops.create_uvsphere(bm, u_segments=10, v_segments=6, radius=radius,
                                  matrix=__import__("mathutils").Matrix.Translation(p))
    bm.to_mesh(mesh)
    bm.free()
    mat = bpy.data.materials.new(name)
    mat.diffuse_color = colour
    mesh.materials.append(mat)
    obj = bpy.data.objects.new(name, mesh)
    collection.objects.link(obj)
    return obj


def _render(path):
    bpy.context.scene.render.filepath = str(path)
    bpy.ops.render.render(write_still=True)


def _side_by_side(paths, out):
    images = [bpy.data.images.load(str(p)) for p in paths]
    w, h = images[0].size
    arrays = []
    for img in images:
        px = np.empty(w * h * 4, dtype=np.float32)
        img.pixels.foreach_get(px)
        arrays.append(px.reshape(h, w, 4))
    combined = np.concatenate(arrays, axis=1)
    img = bpy.data.images.new("combined", w * len(paths), h, alpha=False)
    img.pixels.foreach_set(combined.ravel())
    settings = bpy.context.scene.render.image_settings
    settings.file_format, settings.quality = "JPEG", 82
    img.save_render(str(out), scene=bpy.context.scene)
    settings.file_format = "PNG"


def render_demo(out, tmp):
    """Sample scan (grey) beside the adapted head coloured by its distance to the scan."""
    from headadapt_addon.blender import blendout, bridge
    from headadapt_addon.core import meshio
    from headadapt_addon.core.adapt import adapt

    tpl = load_template()
    sample = ROOT / "assets" / "sample_scan"
    verts, tris = meshio.read_mesh(sample / "scan.ply")
    result = adapt(tpl, verts, tris, meshio.read_landmarks(sample / "landmarks.json"))
    bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
    sc = bpy.context.scene
    _setup(sc)
    # both shown in the template frame, side by side
    scan_t = result.similarity.apply(verts)
    scan_obj = bpy.data.objects.new("scan", bridge.new_mesh("scan", scan_t - [0.1, 0, 0], tris))
    sc.collection.objects.link(scan_obj)
    root = blendout.build_result_objects(tpl, result, sc)
    root.matrix_world = __import__("mathutils").Matrix.Translation((0.1, 0, 0))
    for o in root.children_recursive:
        o.hide_render = o.get("headadapt_part") != "skin"
    sc.display.shading.color_type = "VERTEX"
    v = tpl.skin.verts
    centre = np.array([0.0, v[:, 1].mean(), 0.5 * (v[:, 2].min() + v[:, 2].max()) + 0.02])
    _camera(sc, centre, (0, 1, 0), 0.42)
    sc.render.resolution_x, sc.render.resolution_y = 1200, 640
    _render(tmp / "demo.png")
    _side_by_side([tmp / "demo.png"], out / "demo_result.jpg")
    return out / "demo_result.jpg"


def render_ct(out, tmp):
    """The template adapted onto the real headsq CT (see-through skin, transferred skull) beside the
    CT's own skin and bone, front and side, same frame and camera. Needs ../shared/scans."""
    import os

    from headadapt_addon.blender import bridge
    from tools import realct

    scans = pathlib.Path(os.environ.get("HEADADAPT_SCANS", ROOT.parent / "shared" / "scans"))
    if not (scans / "headsq_ct").is_dir():
        print(f"no CT at {scans / 'headsq_ct'}: real_ct.jpg not rendered")
        return None
    tpl = load_template()
    case = realct.run(tpl, scans)
    bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
    sc = bpy.context.scene
    _setup(sc)
    sc.display.shading.show_cavity = False
    sc.render.resolution_x, sc.render.resolution_y = 520, 600

    def mesh(name, verts, tris, colour):
        mat = bpy.data.materials.new(name)
        mat.diffuse_color = colour
        if colour[3] < 1:
            mat.surface_render_method = "BLENDED"
        me = bridge.new_mesh(name, verts, tris)
        me.materials.append(mat)
        obj = bpy.data.objects.new(name, me)
        sc.collection.objects.link(obj)
        return obj

    bone_t = tpl.skull_tris
    skin_colour, bone_colour = (0.86, 0.68, 0.58, 0.22), (0.93, 0.9, 0.8, 1.0)
    ours = [mesh("adapted skin", case.anatomy.parts["skin"], tpl.skin.tris, skin_colour),
            mesh("transferred skull", case.transferred_bone(), bone_t, bone_colour),
            *(mesh(e, case.anatomy.parts[e], tpl.parts[e].tris, (0.75, 0.8, 0.9, 1.0)) for e in ("eye_l", "eye_r"))]
    real = [mesh("CT skin", case.ct_skin, case.ct_skin_tris, skin_colour),
            mesh("CT bone", case.ct_bone, case.ct_bone_tris, bone_colour)]
    lo, hi = case.ct_skin.min(axis=0), case.ct_skin.max(axis=0)
    centre = np.array([0.0, 0.5 * (lo[1] + hi[1]), 0.5 * (lo[2] + hi[2])])
    paths = []
    for view, direction in (("front", (0, 1, 0)), ("side", (-1, 0, 0))):
        for label, shown in (("ours", ours), ("ct", real)):
            for o in ours + real:
                o.hide_render = o not in shown
            _camera(sc, centre, direction, 0.24)
            paths.append(tmp / f"ct_{view}_{label}.png")
            _render(paths[-1])
    _side_by_side(paths, out / "real_ct.jpg")
    return out / "real_ct.jpg"


BENCH_LIMIT_MM = 10.0


def render_bench(out, tmp, seed=106):
    """A scan-like benchmark head (bench adapt's, 8 clicks): its scan (grey), HeadAdapt's fit and
    nricp_amberg's from the same clicks and calibration, coloured by each vertex's distance from its
    true place (the correspondence error, mm of the true head; grey off the seen skin)."""
    from headadapt_addon.blender import bridge
    from headadapt_addon.blender.view import heat_colours
    from headadapt_addon.core import adapt
    from headadapt_addon.core.mesh import spatial
    from tools import testheads

    sys.path.insert(0, str(ROOT / "headless_tests" / "bench"))
    import bench_adapt

    tpl = load_template()
    head = testheads.make_head(seed, style="scan")
    clicks = {k: head.fdp_clicks[k] for k in bench_adapt.CLICK_SETS["8"] if k in head.fdp_clicks}
    result = adapt.adapt(tpl, head.scan_verts, head.scan_tris, clicks, markers=head.markers)
    nricp, _ = bench_adapt.peer_nricp(tpl, head.scan_verts, head.scan_tris, clicks, result.similarity)
    sim = result.similarity
    truth = sim.apply(head.true_template)
    seen = head.true_on_scan
    bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
    sc = bpy.context.scene
    _setup(sc)
    sc.display.shading.color_type = "VERTEX"
    sc.render.resolution_x, sc.render.resolution_y = 440, 520
    scale = head.similarity[0]

    def mesh(name, verts, tris, colours=None):
        me = bridge.new_mesh(name, verts, tris)
        if colours is not None:
            bridge.set_point_colors(me, "error", colours)
        obj = bpy.data.objects.new(name, me)
        sc.collection.objects.link(obj)
        return obj

    figures = {}
    query = spatial.MeshQuery(head.scan_verts, head.scan_tris, backend=testheads.BACKEND)
    objs = [mesh("scan", sim.apply(head.scan_verts), head.scan_tris,
                 np.tile([0.75, 0.75, 0.75, 1.0], (len(head.scan_verts), 1)))]
    for name, verts in (("headadapt", result.verts_scan), ("nricp_amberg", nricp)):
        figures[name] = bench_adapt.measure(tpl, head, verts, seen & testheads.face_mask(tpl), query)["corr_rms"]
        err = np.linalg.norm(verts - head.true_template, axis=1) / scale * 1000
        objs.append(mesh(name, sim.apply(verts), tpl.skin.tris, heat_colours(np.where(seen, err, np.nan), BENCH_LIMIT_MM)))
    v = truth[seen]
    centre = np.array([0.0, v[:, 1].mean(), np.percentile(v[:, 2], 60)])
    paths = []
    for view, direction in (("front", (0, 1, 0)), ("side", (-1, 0, 0))):
        for obj in objs:
            for o in objs:
                o.hide_render = o is not obj
            _camera(sc, centre, direction, 0.30)
            paths.append(tmp / f"bench_{view}_{obj.name}.png")
            _render(paths[-1])
    _side_by_side(paths, out / "bench_head.jpg")
    print(f"bench head {seed}, 8 clicks: correspondence RMS on the seen face "
          + ", ".join(f"{k} {v:.2f} mm" for k, v in figures.items()))
    return out / "bench_head.jpg"


def main(argv=None):
    """Render the pictures into --out; prints their paths and sizes."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default=str(ROOT / "docs" / "img"))
    parser.add_argument("--only", choices=("demo", "ct", "bench"), help="render this picture alone")
    parser.add_argument("--bench-seed", type=int, default=106, help="bench_head.jpg's head (bench adapt's seed)")
    args = parser.parse_args(argv)
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    tpl = load_template()
    tmp = pathlib.Path(tempfile.mkdtemp(prefix="headadapt-render-"))
    if args.only:
        path = {"demo": lambda: render_demo(out, tmp), "ct": lambda: render_ct(out, tmp),
                "bench": lambda: render_bench(out, tmp, args.bench_seed)}[args.only]()
        print(f"{path}: {path.stat().st_size // 1024} kB" if path else "nothing rendered")
        return

    bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
    sc = bpy.context.scene
    _setup(sc)
    root = scene.add_template(tpl)
    objs = scene.template_objects(root)
    v = tpl.skin.verts
    face = v[:, 2] > 0.60
    centre = np.array([0.0, v[face, 1].mean(), 0.5 * (v[face, 2].min() + v[face, 2].max()) - 0.005])
    labels = bpy.data.collections.new("labels")
    sc.collection.children.link(labels)
    pts = tpl.fdp_points()

    # 1. front + side with FDP ids
    for o in root.children_recursive:
        o.hide_render = o.type != "MESH" or o.get("headadapt_part") in ("cranium", "mandible")
    skin_pts = {k: p for k, p in pts.items() if tpl.meta["fdps"][k]["part"] == "skin"}
    front = {k: p for k, p in skin_pts.items() if p[1] < centre[1] + 0.02 and not k.startswith("10.")}
    side = {k: p for k, p in skin_pts.items() if p[0] > -0.005 and (k.startswith(("10.", "11.", "2.1", "9.3", "2.13")) or p[0] > 0.04)}
    _dots(list(skin_pts.values()), labels, (0.1, 0.35, 1.0, 1), name="fdp dots")
    # labels on a plane in front of the head (orthographic views: depth does not move them)
    y_front, x_side = v[:, 1].min() - 0.01, v[:, 0].max() + 0.01
    front_labels = [_label(k, [p[0] + 0.0012, y_front, p[2] - 0.0008], labels) for k, p in front.items()]
    side_labels = [_label(k, [x_side, p[1] - 0.0012, p[2] - 0.0008], labels, facing=(1, 0, 0))
                   for k, p in side.items()]
    for o in side_labels:
        o.hide_render = True
    _camera(sc, centre, (0, 1, 0), 0.285)
    _render(tmp / "front.png")
    for o in front_labels:
        o.hide_render = True
    for o in side_labels:
        o.hide_render = False
    _camera(sc, centre + [0, 0.03, 0], (-1, 0, 0), 0.285)
    _render(tmp / "side.png")
    _side_by_side([tmp / "front.png", tmp / "side.png"], out / "template_front_side.jpg")

    # 2. anatomy: see-through skin, bones, eyes, teeth, tongue, muscles
    for o in list(labels.objects):
        o.hide_render = True
    for o in root.children_recursive:
        o.hide_render = o.get("headadapt_part") in ("fdp", "marker")
    skin_mat = objs["skin"].data.materials[0]
    skin_mat.diffuse_color = (0.86, 0.68, 0.58, 0.18)
    skin_mat.surface_render_method = "BLENDED"
    sc.display.shading.show_cavity = False
    _camera(sc, centre, (0, 1, 0), 0.285)
    _render(tmp / "a_front.png")
    _camera(sc, centre + [0, 0.03, 0], (-1, 0, 0), 0.285)
    _render(tmp / "a_side.png")
    _side_by_side([tmp / "a_front.png", tmp / "a_side.png"], out / "template_anatomy.jpg")
    # 3. the demo: the bundled sample scan, and the template adapted onto it (distance heat map)
    render_demo(out, tmp)
    # 4. the real CT: our adapted head and transferred skull beside the person's own
    render_ct(out, tmp)
    # 5. a benchmark head: its scan, our fit and nricp_amberg's, coloured by correspondence error
    render_bench(out, tmp, args.bench_seed)
    for name in ("template_front_side.jpg", "template_anatomy.jpg", "demo_result.jpg", "real_ct.jpg", "bench_head.jpg"):
        if not (out / name).exists():
            continue
        print(f"{out / name}: {(out / name).stat().st_size // 1024} kB")


if __name__ == "__main__":
    main(sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else None)
