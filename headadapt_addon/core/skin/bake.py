"""Bake expressions, visemes and FAPs into per-part vertex positions (shape keys), no bpy.

Skin keys come from the skin model's equilibrium for the key's recipe (core.drive); the
mandible, lower teeth and tongue follow the jaw controls; eyes and tongue take the rigid FAPs.
Each FAP key records how many FAP units (in the head's FAPUs) its value 1 stands for, so a .fap
file's values turn into key values. Template or adapted-head frame, metres.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np
from scipy.spatial.transform import Rotation

from .. import mpeg4
from ..anatomy import surface_point
from ..tol import TINY
from . import arkit, drive, parallel
from .build import build

JAW_FOLLOWERS = ("mandible", "teeth_lower", "tongue")


@dataclasses.dataclass
class BakedKey:
    """One shape key: its name, kind, {part: (n,3) positions} of the parts it moves, FAP units at 1."""
    name: str
    kind: str
    moved: dict
    fap_units: float | None = None


LID_MARGINS = {"3.1": "3.3", "3.3": "3.1", "3.2": "3.4", "3.4": "3.2"}


def _fap_units(fap, tpl, parts, moved, fapus):
    """FAP units (of the FAP's FAPU) that a key at value 1 moves its FDP along the FAP's direction.

    The lid FAPs count how much of the opening the key closes (IRISD is the opening / 1024): the
    opening is the margins' middles' distance along the FAP's direction (as seen from the front), and
    a key that closes it (the upper margin turned past the lower one, as a closed lid is: controls
    .LID_OVERLAP) stands for the standard's 1024 units (a .fap's full close keys 1)."""
    ref = tpl.meta["fdps"].get(fap.fdp)
    if ref is None or fap.direction is None or ref["part"] not in moved:
        return None
    tris = tpl.parts[ref["part"]].tris
    if fap.unit == "IRISD" and fap.fdp in LID_MARGINS:
        other = tpl.meta["fdps"][LID_MARGINS[fap.fdp]]
        gap0, gap1 = ((surface_point(x, tris, other) - surface_point(x, tris, ref)) @ np.asarray(fap.direction)
                      for x in (parts[ref["part"]], moved[ref["part"]]))
        return float(1024 * (gap0 - max(gap1, 0.0)) / gap0) if gap0 > TINY else None   # None: shut at rest
    d = surface_point(moved[ref["part"]], tris, ref) - surface_point(parts[ref["part"]], tris, ref)
    return float(d @ np.asarray(fap.direction) / fapus[fap.unit])


def bake(tpl, anatomy=None, kinds=("expression", "viseme", "fap", "arkit"), progress=None, helper=True):
    """Baked keys [BakedKey] for the template or an adapted Anatomy, and timings {build_s, per_key_s}.
    kinds: "expression", "viseme", "fap" (MPEG-4), "arkit" (ARKit's 52, core.skin.arkit). The skin's
    equilibria run on two cores where they can (parallel.equilibria; helper=False: on this one)."""
    jobs = [r for r in drive.shape_key_recipes() if r[1] in kinds]
    if "fap" in kinds:
        jobs += [(name, "fap_rigid", spec) for name, spec in drive.FAP_RIGID.items()]
    arkit_units = arkit.UNITS if "arkit" in kinds else ()
    # every key's skin first (the expensive part, on two cores), then the keys in their order
    skin_jobs = [(name, recipe) for name, kind, recipe in jobs if kind != "fap_rigid"]
    n_keys = len(skin_jobs)
    skin_jobs += [(unit, controls) for unit in arkit_units if (controls := arkit.recipe(tpl, unit))]
    recipes = [r for _, r in skin_jobs]
    t0 = time.perf_counter()
    proc = parallel.start(tpl.directory, recipes, anatomy) if helper else None    # builds while this builds
    try:
        model = build(tpl, anatomy)
    except BaseException:
        if proc:
            parallel.stop(proc)
        raise
    build_s = time.perf_counter() - t0
    parts = anatomy.parts if anatomy is not None else {k: p.verts for k, p in tpl.parts.items()}
    fapus = anatomy.fapus if anatomy is not None else tpl.meta["fapus"]
    t1 = time.perf_counter()
    n_jobs = len(jobs) + len(arkit_units)
    solved, helped = parallel.equilibria(model, recipes, proc, progress and (
        lambda f, i: progress(f * len(skin_jobs) / max(n_jobs, 1), skin_jobs[i][0])))
    names = [name for name, _ in skin_jobs]
    skins, unit_skins = dict(zip(names[:n_keys], solved[:n_keys])), dict(zip(names[n_keys:], solved[n_keys:]))
    keys = []
    for name, kind, recipe in jobs:
        if kind == "fap_rigid":
            part, how, axis, amount = recipe
            v = parts[part]
            centre = v.mean(axis=0)
            if how == "rotate":
                rot = Rotation.from_rotvec(amount * np.asarray(axis)).as_matrix()
                moved = {part: (v - centre) @ rot.T + centre}
            else:
                moved = {part: v + amount * np.asarray(axis)}
            fap = mpeg4.FAP_BY_NAME[name]
            units = (amount / mpeg4.AU_RAD) if how == "rotate" else _fap_units(fap, tpl, parts, moved, fapus)
            keys.append(BakedKey(name, "fap", moved, units))
        else:
            moved = {"skin": skins[name]}
            if recipe.keys() & {"jaw_open", "jaw_thrust", "jaw_shift"}:
                rot, t = model.mandible_transform(recipe)
                for part in JAW_FOLLOWERS:
                    moved[part] = model.on_jaw(parts[part], rot, t)
            units = None
            if kind == "fap":
                units = _fap_units(mpeg4.FAP_BY_NAME[name], tpl, parts, moved, fapus)
            keys.append(BakedKey(name, kind, moved, units))
    if arkit_units:
        for name, moved in arkit.bake_units(tpl, model, parts, JAW_FOLLOWERS, unit_skins):
            keys.append(BakedKey(name, "arkit", moved))
    if progress:
        progress(1.0, keys[-1].name if keys else "")
    per_key = (time.perf_counter() - t1) / max(n_jobs, 1)
    return keys, {"build_s": build_s, "per_key_s": per_key, "keys": len(keys), "helper_keys": helped, "model": model}
