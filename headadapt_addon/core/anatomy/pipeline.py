"""transfer(tpl, result): the template's anatomy carried onto an adapted head, step by step."""

from __future__ import annotations

import numpy as np

from .. import mpeg4
from ..adapt.options import AdaptResult
from ..mesh import geometry, winding
from ..template import Template
from .bone import clear_visible_skin, keep_inside, relax_cleared, unrelax_under_skin
from .lift import lift_visible_skin
from .model import Anatomy
from .rigid import EYE_SCALE, RIGID_FDPS, rigid_from_fdps, seat_orbits, surface_point


def transfer(tpl: Template, result: AdaptResult) -> Anatomy:
    """Carry the template's anatomy onto the adapted head of an AdaptResult (template frame, m)."""
    parts = {"skin": result.verts}
    tris = {name: part.tris for name, part in tpl.parts.items()}
    tpl_fdps = tpl.fdp_points()
    fdps = {}
    for name, ref in tpl.meta["fdps"].items():
        if ref["part"] == "skin":
            fdps[name] = surface_point(parts["skin"], tris["skin"], ref)
    rigid = {}
    for name, (x_pair, y_pair, ref) in RIGID_FDPS.items():
        # centre through the map (it carries the socket around the part), scale and turn by eq 25
        centre = result.map_points(tpl.parts[name].verts.mean(axis=0)[None])[0]
        sim = rigid_from_fdps(tpl.parts[name].verts, tpl_fdps, fdps, x_pair, y_pair, ref, centre,
                              scale=EYE_SCALE if name.startswith("eye") else None)
        rigid[name] = sim
        parts[name] = sim.apply(tpl.parts[name].verts)
    # the skull through the final map (all last-level FPs)
    mapped = {name: result.map_points(tpl.parts[name].verts) for name in ("cranium", "mandible")}
    parts["skin"], offsets = seat_orbits(tpl, result.scan, parts, rigid, mapped)
    # the inside tests of the rest: the adapted skin's built once, the skull's refit as it moves
    skin_inside = winding.FastWinding(parts["skin"], tris["skin"])
    pressed = {}
    for name in mapped:
        pressed[name] = keep_inside(tpl, tpl.parts[name].verts, mapped[name] + offsets[name], parts["skin"],
                                    skin_inside=skin_inside, backend=result.backend)
        # each point goes under its own skin point: neighbours pressed different ways fold the
        # bone (orbit floors, cheeks); relax the folds, giving back as much of the press as can be
        relaxed = geometry.unfold(tpl.parts[name].verts, pressed[name], tris[name])[0]
        lifted = skin_inside(relaxed) < 0.5    # out of the skin again
        relaxed[lifted] = pressed[name][lifted]
        parts[name] = relaxed
    # the skull's: clear_visible_skin moves it a step (1 mm) at a time; its grid keeps for a step, and
    # the terms of its 536 caps at the visible skin for the next ask (most caps have not moved)
    bone_inside = winding.FastWinding(np.vstack([parts["cranium"], parts["mandible"]]), tpl.skull_tris, slack=0.001,
                                      remember=True)
    parts["cranium"], parts["mandible"] = clear_visible_skin(tpl, parts["skin"], parts["cranium"], parts["mandible"],
                                                             skin_inside=skin_inside, bone_inside=bone_inside)
    parts["cranium"], parts["mandible"] = unrelax_under_skin(tpl, parts, pressed, skin_inside=skin_inside,
                                                              bone_inside=bone_inside)
    parts["cranium"], parts["mandible"] = relax_cleared(tpl, parts, skin_inside, bone_inside)
    parts["skin"] = lift_visible_skin(tpl, parts["skin"], parts["cranium"], parts["mandible"],
                                      bone_inside=bone_inside)[0]
    for name, ref in tpl.meta["fdps"].items():
        if ref["part"] != "skin":
            fdps[name] = surface_point(parts[ref["part"]], tris[ref["part"]], ref)

    muscles = []
    for m in tpl.meta["muscles"]:
        muscles.append({"name": m["name"], "regions": m["regions"],
                        "attachment": surface_point(parts[m["attachment"]["part"]], tris[m["attachment"]["part"]],
                                                    m["attachment"]),
                        "insertion": surface_point(parts[m["insertion"]["part"]], tris[m["insertion"]["part"]],
                                                   m["insertion"])})
    sphincters = []
    for sph in tpl.meta["sphincters"]:
        centre = result.map_points(np.asarray(sph["centre"])[None])[0]
        axes = []
        for axis, (a, b) in zip(sph["axes"], sph["scale_pairs"]):
            ratio = np.linalg.norm(fdps[a] - fdps[b]) / np.linalg.norm(tpl_fdps[a] - tpl_fdps[b])
            axes.append(np.asarray(axis) * ratio)
        sphincters.append({"name": sph["name"], "centre": centre, "axes": axes, "regions": sph["regions"]})
    pivot = result.map_points(np.asarray(tpl.meta["jaw"]["pivot"])[None])[0]
    return Anatomy(parts=parts, muscles=muscles, sphincters=sphincters, fdps=fdps,
                   fapus=mpeg4.measure_fapus(fdps), jaw_pivot=pivot, rigid=rigid)
