"""MPEG-4 drive as data: FAPs, expressions and visemes -> skin-model controls and rigid-part motions.

A control is one of core.skin's (muscles, sphincters, jaw, lids, cheek puff, lip push/funnel,
depressor septi), with an activation; 1 is about the amplitude of the matching ARKit face unit.
FAPs the skin cannot express move rigid parts instead (eyeballs, tongue) or the whole head
(head_pitch/yaw/roll: the root object's rotation). Not expressed: pupil dilation (29-30, the
template's eyes have no pupil geometry), tongue roll (47) and the ears (65-68, no ear muscles).
The expression and viseme recipes are hand-made from FACS descriptions (Ekman & Friesen) and
common viseme charts; they are data, edit them here.
"""

from __future__ import annotations

import re

from .. import mpeg4


def _lr(recipe_l):
    """The right side's recipe of a left one (_l <-> _r in every control name)."""
    swap = {"_l": "_r", "_r": "_l"}
    return {(k[:-2] + swap[k[-2:]]) if k[-2:] in swap else k: v for k, v in recipe_l.items()}


def _both(recipe):
    """A recipe applied on both sides (every _l control also as _r)."""
    out = dict(recipe)
    out.update(_lr(recipe))
    return out


# Low-level FAPs on the skin: {FAP name: {control: activation at key value 1}} (left ones; the
# right ones are mirrored below). Key value 1 moves the FAP's FDP in the FAP's direction.
_INNER_LIP_LEFT = {
    "lower_t_midlip": {"orbicularis_oris": 1.0},
    "raise_b_midlip": {"mentalis_l": 0.5, "mentalis_r": 0.5, "orbicularis_oris": 0.5},
    "stretch_l_cornerlip": {"risorius_l": 1.0},
    "lower_t_lip_lm": {"orbicularis_oris": 0.5},
    "raise_b_lip_lm": {"mentalis_l": 1.0, "orbicularis_oris": 0.3},
    "raise_l_cornerlip": {"zygomaticus_major_l": 1.0},
}
_FAP_SKIN_LEFT = {
    "open_jaw": {"jaw_open": 1.0},
    **_INNER_LIP_LEFT,
    **{f"{name}_o": recipe for name, recipe in _INNER_LIP_LEFT.items()},   # outer lip (FAPs 51-60): same muscles
    "thrust_jaw": {"jaw_thrust": 1.0},
    "shift_jaw": {"jaw_shift": 1.0},
    "push_b_lip": {"lip_push_lower": 1.0},
    "push_t_lip": {"lip_push_upper": 1.0},
    "depress_chin": {"mentalis_l": 1.0, "mentalis_r": 1.0},
    "close_t_l_eyelid": {"upper_lid_l": 1.0},
    "close_b_l_eyelid": {"lower_lid_l": 1.0},
    "raise_l_i_eyebrow": {"frontalis_inner_l": 1.0},
    "raise_l_m_eyebrow": {"frontalis_inner_l": 0.5, "frontalis_outer_l": 0.5},
    "raise_l_o_eyebrow": {"frontalis_outer_l": 1.0},
    "squeeze_l_eyebrow": {"corrugator_l": 1.0},
    "puff_l_cheek": {"cheek_puff_l": 1.0},
    "lift_l_cheek": {"cheek_raiser_l": 1.0},
    "stretch_l_nose": {"nasalis_l": 1.0},
    "raise_nose": {"levator_labii_superioris_l": 0.5, "levator_labii_superioris_r": 0.5},
    "bend_nose": {"nasalis_r": 1.0},
}


def _mirror_name(name):
    """The FAP name of the other side: _l_ <-> _r_ and _lm <-> _rm (raise_l_cornerlip, lower_t_lip_lm_o)."""
    return re.sub(r"_([lr])(?=_|m\b|m_)", lambda m: "_" + {"l": "r", "r": "l"}[m.group(1)], name)


FAP_SKIN = {}
for _name, _recipe in _FAP_SKIN_LEFT.items():
    FAP_SKIN[_name] = _recipe
    _other = _mirror_name(_name)
    if _other != _name and _other in mpeg4.FAP_BY_NAME:
        FAP_SKIN[_other] = _lr(_recipe)

