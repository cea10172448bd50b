"""ARKit's 52 blendshapes by simulation: each face unit is a bounded, non-negative activation of the
skin model's controls, fitted once on the template to the CC0 faceunits01 unit (tools/fit_arkit.py)
and stored in assets/template/arkit.json (Template.arkit); any head bakes them on its own anatomy.

Actuators are the model's controls, all pulling one way (activation >= 0); a control that works both
ways gets a second actuator for its other way (the lid raised: upper_lid_raise_l is upper_lid_l < 0;
the jaw slid left: jaw_shift_left is jaw_shift < 0). A Left unit's activation mirrored (_l <-> _r,
jaw_shift <-> jaw_shift_left) is its Right unit's, so the pair is mirror-symmetric on the template.
The gaze units also turn the eyeball (EYE_TURN), tongueOut slides the tongue (TONGUE_OUT): rigid
parts, as the MPEG-4 FAP keys move them. A unit the skin model does not reproduce says why in its table
entry; its key is the nearest shape the model reaches, or neutral when even that is far (every rig
driving the 52 finds every name).
Template frame (or the adapted head's, same axes), metres.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

# ARKit's 52 blendshape names, in Apple's order (ARFaceAnchor.BlendShapeLocation).
UNITS = (
    "eyeBlinkLeft", "eyeLookDownLeft", "eyeLookInLeft", "eyeLookOutLeft", "eyeLookUpLeft", "eyeSquintLeft",
    "eyeWideLeft", "eyeBlinkRight", "eyeLookDownRight", "eyeLookInRight", "eyeLookOutRight", "eyeLookUpRight",
    "eyeSquintRight", "eyeWideRight", "jawForward", "jawLeft", "jawRight", "jawOpen", "mouthClose",
    "mouthFunnel", "mouthPucker", "mouthLeft", "mouthRight", "mouthSmileLeft", "mouthSmileRight",
    "mouthFrownLeft", "mouthFrownRight", "mouthDimpleLeft", "mouthDimpleRight", "mouthStretchLeft",
    "mouthStretchRight", "mouthRollLower", "mouthRollUpper", "mouthShrugLower", "mouthShrugUpper",
    "mouthPressLeft", "mouthPressRight", "mouthLowerDownLeft", "mouthLowerDownRight", "mouthUpperUpLeft",
    "mouthUpperUpRight", "browDownLeft", "browDownRight", "browInnerUp", "browOuterUpLeft", "browOuterUpRight",
    "cheekPuff", "cheekSquintLeft", "cheekSquintRight", "noseSneerLeft", "noseSneerRight", "tongueOut",
)

# Actuators that are a control driven the other way: {actuator: (control, sign)}.
REVERSED = {
    "upper_lid_raise_l": ("upper_lid_l", -1.0), "upper_lid_raise_r": ("upper_lid_r", -1.0),
    "lower_lid_drop_l": ("lower_lid_l", -1.0), "lower_lid_drop_r": ("lower_lid_r", -1.0),
    "jaw_shift_left": ("jaw_shift", -1.0),
}
# Largest activation of an actuator in a fit (muscles up to 3 times the unit strength, as the
# expressions use); lids within their full turn; the jaw within ARKit's range.
BOUNDS = {"upper_lid": 1.0, "lower_lid": 1.0, "upper_lid_raise": 0.6, "lower_lid_drop": 0.6,
          "jaw_open": 1.3, "jaw_thrust": 2.0, "jaw_shift": 2.0, "jaw_shift_left": 2.0}
MUSCLE_BOUND = 3.0

# The gaze units turn the eyeball about its centre (radians about a Blender axis at activation 1;
# the person's left is +X, the face looks toward -Y): ARKit's eyeLook at 1 is about 25 degrees.
EYE_TURN_RAD = np.radians(25.0)
EYE_TURN = {  # unit: (part, axis, sign)
    "eyeLookUpLeft": ("eye_l", (1.0, 0.0, 0.0), -1.0), "eyeLookDownLeft": ("eye_l", (1.0, 0.0, 0.0), 1.0),
    "eyeLookInLeft": ("eye_l", (0.0, 0.0, 1.0), -1.0), "eyeLookOutLeft": ("eye_l", (0.0, 0.0, 1.0), 1.0),
    "eyeLookUpRight": ("eye_r", (1.0, 0.0, 0.0), -1.0), "eyeLookDownRight": ("eye_r", (1.0, 0.0, 0.0), 1.0),
    "eyeLookInRight": ("eye_r", (0.0, 0.0, 1.0), 1.0), "eyeLookOutRight": ("eye_r", (0.0, 0.0, 1.0), -1.0),
}
TONGUE_OUT = 0.02                     # tongueOut slides the tongue this far forward, m


def mirror_unit(name):
    """The other side's unit name (Left <-> Right), or the name itself for a midline unit."""
    return name.replace("Left", "\0").replace("Right", "Left").replace("\0", "Right")


