"""Render the Landmarks panel's reference picture: the template's face from the front with the 8 clicks
(where a person clicks them) as dots and their ids: assets/reference/clicks8.png.

    ./ha python tools/render_reference.py
"""
import pathlib
import sys

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tools"))

import bpy  # noqa: E402
import render_pictures as rp  # noqa: E402

from headadapt_addon.blender import scene  # noqa: E402
from headadapt_addon.core import mpeg4  # noqa: E402
from headadapt_addon.core.template import load_template  # noqa: E402

OUT = ROOT / "assets" / "reference" / "clicks8.png"
SIZE = (360, 400)
SIZE_TEXT = 0.012          # m: legible at the panel's size of the picture


def main():
    tpl = load_template()
    bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
    sc = bpy.context.scene
    rp._setup(sc)
    sc.render.resolution_x, sc.render.resolution_y = SIZE
    sc.world.color = (0.2, 0.2, 0.2)
    root = scene.add_template(tpl)
    for o in root.children_recursive:
        o.hide_render = o.type != "MESH" or o.get("headadapt_part") in ("cranium", "mandible")
    labels = bpy.data.collections.new("labels")
    sc.collection.children.link(labels)
    clicks = {k: p for k, p in tpl.click_points().items() if k in mpeg4.CLICKS_8}
    rp._dots(list(clicks.values()), labels, (1.0, 0.85, 0.1, 1), radius=0.0032, name="clicks")
    v = tpl.skin.verts
    y_front = v[:, 1].min() - 0.01
    for k, p in clicks.items():        # ids beside the dots, outward from the face's midline
        width = SIZE_TEXT * 0.6 * len(k)
        if k in ("3.8", "3.11"):       # the inner eye corners: below, toward the nose
            x, z = p[0] - width / 2 + (0.004 if p[0] > 0 else -0.004), p[2] - 0.016
        elif p[0] > 0.002 or k in ("9.3", "2.10"):
            x, z = p[0] + 0.007, p[2] - 0.003
        else:
            x, z = p[0] - 0.006 - width, p[2] - 0.003
        rp._label(k, [x, y_front, z], labels, size=SIZE_TEXT, colour=(0.0, 0.05, 0.4, 1))
    face = v[:, 2] > 0.62
    centre = np.array([0.0, v[face, 1].mean(), 0.5 * (v[face, 2].min() + v[face, 2].max()) - 0.015])
    rp._camera(sc, centre, (0, 1, 0), 0.19)
    OUT.parent.mkdir(parents=True, exist_ok=True)
    rp._render(OUT)
    print(f"{OUT}: {OUT.stat().st_size // 1024} kB")


if __name__ == "__main__":
    main()
