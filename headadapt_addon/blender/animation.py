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


def written_rest(tpl, anatomy):
    """(parts, jaw pivot) of a head hierarchy as HeadAdapt wrote it (root frame, metres; the jaw's parts
    relative to the pivot): the anatomy's, else (the template's own hierarchy) the template's."""
    if anatomy is not None:
        return anatomy.parts, np.asarray(anatomy.jaw_pivot, dtype=float)
    return {k: p.verts for k, p in tpl.parts.items()}, np.asarray(tpl.meta["jaw"]["pivot"], dtype=float)


def moved_frame(obj, written):
    """The similarity taking a part's coordinates as HeadAdapt wrote them (`written`, (n,3)) onto its
    mesh now, where the artist has since applied the head's scale, rotation or location (Ctrl-A: the
    mesh changed by a similarity, the object's transform the other way); None where the mesh is as
    written (to float32) or was changed otherwise (edited: the keys keep the written frame)."""
    from ..core.adapt.calibration import umeyama
    now = bridge.vertex_positions(obj.data)
    if now.shape != np.shape(written):
        return None
    size = max(float(np.ptp(written, axis=0).max()), 1e-12)
    if np.abs(now - written).max() <= 1e-5 * size:
        return None
    sim = umeyama(written, now)
    return sim if np.abs(sim.apply(written) - now).max() <= 1e-5 * size * sim.scale else None