# FAPs that move a rigid part: {FAP name: (part, kind, axis or direction, amount at key value 1)}.
# Rotations in radians about an axis through the part's centre (Blender frame), slides in metres.
FAP_RIGID = {
    "yaw_l_eyeball": ("eye_l", "rotate", (0.0, 0.0, 1.0), 0.5),
    "yaw_r_eyeball": ("eye_r", "rotate", (0.0, 0.0, 1.0), 0.5),
    "pitch_l_eyeball": ("eye_l", "rotate", (1.0, 0.0, 0.0), 0.5),
    "pitch_r_eyeball": ("eye_r", "rotate", (1.0, 0.0, 0.0), 0.5),
    "thrust_l_eyeball": ("eye_l", "slide", (0.0, -1.0, 0.0), 0.005),
    "thrust_r_eyeball": ("eye_r", "slide", (0.0, -1.0, 0.0), 0.005),
    "shift_tongue_tip": ("tongue", "slide", (-1.0, 0.0, 0.0), 0.01),
    "raise_tongue_tip": ("tongue", "slide", (0.0, 0.0, 1.0), 0.008),
    "thrust_tongue_tip": ("tongue", "slide", (0.0, -1.0, 0.0), 0.01),
    "raise_tongue": ("tongue", "slide", (0.0, 0.0, 1.0), 0.008),
}
# The head rotation FAPs turn the whole head about 7.1: (axis, Blender rotation channel).
FAP_HEAD = {"head_pitch": (0, "x"), "head_yaw": (2, "z"), "head_roll": (1, "y")}
NOT_EXPRESSED = ("dilate_l_pupil", "dilate_r_pupil", "tongue_roll", "raise_l_ear", "raise_r_ear",
                 "pull_l_ear", "pull_r_ear")

# The six expressions (FAP 2) at full intensity: fitted once on the template to their artist
# references (ARTIST_REFERENCE, below) by bounded least squares over FACS-plausible controls (joy,
# fear, disgust, surprise) or all of them (sadness, anger: their references need the chin and lip
# pushes), then scaled so the baked key has the reference's magnitude; lids within +-1. Joy (AU6 +
# AU12: cheek raiser and zygomaticus major) was picked from a grid over the zygomaticus major, the
# cheek raiser and the orbicularis oculi on the template and generated heads 5 and 9, for the least
# cosine over the three (not the template's own optimum); disgust (AU9 + AU10) is the bounded
# least-squares fit over its FACS muscles.
EXPRESSION_RECIPES = {
    "joy": _both({"zygomaticus_major_l": 1.7, "orbicularis_oculi_l": 0.9, "lower_lid_l": 1.0, "cheek_raiser_l": 1.2}),
    "sadness": _both({"frontalis_inner_l": 0.86, "corrugator_l": 0.33, "levator_labii_superioris_l": 0.04, "zygomaticus_minor_l": 0.09, "risorius_l": 0.35, "depressor_anguli_oris_l": 0.61, "mentalis_l": 0.83, "nasalis_l": 0.32, "cheek_puff_l": 0.27}) | {"lip_push_upper": 0.1, "lip_push_lower": 0.71, "jaw_open": 0.08, "jaw_thrust": 0.22},
    "anger": _both({"corrugator_l": 2.54, "zygomaticus_major_l": 0.39, "mentalis_l": 0.69, "buccinator_l": 0.06, "orbicularis_oculi_l": 0.39, "cheek_puff_l": 0.16, "lower_lid_l": 0.89, "upper_lid_l": 0.24}) | {"lip_push_upper": 0.08, "lip_push_lower": 0.47},
    "fear": _both({"frontalis_inner_l": 0.85, "frontalis_outer_l": 0.32, "corrugator_l": 0.05, "risorius_l": 0.52, "upper_lid_l": -0.4, "depressor_labii_inferioris_l": 0.24, "mentalis_l": 0.97}) | {"jaw_open": 0.3},
    "disgust": _both({"levator_alaeque_nasi_l": 0.92, "levator_labii_superioris_l": 0.34, "corrugator_l": 1.49, "depressor_anguli_oris_l": 0.21, "orbicularis_oculi_l": 0.64, "lower_lid_l": 0.28, "cheek_raiser_l": 0.11, "depressor_supercilii_l": 1.46}) | {"lip_push_upper": 0.34},
    "surprise": _both({"frontalis_inner_l": 0.88, "frontalis_outer_l": 0.9, "upper_lid_l": -0.45, "mentalis_l": 0.88}) | {"jaw_open": 0.52},
}