def mirror_actuator(name):
    """The other side's actuator: _l <-> _r, jaw_shift <-> jaw_shift_left."""
    if name in ("jaw_shift", "jaw_shift_left"):
        return "jaw_shift_left" if name == "jaw_shift" else "jaw_shift"
    swap = {"_l": "_r", "_r": "_l"}
    return name[:-2] + swap[name[-2:]] if name[-2:] in swap else name


def actuators(controls):
    """Every actuator of a model with these controls (its controls, then the reversed ones)."""
    return (*controls, *(a for a, (c, _) in REVERSED.items() if c in controls))


def bound(actuator):
    """Largest activation of an actuator in a fit."""
    base = actuator[:-2] if actuator[-2:] in ("_l", "_r") else actuator
    return BOUNDS.get(base, MUSCLE_BOUND)


def to_controls(activations):
    """The model's {control: activation} of {actuator: activation >= 0}."""
    out = {}
    for name, a in activations.items():
        control, sign = REVERSED.get(name, (name, 1.0))
        out[control] = out.get(control, 0.0) + sign * float(a)
    return {k: v for k, v in out.items() if v}


def table(tpl):
    """{unit: entry} of the template's stored fit (assets/template/arkit.json), every unit of UNITS."""
    units = tpl.arkit.get("units", {})
    missing = [u for u in UNITS if u not in units]
    if missing:
        raise KeyError(f"the template's ARKit table lacks {', '.join(missing)} (run tools/fit_arkit.py)")
    return units


def expressed(tpl):
    """The units the model expresses (their fit reaches the table's thresholds), in ARKit's order."""
    units = table(tpl)
    return tuple(u for u in UNITS if units[u]["expressed"])


def recipe(tpl, unit):
    """The model's {control: activation} of a unit at 1: the table's activations (a unit not expressed
    has the nearest shape the model reaches, or none: a neutral key)."""
    return to_controls(table(tpl)[unit]["activations"])


def rigid_moves(unit, parts):
    """{part: (k,3) positions} of the rigid parts a unit at 1 moves (eyeball turn, tongue slide)."""
    if unit in EYE_TURN:
        part, axis, sign = EYE_TURN[unit]
        v = parts[part]
        centre = v.mean(axis=0)
        rot = Rotation.from_rotvec(sign * EYE_TURN_RAD * np.asarray(axis)).as_matrix()
        return {part: (v - centre) @ rot.T + centre}
    if unit == "tongueOut":
        return {"tongue": parts["tongue"] + TONGUE_OUT * np.array([0.0, -1.0, 0.0])}
    return {}


def bake_units(tpl, model, parts, followers, skins):
    """[(unit, {part: (k,3) positions})] of the 52 units at 1 on a built SkinModel and its parts: the
    skin at the unit's equilibrium (`skins` {unit: skin}, made for every unit with a recipe; a neutral
    key keeps the rest shape), the jaw's followers (part names) where the jaw moves, the rigid parts
    of rigid_moves."""
    out = []
    for unit in UNITS:
        controls = recipe(tpl, unit)
        moved = {"skin": skins[unit] if controls else np.array(parts["skin"], dtype=float)}
        if controls.keys() & {"jaw_open", "jaw_thrust", "jaw_shift"}:
            rot, t = model.mandible_transform(controls)
            for part in followers:
                moved[part] = model.on_jaw(parts[part], rot, t)
        moved.update(rigid_moves(unit, parts))
        out.append((unit, moved))
    return out
