"""Blender side of the expressions: read a head's anatomy from its objects, write shape keys, the
preview action and .fap keyframes. The simulation itself is core.skin (build, bake)."""

import json

import bpy
import numpy as np

from ..core import mpeg4
from ..core.anatomy import Anatomy
from ..core.exceptions import HeadAdaptError
from ..core.skin.drive import FAP_HEAD
from . import bridge, scene

JAW_CHILDREN = ("mandible", "teeth_lower")     # meshes stored relative to the jaw pivot empty
PREVIEW_FRAMES = 30                            # frames per expression in the preview


def stored_anatomy(tpl, root):
    """The Anatomy a head hierarchy was built with (root frame, metres): the adapted head's, stored on
    its root by blendout.build_result_objects; None for the template's own hierarchy (the bake then
    simulates the template). The parts' objects are not read back (float32, edits to the meshes)."""
    if "headadapt_anatomy" in root:
        return Anatomy.from_plain(root["headadapt_anatomy"].to_dict(), tpl)
    if root.get("headadapt_part") == "root":
        return None
    raise HeadAdaptError(f"{root.name!r} has no HeadAdapt anatomy: adapt again (results made before "
                         f"HeadAdapt 0.1 kept it in their objects only)")


def write_shape_keys(root, keys):
    """Add the baked keys as shape keys on the head's part objects; record them on the skin object."""
    objs = scene.template_objects(root)
    pivot = np.array(objs["jaw_pivot"].location)
    for key in keys:
        for part, verts in key.moved.items():
            block = bridge.add_shape_key(objs[part], key.name, verts - (pivot if part in JAW_CHILDREN else 0.0))
            block.slider_min, block.slider_max = -1.0, 3.0
    info = json.loads(objs["skin"].get("headadapt_keys", "{}"))
    info.update({k.name: {"kind": k.kind, "parts": sorted(k.moved), "fap_units": k.fap_units} for k in keys})
    objs["skin"]["headadapt_keys"] = json.dumps(info)
    return info


def _fcurve_set(id_data, path, frames, values, index=-1):
    """Keyframe `path` (channel index) on id_data at frames with values in one go, linear interpolation."""
    if id_data.animation_data is None:
        id_data.animation_data_create()
    action = id_data.animation_data.action
    if action is None:
        action = bpy.data.actions.new(f"HeadAdapt {id_data.name}")
        id_data.animation_data.action = action
    id_data.keyframe_insert(path, index=index, frame=float(frames[0]))   # creates the F-curve (any action API)
    fc = next(f for f in _fcurves(id_data) if f.data_path == path and (index < 0 or f.array_index == index))
    fc.keyframe_points.clear()
    fc.keyframe_points.add(len(frames))
    fc.keyframe_points.foreach_set("co", np.c_[frames, values].astype(np.float32).ravel())
    fc.keyframe_points.foreach_set("interpolation", np.full(len(frames), 1, dtype=np.int32))   # LINEAR
    fc.update()
    return fc


def _fcurves(id_data):
    action = id_data.animation_data.action
    if hasattr(action, "fcurves") and not hasattr(action, "layers"):
        return action.fcurves
    from bpy_extras import anim_utils  # Blender 4.4+: layered actions
    bag = anim_utils.action_get_channelbag_for_slot(action, id_data.animation_data.action_slot)
    return bag.fcurves


def _key_owners(root, name):
    """The shape-key datablocks (skin, jaw parts, eyes, ...) that carry a key called name."""
    out = []
    for o in root.children_recursive:
        if o.type == "MESH" and o.data.shape_keys and name in o.data.shape_keys.key_blocks:
            out.append(o.data.shape_keys)
    return out


def keyframe_key(root, name, frames, values):
    """Keyframe shape key `name` on every part that has it."""
    for owner in _key_owners(root, name):
        _fcurve_set(owner, f'key_blocks["{name}"].value', np.asarray(frames, float), np.asarray(values, float))


