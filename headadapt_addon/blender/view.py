"""How a head and its scan look in the viewport, without setup: the heat map shown (Solid shading by
the colour attribute) with a legend in mm beside the head, the scan as wire so result and scan are
told apart, the anatomy helpers (FDP and marker empties, muscle curves) hidden until asked for and
drawn without relationship lines."""

import bpy
import numpy as np

from . import bridge

HEAT_ATTRIBUTE = "HeadAdapt distance"
HEAT_LIMIT_MM = 3.0                 # red at and beyond (blendout.heat_colours)
LEGEND_MM = (0.0, 1.5, 3.0)         # the legend's labelled values
# helper kind -> the headadapt_part tags of its objects (the group empty and its children)
HELPERS = {"fdps": ("fdps", "fdp"), "markers": ("markers", "marker"), "muscles": ("muscles", "muscle", "sphincter")}


def heat_colours(dist_mm, limit_mm=HEAT_LIMIT_MM):
    """RGBA (n,4): blue at 0 mm through green and yellow to red at limit_mm and beyond; grey where NaN (no scan)."""
    dist_mm = np.asarray(dist_mm, dtype=float)
    t = np.clip(np.nan_to_num(dist_mm, nan=0.0) / limit_mm, 0.0, 1.0)
    r = np.clip(2 * t, 0, 1)
    g = np.clip(2 - 2 * t, 0, 1) * np.clip(2 * t + 0.3, 0, 1)
    b = np.clip(1 - 2 * t, 0, 1)
    rgba = np.c_[r, g, b, np.ones_like(t)]
    rgba[np.isnan(dist_mm)] = (0.6, 0.6, 0.6, 1.0)
    return rgba


def hide(obj, hidden=True):
    """Hide an object in the viewport (the eye: still evaluated, so its world matrix stays right) and
    in renders."""
    obj.hide_set(hidden)
    obj.hide_render = hidden


def set_helpers_visible(root, kind, visible):
    """Show or hide one kind of helper (HELPERS) under a head root, in the viewport and in renders."""
    parts = HELPERS[kind]
    for obj in root.children_recursive:
        if obj.get("headadapt_part") in parts:
            hide(obj, not visible)


def helpers_visible(root, kind):
    """True when the helpers of a kind under root are shown."""
    return any(not o.hide_get() for o in root.children_recursive if o.get("headadapt_part") in HELPERS[kind])


def view3d_spaces(screens):
    """The 3D viewport spaces of the given screens."""
    return [space for screen in screens for area in screen.areas if area.type == "VIEW_3D"
            for space in area.spaces if space.type == "VIEW_3D"]


def show_heat_map(screens, on=True):
    """Solid shading by the active colour attribute (the skin's heat map) in the screens' 3D views, or
    by material again; relationship lines off (helpers would draw dashed lines to their group empty)."""
    for space in view3d_spaces(screens):
        space.shading.type = "SOLID"
        space.shading.color_type = "VERTEX" if on else "MATERIAL"
        space.overlay.show_relationship_lines = False
        space.overlay.wireframe_opacity = 0.35         # a scan drawn as wire veils the heat map lightly


def heat_map_shown(screens):
    spaces = view3d_spaces(screens)
    return bool(spaces) and all(s.shading.type == "SOLID" and s.shading.color_type == "VERTEX" for s in spaces)


def show_scan_as_wire(scan, on=True):
    """The scan drawn as wire (the result inside it stays visible and distinguishable) or solid."""
    scan.display_type = "WIRE" if on else "TEXTURED"


def add_heat_legend(root, tpl, collection):
    """A colour bar with the heat map's colours and text labels in mm, standing beside the head (root
    frame: the template's, so it scales and turns with the head); parented to root."""
    skin = tpl.skin.verts
    lo, hi = skin.min(axis=0), skin.max(axis=0)
    width = 0.012
    x0 = lo[0] - 0.03 - width               # the viewer's left of the face (the sidebar is on the right)
    z0, z1 = lo[2] + 0.06, hi[2] - 0.04
    y = lo[1] + 0.5 * (hi[1] - lo[1])
    steps = 24
    mm = np.linspace(0.0, HEAT_LIMIT_MM, steps + 1)
    z = z0 + (z1 - z0) * mm / HEAT_LIMIT_MM
    verts = np.array([(x, y, zz) for zz in z for x in (x0, x0 + width)])
    quads = np.array([(2 * i, 2 * i + 1, 2 * i + 3, 2 * i + 2) for i in range(steps)])
    bar = bpy.data.objects.new("HeadAdapt heat legend", bridge.new_mesh("HeadAdapt heat legend", verts, quads))
    bridge.set_point_colors(bar.data, HEAT_ATTRIBUTE, heat_colours(np.repeat(mm, 2)))
    objs = [(bar, "legend")]
    labels = [(f"{v:g} mm" + ("+" if v >= HEAT_LIMIT_MM else ""), x0 - 0.004, z0 + (z1 - z0) * v / HEAT_LIMIT_MM,
               "RIGHT") for v in LEGEND_MM] + [("distance to scan", x0 + width / 2, z1 + 0.015, "CENTER")]
    for text, x, zz, align in labels:
        curve = bpy.data.curves.new(f"HeadAdapt legend {text}", "FONT")
        curve.body, curve.size, curve.align_x, curve.align_y = text, 0.009, align, "CENTER"
        label = bpy.data.objects.new(curve.name, curve)
        label.location = (x, y, zz)
        label.rotation_euler = (np.pi / 2, 0.0, 0.0)        # in the XZ plane, read from the front (-Y)
        objs.append((label, "legend_label"))
    for obj, part in objs:
        collection.objects.link(obj)
        obj.parent = root
        obj["headadapt_part"] = part
    return bar