# The fourteen visemes (FAP 1), by their names in mpeg4.VISEMES.
VISEME_RECIPES = {
    "p_b_m": {"orbicularis_oris": 0.6, "mentalis_l": 0.2, "mentalis_r": 0.2},
    "f_v": {"jaw_open": 0.1, "mentalis_l": 0.6, "mentalis_r": 0.6, "levator_labii_superioris_l": 0.2,
            "levator_labii_superioris_r": 0.2},
    "T_D": {"jaw_open": 0.2, "risorius_l": 0.1, "risorius_r": 0.1},
    "t_d": {"jaw_open": 0.15, "risorius_l": 0.2, "risorius_r": 0.2},
    "k_g": {"jaw_open": 0.25, "risorius_l": 0.15, "risorius_r": 0.15},
    "tS_dZ_S": {"jaw_open": 0.15, "lip_funnel": 0.5, "lip_push_upper": 0.5, "lip_push_lower": 0.5},
    "s_z": {"jaw_open": 0.08, "risorius_l": 0.4, "risorius_r": 0.4},
    "n_l": {"jaw_open": 0.2, "risorius_l": 0.1, "risorius_r": 0.1},
    "r": {"jaw_open": 0.15, "lip_funnel": 0.3, "orbicularis_oris": 0.3},
    "A": {"jaw_open": 0.6},
    "e": {"jaw_open": 0.35, "risorius_l": 0.4, "risorius_r": 0.4},
    "I": {"jaw_open": 0.2, "risorius_l": 0.5, "risorius_r": 0.5, "zygomaticus_major_l": 0.2,
          "zygomaticus_major_r": 0.2},
    "Q": {"jaw_open": 0.4, "lip_funnel": 0.6, "orbicularis_oris": 0.3},
    "U": {"jaw_open": 0.15, "orbicularis_oris": 0.7, "lip_push_upper": 0.6, "lip_push_lower": 0.6},
}

# ARKit face units (faceunits01) -> the controls whose activations the benchmark fits to them.
ARKIT_CONTROLS = {
    "jawOpen": ("jaw_open",),
    "mouthSmileLeft": ("zygomaticus_major_l", "risorius_l", "zygomaticus_minor_l"),
    "mouthSmileRight": ("zygomaticus_major_r", "risorius_r", "zygomaticus_minor_r"),
    "browInnerUp": ("frontalis_inner_l", "frontalis_inner_r"),
    "browOuterUpLeft": ("frontalis_outer_l",),
    "browOuterUpRight": ("frontalis_outer_r",),
    "eyeBlinkLeft": ("upper_lid_l", "lower_lid_l", "orbicularis_oculi_l"),
    "eyeBlinkRight": ("upper_lid_r", "lower_lid_r", "orbicularis_oculi_r"),
    "mouthPucker": ("orbicularis_oris", "lip_push_upper", "lip_push_lower"),
    "mouthFunnel": ("orbicularis_oris", "lip_funnel", "lip_push_upper", "lip_push_lower", "jaw_open",
                    "depressor_septi"),
    "cheekPuff": ("cheek_puff_l", "cheek_puff_r"),
    "cheekSquintLeft": ("cheek_raiser_l",),
    "cheekSquintRight": ("cheek_raiser_r",),
    "noseSneerLeft": ("levator_alaeque_nasi_l", "depressor_supercilii_l", "corrugator_l"),
    "noseSneerRight": ("levator_alaeque_nasi_r", "depressor_supercilii_r", "corrugator_r"),
}


# The eye closed (ARKit eyeBlink): both lids at 1, the upper margin meets the risen lower one.
BLINK = {"eyeBlinkLeft": {"upper_lid_l": 1.0, "lower_lid_l": 1.0},
         "eyeBlinkRight": {"upper_lid_r": 1.0, "lower_lid_r": 1.0}}


def _units(**weights):
    """Artist reference {face unit: weight}; a name ending in _ stands for its Left and Right units."""
    out = {}
    for name, w in weights.items():
        if name.endswith("_"):
            out[name[:-1] + "Left"] = out[name[:-1] + "Right"] = w
        else:
            out[name] = w
    return out