def preview_action(root, names=mpeg4.EXPRESSIONS, frames_each=PREVIEW_FRAMES, start=1):
    """Keyframe the named keys one after another (0 -> 1 -> 0 each) and set the scene's frame range."""
    for i, name in enumerate(names):
        a = start + i * frames_each
        frames = [start, a, a + frames_each // 3, a + 2 * frames_each // 3, a + frames_each]
        frames = sorted(set(frames))
        values = [1.0 if f in (a + frames_each // 3, a + 2 * frames_each // 3) else 0.0 for f in frames]
        keyframe_key(root, name, frames, values)
    sc = bpy.context.scene
    sc.frame_start, sc.frame_end = start, start + len(names) * frames_each
    return sc.frame_end


def head_pivot(root):
    """The point the head turns about (FDP 7.1, the top of the spine), in root's frame: stored on the
    root by scene.add_template (the template's) and blendout.build_result_objects (the adapted one)."""
    if "headadapt_head_pivot" in root:
        return np.array(root["headadapt_head_pivot"], dtype=float)
    from ..core.template import bundled_template  # a head made before the pivot was stored
    return np.asarray(bundled_template().meta["head_pivot"], dtype=float)


def head_rotation(root, anim, frames):
    """Keyframe head_pitch/yaw/roll (FAP 48-50, AU = mpeg4.AU_RAD) as root's rotation about the head
    pivot: the root's location is keyed with it so the pivot stays where it is. Returns how many of
    the three the file gives."""
    import mathutils
    cols = {axis: anim.values[:, mpeg4.FAP_BY_NAME[name].number] for name, (axis, _) in FAP_HEAD.items()}
    cols = {axis: col for axis, col in cols.items() if (~np.isnan(col)).any()}
    if not cols:
        return 0
    base_rot, base_loc = np.array(root.rotation_euler), np.array(root.location)
    angles = np.tile(base_rot, (len(frames), 1))
    for axis, col in cols.items():
        given = ~np.isnan(col)
        angles[:, axis] = base_rot[axis] + np.interp(frames, frames[given], col[given] * mpeg4.AU_RAD)
        _fcurve_set(root, "rotation_euler", frames[given], angles[given, axis], index=axis)
    scaled_pivot = mathutils.Vector(np.array(root.scale) * head_pivot(root))
    mode = root.rotation_mode if root.rotation_mode in ("XYZ", "XZY", "YXZ", "YZX", "ZXY", "ZYX") else "XYZ"

    def turned(a):
        return np.array(mathutils.Euler(a, mode).to_matrix() @ scaled_pivot)
    rest = base_loc + turned(base_rot)
    loc = np.array([rest - turned(a) for a in angles])
    for axis in range(3):
        _fcurve_set(root, "location", frames, loc[:, axis], index=axis)
    return len(cols)


def import_fap(root, anim, start=1):
    """Keyframe an MPEG-4 FapAnimation on a baked head: FAP keys, expressions, visemes, head rotation.

    A FAP's key value is its .fap value / the FAP units its key stands for (recorded at bake time);
    expressions take intensity / 63; visemes blend by viseme_blend / 63 (mpeg4.INTENSITY_MAX);
    head_pitch/yaw/roll turn the root about the head pivot (head_rotation). Returns {what: count} keyed.
    """
    full = float(mpeg4.INTENSITY_MAX)
    objs = scene.template_objects(root)
    info = json.loads(objs["skin"].get("headadapt_keys", "{}"))
    if not info:
        raise HeadAdaptError(f"{root.name!r} has no baked shape keys: bake expressions first")
    frames = anim.frames - anim.frames[0] + start
    sc = bpy.context.scene
    if anim.fps > 0:
        sc.render.fps, sc.render.fps_base = int(round(anim.fps)), round(anim.fps) / anim.fps
    counts = {"faps": 0, "expressions": 0, "visemes": 0, "head": 0}
    for number, fap in mpeg4.FAPS.items():
        col = anim.values[:, number]
        given = ~np.isnan(col)
        if fap.kind == "high" or not given.any():
            continue
        if fap.name in info and info[fap.name].get("fap_units"):
            keyframe_key(root, fap.name, frames[given], col[given] / info[fap.name]["fap_units"])
            counts["faps"] += 1
    counts["head"] = head_rotation(root, anim, frames)
    ex = anim.expressions
    if (~np.isnan(ex[:, 0])).any():
        rows = ~np.isnan(ex[:, 0])
        for i, name in enumerate(mpeg4.EXPRESSIONS, start=1):
            if name not in info:
                continue
            w = (np.where(ex[rows, 0] == i, ex[rows, 1], 0.0) + np.where(ex[rows, 2] == i, ex[rows, 3], 0.0)) / full
            keyframe_key(root, name, frames[rows], w)
            counts["expressions"] += 1
    vi = anim.visemes
    if (~np.isnan(vi[:, 0])).any():
        rows = ~np.isnan(vi[:, 0])
        blend = np.nan_to_num(vi[rows, 2], nan=full) / full
        for number, (name, _) in mpeg4.VISEMES.items():
            key = f"viseme_{name}"
            if key not in info:
                continue
            w = np.where(vi[rows, 0] == number, blend, 0.0) + np.where(vi[rows, 1] == number, 1.0 - blend, 0.0)
            keyframe_key(root, key, frames[rows], w)
            counts["visemes"] += 1
    sc.frame_start, sc.frame_end = int(frames[0]), int(frames[-1])
    return counts