def write_shape_keys(root, keys, rest=None):
    """Add the baked keys as shape keys on the head's part objects; record them on the skin object.
    rest: written_rest of the anatomy baked; a part whose mesh the artist has since moved by a
    similarity (Apply Scale, a head in mm made 1 unit = 1 mm) gets its keys in that frame too."""
    objs = scene.template_objects(root)
    pivot = np.array(objs["jaw_pivot"].location)
    frames = {}                                        # part -> (similarity, offset) where it moved
    if rest is not None:
        parts, written_pivot = rest
        for part in {p for key in keys for p in key.moved}:
            offset = written_pivot if part in JAW_CHILDREN else 0.0
            sim = moved_frame(objs[part], parts[part] - offset)
            if sim is not None:
                frames[part] = (sim, offset)
    for key in keys:
        for part, verts in key.moved.items():
            if part in frames:
                sim, offset = frames[part]
                local = sim.apply(verts - offset)
            else:
                local = verts - (pivot if part in JAW_CHILDREN else 0.0)
            block = bridge.add_shape_key(objs[part], key.name, local)
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
        owner = getattr(id_data, "user", None) or id_data       # a shape-key block: named by its mesh
        action = bpy.data.actions.new(f"HeadAdapt {owner.name}")
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
    """Keyframe the named keys one after another (0 -> 1 -> 0 each) and set the scene's frame range; what
    HeadAdapt keyed on this head before (an earlier preview, a .fap) is taken off first."""
    skin = scene.template_objects(root).get("skin")
    clear_animation(root, set(json.loads(skin.get("headadapt_keys", "{}"))) | set(names) if skin else set(names))
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
    root by scene.add_template (the template's) and blendout.build_result_objects (the adapted one),
    moved with the skin where the artist has applied the head's scale since (moved_frame)."""
    from ..core.template import bundled_template
    if "headadapt_head_pivot" in root:
        pivot = np.array(root["headadapt_head_pivot"], dtype=float)
    else:                                           # a head made before the pivot was stored
        pivot = np.asarray(bundled_template().meta["head_pivot"], dtype=float)
    skin = scene.template_objects(root).get("skin")
    if skin is None or skin.parent != root:
        return pivot
    tpl = bundled_template()
    try:
        written = written_rest(tpl, stored_anatomy(tpl, root))[0]["skin"]
    except HeadAdaptError:
        return pivot
    sim = moved_frame(skin, written)
    if sim is None:
        return pivot
    return (np.array(skin.matrix_local) @ np.r_[sim.apply(pivot), 1.0])[:3]


def clear_animation(root, names):
    """Take off the keyframes HeadAdapt put on this head, so the next ones play alone: the F-curves of the
    baked keys `names` on every part (the bake's preview, an earlier .fap), those keys set back to 0,
    and an earlier .fap's head turn (the root's rotation and location F-curves, the root back at the
    rest pose it had before that turn)."""
    import mathutils
    for o in [root, *root.children_recursive]:
        keys = o.data.shape_keys if o.type == "MESH" else None
        if keys is None:
            continue
        fcurves = _fcurves(keys) if keys.animation_data and keys.animation_data.action else None
        for fc in [f for f in (fcurves or ()) if _keyed_name(f.data_path) in names]:
            fcurves.remove(fc)
        for block in keys.key_blocks[1:]:
            if block.name in names:
                block.value = 0.0
    if HEAD_REST in root:
        fcurves = _fcurves(root) if root.animation_data and root.animation_data.action else None
        for fc in [f for f in (fcurves or ()) if f.data_path in ("location", *ROTATIONS)]:
            fcurves.remove(fc)
        rest, turn = _head_rest(root)                    # its turn and place; its scale as it is now
        rest[:3, :3] = turn * np.array(root.scale)
        root.matrix_basis = mathutils.Matrix(rest.tolist())


def _keyed_name(data_path):
    """The shape key a `key_blocks["NAME"].value` F-curve drives, else None."""
    head, tail = 'key_blocks["', '"].value'
    return data_path[len(head):-len(tail)] if data_path.startswith(head) and data_path.endswith(tail) else None


HEAD_REST = "headadapt_head_rest"        # the root's matrix_basis before a .fap first turned it
ROTATIONS = ("rotation_euler", "rotation_quaternion", "rotation_axis_angle")


def _head_rest(root):
    """The root's rest pose (HEAD_REST) as (its 4x4 matrix, its turn: the 3x3 part with unit columns)."""
    rest = np.reshape(root[HEAD_REST], (4, 4))
    return rest, rest[:3, :3] / np.linalg.norm(rest[:3, :3], axis=0)


def head_rotation(root, anim, frames):
    """Keyframe head_pitch/yaw/roll (FAP 48-50, AU = mpeg4.AU_RAD) as root's rotation about the head
    pivot: the turn is applied in the head's own frame after its rest rotation (the root's pose before
    a .fap first turned it, kept on the root), in whichever rotation mode the root uses, and the
    root's location is keyed with it so the pivot stays where it is. Returns how many of the three
    the file gives."""
    from scipy.spatial.transform import Rotation
    cols = {axis: anim.values[:, mpeg4.FAP_BY_NAME[name].number] for name, (axis, _) in FAP_HEAD.items()}
    cols = {axis: col for axis, col in cols.items() if (~np.isnan(col)).any()}
    if not cols:
        return 0
    if HEAD_REST not in root:
        root[HEAD_REST] = [float(v) for row in root.matrix_basis for v in row]
    rest, turn = _head_rest(root)
    rest_turn = Rotation.from_matrix(turn)
    scale = np.array(root.scale)            # the artist's now (a root scaled for export since the rest)
    keyed = np.zeros(len(frames), bool)
    turn = np.zeros((len(frames), 3))
    for axis, col in cols.items():
        given = ~np.isnan(col)
        keyed |= given
        turn[:, axis] = np.interp(frames, frames[given], col[given] * mpeg4.AU_RAD)
    frames, turn = frames[keyed], turn[keyed]
    turned = rest_turn * Rotation.from_euler("xyz", turn)          # Blender's XYZ Euler: X first
    pivot = scale * head_pivot(root)
    loc = rest[:3, 3] + rest_turn.apply(pivot) - turned.apply(pivot)
    mode = root.rotation_mode
    if mode == "QUATERNION":
        path, channels = "rotation_quaternion", _continuous(turned.as_quat()[:, [3, 0, 1, 2]])
    elif mode == "AXIS_ANGLE":
        rotvec = turned.as_rotvec()
        angle = np.linalg.norm(rotvec, axis=1)
        axis = np.where(angle[:, None] > 1e-12, rotvec / np.maximum(angle, 1e-12)[:, None], (0.0, 1.0, 0.0))
        path, channels = "rotation_axis_angle", np.c_[angle, axis]
    else:                   # an Euler order: Blender's ZXY applies Z first, as scipy's extrinsic "zxy"
        order = mode.lower()
        angles = np.unwrap(turned.as_euler(order), axis=0)
        path, channels = "rotation_euler", angles[:, [order.index(c) for c in "xyz"]]
    for i in range(channels.shape[1]):
        _fcurve_set(root, path, frames, channels[:, i], index=i)
    for i in range(3):
        _fcurve_set(root, "location", frames, loc[:, i], index=i)
    return len(cols)


def _continuous(quats):
    """Quaternions (k,4) with their signs chosen so each is the nearer of q and -q to the one before."""
    flip = np.r_[1.0, np.sign(np.einsum("ij,ij->i", quats[1:], quats[:-1]) + 1e-300)]
    return quats * np.cumprod(flip)[:, None]


MAX_FRAME = 1_048_574                    # Blender's last frame
SLIDER_LIMIT = 10.0                      # a shape key's slider reaches -10..10 at most


def _scene_fps(fps):
    """(fps, fps_base) of the scene for a file's frame rate (Blender: an integer 1..32767 over a base
    1e-5..1e6), or None when Blender's scene cannot hold it."""
    whole = min(32767, max(1, int(round(fps))))
    base = whole / fps
    return (whole, base) if 1e-5 <= base <= 1e6 else None


def import_fap(root, anim, start=1):
    """Keyframe an MPEG-4 FapAnimation on a baked head: FAP keys, expressions, visemes, head rotation.

    The file's animation replaces what HeadAdapt keyed on this head before (the bake's preview, an
    earlier .fap: clear_animation). A FAP's key value is its .fap value / the FAP units its key stands
    for (recorded at bake time); expressions take intensity / 63; visemes blend by viseme_blend / 63
    (mpeg4.INTENSITY_MAX); head_pitch/yaw/roll turn the root about the head pivot (head_rotation). A key
    asked beyond its slider range gets its range widened, up to Blender's -10..10; beyond that it is
    cut there and named in "clipped". Everything is checked before anything changes: HeadAdaptError
    for a file with no frames, longer than Blender's timeline or at a frame rate its scene cannot
    hold. Of an inner lip FAP and its outer one given at the same frame, the stronger plays (one lip's
    motion). Returns {what: count the file asks for and the head plays (faps, expressions, visemes, head
    turns), "lip_pairs_merged": how many such pairs, "clipped": {key: the largest value asked},
    "unbaked": [the keys the file asks for that are not baked on the head]}.
    """
    full = float(mpeg4.INTENSITY_MAX)
    objs = scene.template_objects(root)
    info = json.loads(objs["skin"].get("headadapt_keys", "{}"))
    if not info:
        raise HeadAdaptError(f"{root.name!r} has no baked shape keys: bake expressions first")
    if not len(anim.frames):
        raise HeadAdaptError("the file holds no frames: nothing to play")
    span = int(anim.frames[-1]) - int(anim.frames[0])
    if span + start > MAX_FRAME:
        raise HeadAdaptError(f"its frames span {span + 1:,} frame numbers; Blender's timeline ends at frame "
                             f"{MAX_FRAME:,}")
    rate = _scene_fps(anim.fps)
    if rate is None:
        raise HeadAdaptError(f"a frame rate of {anim.fps:g} fps is beyond what a Blender scene can play")
    frames = (anim.frames - anim.frames[0]).astype(np.float64) + start
    curves = {}                                            # key name -> (frames, values)
    counts = {"faps": 0, "expressions": 0, "visemes": 0, "head": 0, "lip_pairs_merged": 0}
    unbaked = []                                           # keys the file asks for that the head lacks
    for number, fap in mpeg4.FAPS.items():
        col = anim.values[:, number]
        given = ~np.isnan(col)
        if fap.kind == "high" or not given.any() or fap.name in FAP_HEAD:    # the head turns its root
            continue
        if fap.name in info and info[fap.name].get("fap_units"):
            value = col / info[fap.name]["fap_units"]
            # an inner lip FAP (4-13) and its outer one (51-60) drive the same muscles, so their keys
            # are one lip's motion: where a file gives both, the stronger plays (the inner at a tie)
            # and the other rests, so the lip moves once, not twice (nor by half where one is 0)
            pair = mpeg4.FAP_BY_NAME.get(fap.name[:-2] if fap.name.endswith("_o") else f"{fap.name}_o")
            if pair is not None and pair.name in info and info[pair.name].get("fap_units"):
                other = anim.values[:, pair.number] / info[pair.name]["fap_units"]
                both = given & ~np.isnan(other)
                outer = fap.name.endswith("_o")
                rests = np.abs(value) < np.abs(other) if not outer else np.abs(value) <= np.abs(other)
                value = np.where(both & rests, 0.0, value)
                counts["lip_pairs_merged"] += bool(both.any()) and outer
            curves[fap.name] = (frames[given], value[given])
            counts["faps"] += 1
        elif fap.name not in info:
            unbaked.append(fap.name)
    ex = anim.expressions
    if (~np.isnan(ex[:, 0])).any():
        rows = ~np.isnan(ex[:, 0])
        asked = set(ex[rows, 0].astype(int)) | set(ex[rows, 2][~np.isnan(ex[rows, 2])].astype(int))
        unbaked += [name for i, name in enumerate(mpeg4.EXPRESSIONS, start=1) if i in asked and name not in info]
        for i, name in enumerate(mpeg4.EXPRESSIONS, start=1):
            if name in info:        # every baked one is keyed (0 where not asked), so the file plays alone
                w = (np.where(ex[rows, 0] == i, ex[rows, 1], 0.0) + np.where(ex[rows, 2] == i, ex[rows, 3], 0.0)) / full
                curves[name] = (frames[rows], w)
                counts["expressions"] += i in asked
    vi = anim.visemes
    if (~np.isnan(vi[:, 0])).any():
        rows = ~np.isnan(vi[:, 0])
        blend = np.nan_to_num(vi[rows, 2], nan=full) / full
        asked = set(vi[rows, 0].astype(int)) | set(vi[rows, 1][~np.isnan(vi[rows, 1])].astype(int))
        unbaked += [f"viseme_{name}" for number, (name, _) in mpeg4.VISEMES.items()
                    if number in asked and f"viseme_{name}" not in info]
        for number, (name, _) in mpeg4.VISEMES.items():
            key = f"viseme_{name}"
            if key in info:
                w = np.where(vi[rows, 0] == number, blend, 0.0) + np.where(vi[rows, 1] == number, 1.0 - blend, 0.0)
                curves[key] = (frames[rows], w)
                counts["visemes"] += number in asked
    clear_animation(root, set(info))
    sc = bpy.context.scene
    sc.render.fps, sc.render.fps_base = rate
    clipped = {}
    for name, (at, values) in curves.items():
        low, high = float(values.min()), float(values.max())
        if low < -SLIDER_LIMIT or high > SLIDER_LIMIT:
            clipped[name] = high if high > -low else low
            values = np.clip(values, -SLIDER_LIMIT, SLIDER_LIMIT)
        for owner in _key_owners(root, name):
            block = owner.key_blocks[name]
            block.slider_min = min(block.slider_min, max(low, -SLIDER_LIMIT))
            block.slider_max = max(block.slider_max, min(high, SLIDER_LIMIT))
            _fcurve_set(owner, f'key_blocks["{name}"].value', at, values)
    counts["head"] = head_rotation(root, anim, frames)
    sc.frame_start, sc.frame_end = int(frames[0]), int(frames[-1])
    counts["clipped"] = clipped
    counts["unbaked"] = unbaked
    return counts