# The artist's reference of each shipped key: a blend of the CC0 faceunits01 ARKit face units
# ({unit: weight}), after FACS (Ekman & Friesen) for the expressions and the usual ARKit viseme
# charts. The benchmark (headless_tests/bench/bench_expressions.py) compares each baked key with
# its reference in direction (cosine) and size (magnitude ratio). FAP keys without a matching unit
# have none. Left FAPs are listed; the right ones mirror.
ARTIST_REFERENCE = {
    "joy": _units(mouthSmile_=1.0, cheekSquint_=0.6, eyeSquint_=0.4),
    "sadness": _units(browInnerUp=1.0, mouthFrown_=1.0, mouthShrugLower=0.3, browDown_=0.2),
    "anger": _units(browDown_=1.0, eyeSquint_=0.5, mouthPress_=0.6, noseSneer_=0.3),
    "fear": _units(browInnerUp=1.0, browOuterUp_=0.4, eyeWide_=1.0, mouthStretch_=0.8, jawOpen=0.2),
    "disgust": _units(noseSneer_=1.0, mouthUpperUp_=0.6, mouthFrown_=0.3, cheekSquint_=0.3, browDown_=0.3),
    "surprise": _units(browInnerUp=1.0, browOuterUp_=1.0, eyeWide_=1.0, jawOpen=0.3),
    "viseme_p_b_m": _units(mouthPress_=0.5, mouthRollLower=0.3, mouthRollUpper=0.3),
    "viseme_f_v": _units(mouthRollLower=0.6, mouthUpperUp_=0.3, jawOpen=0.05),
    "viseme_T_D": _units(jawOpen=0.15, mouthStretch_=0.1),
    "viseme_t_d": _units(jawOpen=0.12, mouthStretch_=0.2),
    "viseme_k_g": _units(jawOpen=0.2, mouthStretch_=0.15),
    "viseme_tS_dZ_S": _units(mouthFunnel=0.6, mouthPucker=0.2, jawOpen=0.1),
    "viseme_s_z": _units(jawOpen=0.05, mouthStretch_=0.4),
    "viseme_n_l": _units(jawOpen=0.15, mouthStretch_=0.1),
    "viseme_r": _units(mouthFunnel=0.3, mouthPucker=0.3, jawOpen=0.1),
    "viseme_A": _units(jawOpen=0.5),
    "viseme_e": _units(jawOpen=0.3, mouthStretch_=0.4),
    "viseme_I": _units(jawOpen=0.15, mouthSmile_=0.3, mouthStretch_=0.4),
    "viseme_Q": _units(mouthFunnel=0.7, jawOpen=0.3),
    "viseme_U": _units(mouthPucker=0.8, mouthFunnel=0.2, jawOpen=0.1),
    "open_jaw": _units(jawOpen=0.8),                       # open_jaw at 1 turns 22 deg, jawOpen about 27
    "thrust_jaw": _units(jawForward=1.0),
    "shift_jaw": _units(jawRight=1.0),
    "raise_b_midlip": _units(mouthShrugLower=1.0),
    "push_t_lip": _units(mouthShrugUpper=1.0),
    "close_t_l_eyelid": _units(eyeBlinkLeft=1.0),
    "stretch_l_cornerlip": _units(mouthStretchLeft=1.0),
    "raise_l_cornerlip": _units(mouthSmileLeft=1.0),
    "raise_l_o_eyebrow": _units(browOuterUpLeft=1.0),
    "squeeze_l_eyebrow": _units(browDownLeft=1.0),
    "lift_l_cheek": _units(cheekSquintLeft=1.0),
    "stretch_l_nose": _units(noseSneerLeft=1.0),
}
for _name in [k for k in ARTIST_REFERENCE if _mirror_name(k) != k]:
    _other = {u.replace("Left", "\0").replace("Right", "Left").replace("\0", "Right"): w
              for u, w in ARTIST_REFERENCE[_name].items()}
    ARTIST_REFERENCE[_mirror_name(_name)] = _other
for _name in [k for k in ARTIST_REFERENCE if k.endswith(("_cornerlip",)) and not k.endswith("_o")]:
    ARTIST_REFERENCE[_name + "_o"] = ARTIST_REFERENCE[_name]           # the outer lip FAP, same muscles


def reference_units():
    """Every face unit a reference names (sorted)."""
    return sorted({u for ref in ARTIST_REFERENCE.values() for u in ref} | set(BLINK))


def shape_key_recipes():
    """Every bakeable key: [(key name, kind "expression"/"viseme"/"fap", {control: activation})]."""
    keys = [(name, "expression", EXPRESSION_RECIPES[name]) for name in mpeg4.EXPRESSIONS]
    keys += [(f"viseme_{name}", "viseme", VISEME_RECIPES[name]) for _, (name, _) in sorted(mpeg4.VISEMES.items())
             if name != "none"]
    keys += [(fap.name, "fap", FAP_SKIN[fap.name]) for fap in mpeg4.FAPS.values() if fap.name in FAP_SKIN]
    return keys
