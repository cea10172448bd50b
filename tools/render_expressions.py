"""Render the expressions contact sheet (Workbench, headless): docs/img/expressions_sheet.jpg.

    ./ha python tools/render_expressions.py [--out docs/img] [--seeds 7,3,11]

Three generated heads (tools/testheads.py seeds), each adapted from its clicks, its anatomy transferred
and its keys baked on its own anatomy (core.skin.bake): one row per head, one column per key at 1:
neutral, the six MPEG-4 expressions, a blink (both eyes), and eight ARKit keys. Front view, skin and
eyes; the key's name above each column.
"""
import argparse
import pathlib
import sys
import tempfile

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import bpy  # noqa: E402

from headadapt_addon.blender import bridge  # noqa: E402
from headadapt_addon.core import adapt, anatomy, mpeg4  # noqa: E402
from headadapt_addon.core.skin import bake, drive  # noqa: E402
from headadapt_addon.core.template import load_template  # noqa: E402
from tools import render_pictures, testheads  # noqa: E402

ARKIT_SHOWN = ("jawOpen", "mouthSmileLeft", "mouthPucker", "cheekSquintLeft", "browInnerUp", "cheekPuff",
               "mouthFrownLeft", "jawLeft")
CELL = (190, 220)
ORTHO = 0.215                   # the view's height, m
SHOWN_PARTS = ("skin", "eye_l", "eye_r", "teeth_upper", "teeth_lower")


def columns(tpl, ana):
    """[(label, {part: positions})] of one head: neutral, the six expressions, a blink, the ARKit keys."""
    keys, timing = bake.bake(tpl, ana, kinds=("expression", "arkit"))
    model = timing["model"]
    by_name = {k.name: k for k in keys}
    cols = [("neutral", {})]
    cols += [(name, by_name[name].moved) for name in mpeg4.EXPRESSIONS]
    cols.append(("blink", {"skin": model.equilibrium(drive.BLINK["eyeBlinkLeft"] | drive.BLINK["eyeBlinkRight"])}))
    cols += [(name, by_name[name].moved) for name in ARKIT_SHOWN]
    return cols


def _grid(paths, n_cols, out):
    images = [bpy.data.images.load(str(p)) for p in paths]
    w, h = images[0].size
    rows = []
    for r in range(len(images) // n_cols):
        arrays = []
        for img in images[r * n_cols:(r + 1) * n_cols]:
            px = np.empty(w * h * 4, dtype=np.float32)
            img.pixels.foreach_get(px)
            arrays.append(px.reshape(h, w, 4))
        rows.append(np.concatenate(arrays, axis=1))
    combined = np.concatenate(rows[::-1], axis=0)            # Blender's pixels start at the bottom row
    img = bpy.data.images.new("sheet", combined.shape[1], combined.shape[0], alpha=False)
    img.pixels.foreach_set(combined.ravel())
    settings = bpy.context.scene.render.image_settings
    img.save_render(str(out.with_suffix(".png")), scene=bpy.context.scene)     # lossless, to look at
    settings.file_format, settings.quality = "JPEG", 72
    img.save_render(str(out), scene=bpy.context.scene)
    settings.file_format = "PNG"


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default=str(ROOT / "docs" / "img"))
    parser.add_argument("--seeds", default="7,3,11")
    args = parser.parse_args(argv)
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    tmp = pathlib.Path(tempfile.mkdtemp(prefix="headadapt-sheet-"))
    tpl = load_template()
    bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
    sc = bpy.context.scene
    render_pictures._setup(sc)
    sc.render.resolution_x, sc.render.resolution_y = CELL
    colours = {"skin": (0.86, 0.68, 0.58, 1), "eye_l": (0.95, 0.95, 0.97, 1), "eye_r": (0.95, 0.95, 0.97, 1),
               "teeth_upper": (0.97, 0.96, 0.9, 1), "teeth_lower": (0.97, 0.96, 0.9, 1)}
    paths, n_cols = [], 0
    for seed in map(int, args.seeds.split(",")):
        head = testheads.make_head(seed)
        ana = anatomy.transfer(tpl, adapt.adapt(tpl, head.scan_verts, head.scan_tris, head.fdp_clicks))
        objs = {}
        for part in SHOWN_PARTS:
            me = bridge.new_mesh(f"{seed} {part}", ana.parts[part], tpl.parts[part].tris)
            mat = bpy.data.materials.new(f"{seed} {part}")
            mat.diffuse_color = colours[part]
            me.materials.append(mat)
            me.shade_smooth()
            objs[part] = bpy.data.objects.new(me.name, me)
            sc.collection.objects.link(objs[part])
        v = ana.parts["skin"]
        nose, chin = ana.fdps["9.3"], ana.fdps["2.1"]
        centre = np.array([nose[0], v[:, 1].mean(), 0.5 * (nose[2] + chin[2]) + 0.025])
        cam = render_pictures._camera(sc, centre, (0, 1, 0), ORTHO)
        cols = columns(tpl, ana)
        n_cols = len(cols)
        half = 0.5 * ORTHO
        label = render_pictures._label("", centre + [-0.93 * half * CELL[0] / CELL[1], -0.2, 0.86 * half],
                                       sc.collection, size=0.0105)
        for i, (name, moved) in enumerate(cols):
            for part, obj in objs.items():
                bridge.set_vertex_positions(obj.data, moved.get(part, ana.parts[part]))
            label.data.body = f"{name}  (seed {seed})" if i == 0 else name
            paths.append(tmp / f"{seed}_{i:02d}.png")
            render_pictures._render(paths[-1])
        for obj in (*objs.values(), cam, label):
            bpy.data.objects.remove(obj)
        print(f"seed {seed}: {n_cols} keys rendered", flush=True)
    _grid(paths, n_cols, out / "expressions_sheet.jpg")
    (out / "expressions_sheet.png").replace(tmp / "expressions_sheet.png")
    print(f"lossless copy: {tmp / 'expressions_sheet.png'}")
    print(f"{out / 'expressions_sheet.jpg'}: {(out / 'expressions_sheet.jpg').stat().st_size // 1024} kB")


if __name__ == "__main__":
    main(sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else None)
