"""MPEG-4 face animation tables (ISO/IEC 14496-2, Annex C): FDPs, FAPUs, FAPs, expressions, visemes.

Frames: "left" and "right" are the face's own. In Blender's frame the head faces -Y with Z up, so
the person's left is +X, "up" is +Z and "forward" (toward the viewer) is -Y. Directions below are
given in that frame.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .exceptions import LandmarkError


@dataclass(frozen=True)
class FDP:
    """One facial definition point: standard id ("3.7"), human label, side, mirror partner, part."""
    id: str
    label: str
    side: str            # "L", "R" or "M" (midline)
    mirror: str | None   # the partner across the midline, None on the midline
    part: str            # skin, eye_l, eye_r, teeth_upper, teeth_lower, tongue, internal, hair


# (id, label, side, mirror partner, part): the standard's order, groups 2 to 11.
_FDP_ROWS = [
    ("2.1", "Chin bottom (gnathion)", "M", None, "skin"),
    ("2.2", "Inner upper lip, middle", "M", None, "skin"),
    ("2.3", "Inner lower lip, middle", "M", None, "skin"),
    ("2.4", "Inner lip corner, left", "L", "2.5", "skin"),
    ("2.5", "Inner lip corner, right", "R", "2.4", "skin"),
    ("2.6", "Inner upper lip, left midway", "L", "2.7", "skin"),
    ("2.7", "Inner upper lip, right midway", "R", "2.6", "skin"),
    ("2.8", "Inner lower lip, left midway", "L", "2.9", "skin"),
    ("2.9", "Inner lower lip, right midway", "R", "2.8", "skin"),
    ("2.10", "Chin boss", "M", None, "skin"),
    ("2.11", "Chin corner, left", "L", "2.12", "skin"),
    ("2.12", "Chin corner, right", "R", "2.11", "skin"),
    ("2.13", "Jaw angle (gonion), left", "L", "2.14", "skin"),
    ("2.14", "Jaw angle (gonion), right", "R", "2.13", "skin"),
    ("3.1", "Upper inner eyelid centre, left", "L", "3.2", "skin"),
    ("3.2", "Upper inner eyelid centre, right", "R", "3.1", "skin"),
    ("3.3", "Lower inner eyelid centre, left", "L", "3.4", "skin"),
    ("3.4", "Lower inner eyelid centre, right", "R", "3.3", "skin"),
    ("3.5", "Pupil centre, left", "L", "3.6", "eye_l"),
    ("3.6", "Pupil centre, right", "R", "3.5", "eye_r"),
    ("3.7", "Outer eye corner, left", "L", "3.12", "skin"),
    ("3.8", "Inner eye corner, right", "R", "3.11", "skin"),
    ("3.9", "Lower outer eyelid centre, left", "L", "3.10", "skin"),
    ("3.10", "Lower outer eyelid centre, right", "R", "3.9", "skin"),
    ("3.11", "Inner eye corner, left", "L", "3.8", "skin"),
    ("3.12", "Outer eye corner, right", "R", "3.7", "skin"),
    ("3.13", "Upper outer eyelid centre, left", "L", "3.14", "skin"),
    ("3.14", "Upper outer eyelid centre, right", "R", "3.13", "skin"),
    ("4.1", "Eyebrow inner end, left", "L", "4.2", "skin"),
    ("4.2", "Eyebrow inner end, right", "R", "4.1", "skin"),
    ("4.3", "Eyebrow top, left", "L", "4.4", "skin"),
    ("4.4", "Eyebrow top, right", "R", "4.3", "skin"),
    ("4.5", "Eyebrow outer end, left", "L", "4.6", "skin"),
    ("4.6", "Eyebrow outer end, right", "R", "4.5", "skin"),
    ("5.1", "Cheek centre, left", "L", "5.2", "skin"),
    ("5.2", "Cheek centre, right", "R", "5.1", "skin"),
    ("5.3", "Cheek bone, left", "L", "5.4", "skin"),
    ("5.4", "Cheek bone, right", "R", "5.3", "skin"),
    ("6.1", "Tongue tip", "M", None, "tongue"),
    ("6.2", "Tongue body centre", "M", None, "tongue"),
    ("6.3", "Tongue border, left", "L", "6.4", "tongue"),
    ("6.4", "Tongue border, right", "R", "6.3", "tongue"),
    ("7.1", "Top of the spine (head rotation centre)", "M", None, "internal"),
    ("8.1", "Outer upper lip, middle", "M", None, "skin"),
    ("8.2", "Outer lower lip, middle", "M", None, "skin"),
    ("8.3", "Outer lip corner, left", "L", "8.4", "skin"),
    ("8.4", "Outer lip corner, right", "R", "8.3", "skin"),
    ("8.5", "Outer upper lip, left midway", "L", "8.6", "skin"),
    ("8.6", "Outer upper lip, right midway", "R", "8.5", "skin"),
    ("8.7", "Outer lower lip, left midway", "L", "8.8", "skin"),
    ("8.8", "Outer lower lip, right midway", "R", "8.7", "skin"),
    ("8.9", "Cupid's bow peak, right", "R", "8.10", "skin"),
    ("8.10", "Cupid's bow peak, left", "L", "8.9", "skin"),
    ("9.1", "Nostril border, left", "L", "9.2", "skin"),
    ("9.2", "Nostril border, right", "R", "9.1", "skin"),
    ("9.3", "Nose tip", "M", None, "skin"),
    ("9.4", "Nose bottom edge, right", "R", "9.5", "skin"),
    ("9.5", "Nose bottom edge, left", "L", "9.4", "skin"),
    ("9.6", "Nose bone upper edge, right", "R", "9.7", "skin"),
    ("9.7", "Nose bone upper edge, left", "L", "9.6", "skin"),
    ("9.8", "Upper teeth, top", "M", None, "teeth_upper"),
    ("9.9", "Lower teeth, bottom", "M", None, "teeth_lower"),
    ("9.10", "Upper teeth, bottom", "M", None, "teeth_upper"),
    ("9.11", "Lower teeth, top", "M", None, "teeth_lower"),
    ("9.12", "Nose bump (nose bone, middle lower edge)", "M", None, "skin"),
    ("9.13", "Nose bone lower edge, left", "L", "9.14", "skin"),
    ("9.14", "Nose bone lower edge, right", "R", "9.13", "skin"),
    ("9.15", "Subnasale (bottom middle of the nose)", "M", None, "skin"),
    ("10.1", "Ear top, left", "L", "10.2", "skin"),
    ("10.2", "Ear top, right", "R", "10.1", "skin"),
    ("10.3", "Ear back, left", "L", "10.4", "skin"),
    ("10.4", "Ear back, right", "R", "10.3", "skin"),
    ("10.5", "Ear lobe bottom, left", "L", "10.6", "skin"),
    ("10.6", "Ear lobe bottom, right", "R", "10.5", "skin"),
    ("10.7", "Lobe-face lower contact, left", "L", "10.8", "skin"),
    ("10.8", "Lobe-face lower contact, right", "R", "10.7", "skin"),
    ("10.9", "Ear-face upper contact, left", "L", "10.10", "skin"),
    ("10.10", "Ear-face upper contact, right", "R", "10.9", "skin"),
    ("11.1", "Hairline, middle", "M", None, "skin"),
    ("11.2", "Hairline border, right", "R", "11.3", "skin"),
    ("11.3", "Hairline border, left", "L", "11.2", "skin"),
    ("11.4", "Top of the skull", "M", None, "skin"),
    ("11.5", "Hair thickness over 11.4", "M", None, "hair"),
    ("11.6", "Back of the skull", "M", None, "skin"),
]

FDPS: dict[str, FDP] = {row[0]: FDP(*row) for row in _FDP_ROWS}

# The FDPs the paper's calibration (sec 3.1) needs.
CALIBRATION_FDPS = ("2.1", "11.1", "3.7", "3.12", "8.3", "8.4", "10.9", "10.10")

# What an artist clicks: the 8 points every face shows from the front (eye corners, mouth
# corners, nose tip, chin boss), and 11 adding the subnasale and the lips' middles.
CLICKS_8 = ("3.7", "3.11", "3.8", "3.12", "8.3", "8.4", "9.3", "2.10")
CLICKS_11 = CLICKS_8 + ("9.15", "8.1", "8.2")

# Where to click the FDPs people misplace, said where the picker asks for them. The eye and lip
# corners are where the template puts them (the canthi, the commissure: test_template.py); the
# subnasale hides under the nose in a front view, and the real scans' clicks of it, picked on front
# renders, lay on the nose's underside 8 and 14 mm in front of it (docs/MEASUREMENTS.md, stop 60).
_EYE = "where the upper and lower lids meet, at the {} end of the eye's opening"
_LIP = "where the slit between the lips ends, not on the cheek beyond it"
CLICK_HINTS = {
    "3.7": _EYE.format("outer"), "3.12": _EYE.format("outer"),
    "3.11": _EYE.format("inner"), "3.8": _EYE.format("inner"),
    "8.3": _LIP, "8.4": _LIP,
    "9.15": "in the corner where the nose's underside meets the upper lip, not on the nose's underside "
            "(look from below the nose to see it)",
}


def fdp_sort_key(name: str) -> tuple[int, int]:
    """Sort key putting FDP ids in the standard's order ("2.1" < "2.10" < "3.1")."""
    group, index = name.split(".")
    return int(group), int(index)


def check_fdp_name(name: str) -> str:
    """Return name if it is a standard FDP id, else raise LandmarkError naming it."""
    if name not in FDPS:
        raise LandmarkError(f"unknown FDP name {name!r}: MPEG-4 FDPs are '2.1' to '11.6' "
                            f"(for example '3.7' = {FDPS['3.7'].label})")
    return name


# ---------------------------------------------------------------------------------------------
# FAPUs
# ---------------------------------------------------------------------------------------------
FAPU_NAMES = ("IRISD", "ES", "ENS", "MNS", "MW", "AU")
AU_RAD = 1e-5                  # the angle unit of rotation FAPs, rad
INTENSITY_MAX = 63             # FAP 1/2: viseme blend and expression intensity run 0..63

_FAPU_NEEDS = {"IRISD": ("3.1", "3.3"), "ES": ("3.5", "3.6"), "ENS": ("3.5", "3.6", "9.15"),
               "MNS": ("9.15", "2.2"), "MW": ("8.3", "8.4")}


def measure_fapus(points: dict) -> dict[str, float]:
    """FAPUs of a neutral face from its FDP positions {id: xyz}, in the points' length unit (AU in rad).

    IRISD = |3.1-3.3|, ES = |3.5-3.6|, ENS = distance from the pupils' midpoint to 9.15,
    MNS = |9.15-2.2|, MW = |8.3-8.4|, each divided by 1024; AU = AU_RAD.
    """
    missing = sorted({n for need in _FAPU_NEEDS.values() for n in need} - set(points), key=fdp_sort_key)
    if missing:
        raise LandmarkError(f"cannot measure FAPUs: FDP(s) {', '.join(missing)} missing")
    p = {k: np.asarray(points[k], dtype=float) for k in points}
    eyes = 0.5 * (p["3.5"] + p["3.6"])
    dist = {"IRISD": np.linalg.norm(p["3.1"] - p["3.3"]),
            "ES": np.linalg.norm(p["3.5"] - p["3.6"]),
            "ENS": np.linalg.norm(eyes - p["9.15"]),
            "MNS": np.linalg.norm(p["9.15"] - p["2.2"]),
            "MW": np.linalg.norm(p["8.3"] - p["8.4"])}
    out = {k: float(v) / 1024.0 for k, v in dist.items()}
    out["AU"] = AU_RAD
    return out


# ---------------------------------------------------------------------------------------------
# FAPs
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class FAP:
    """One facial animation parameter: number, name, unit (FAPU), FDP it moves, direction (Blender frame)."""
    number: int
    name: str
    unit: str
    fdp: str | None
    direction: tuple[float, float, float] | None   # unit vector of positive motion; None for rotations
    kind: str                                      # "translation", "rotation", "scale" or "high"


_UP, _DOWN, _FWD = (0.0, 0.0, 1.0), (0.0, 0.0, -1.0), (0.0, -1.0, 0.0)
_LEFT, _RIGHT = (1.0, 0.0, 0.0), (-1.0, 0.0, 0.0)

# The standard's 68 FAPs. Positive directions follow the standard's table (left/right are the
# face's own): e.g. stretch_l_cornerlip moves the left corner to the left, squeeze_l_eyebrow
# moves the left brow toward the midline.
_FAP_ROWS = [
    (1, "viseme", "", None, None, "high"),
    (2, "expression", "", None, None, "high"),
    (3, "open_jaw", "MNS", "2.1", _DOWN, "translation"),
    (4, "lower_t_midlip", "MNS", "2.2", _DOWN, "translation"),
    (5, "raise_b_midlip", "MNS", "2.3", _UP, "translation"),
    (6, "stretch_l_cornerlip", "MW", "2.4", _LEFT, "translation"),
    (7, "stretch_r_cornerlip", "MW", "2.5", _RIGHT, "translation"),
    (8, "lower_t_lip_lm", "MNS", "2.6", _DOWN, "translation"),
    (9, "lower_t_lip_rm", "MNS", "2.7", _DOWN, "translation"),
    (10, "raise_b_lip_lm", "MNS", "2.8", _UP, "translation"),
    (11, "raise_b_lip_rm", "MNS", "2.9", _UP, "translation"),
    (12, "raise_l_cornerlip", "MNS", "2.4", _UP, "translation"),
    (13, "raise_r_cornerlip", "MNS", "2.5", _UP, "translation"),
    (14, "thrust_jaw", "MNS", "2.1", _FWD, "translation"),
    (15, "shift_jaw", "MW", "2.1", _RIGHT, "translation"),
    (16, "push_b_lip", "MNS", "2.3", _FWD, "translation"),
    (17, "push_t_lip", "MNS", "2.2", _FWD, "translation"),
    (18, "depress_chin", "MNS", "2.10", _UP, "translation"),
    (19, "close_t_l_eyelid", "IRISD", "3.1", _DOWN, "translation"),
    (20, "close_t_r_eyelid", "IRISD", "3.2", _DOWN, "translation"),
    (21, "close_b_l_eyelid", "IRISD", "3.3", _UP, "translation"),
    (22, "close_b_r_eyelid", "IRISD", "3.4", _UP, "translation"),
    (23, "yaw_l_eyeball", "AU", "3.5", None, "rotation"),
    (24, "yaw_r_eyeball", "AU", "3.6", None, "rotation"),
    (25, "pitch_l_eyeball", "AU", "3.5", None, "rotation"),
    (26, "pitch_r_eyeball", "AU", "3.6", None, "rotation"),
    (27, "thrust_l_eyeball", "ES", "3.5", _FWD, "translation"),
    (28, "thrust_r_eyeball", "ES", "3.6", _FWD, "translation"),
    (29, "dilate_l_pupil", "IRISD", "3.5", None, "scale"),
    (30, "dilate_r_pupil", "IRISD", "3.6", None, "scale"),
    (31, "raise_l_i_eyebrow", "ENS", "4.1", _UP, "translation"),
    (32, "raise_r_i_eyebrow", "ENS", "4.2", _UP, "translation"),
    (33, "raise_l_m_eyebrow", "ENS", "4.3", _UP, "translation"),
    (34, "raise_r_m_eyebrow", "ENS", "4.4", _UP, "translation"),
    (35, "raise_l_o_eyebrow", "ENS", "4.5", _UP, "translation"),
    (36, "raise_r_o_eyebrow", "ENS", "4.6", _UP, "translation"),
    (37, "squeeze_l_eyebrow", "ES", "4.1", _RIGHT, "translation"),
    (38, "squeeze_r_eyebrow", "ES", "4.2", _LEFT, "translation"),
    (39, "puff_l_cheek", "ES", "5.1", _LEFT, "translation"),
    (40, "puff_r_cheek", "ES", "5.2", _RIGHT, "translation"),
    (41, "lift_l_cheek", "ENS", "5.3", _UP, "translation"),
    (42, "lift_r_cheek", "ENS", "5.4", _UP, "translation"),
    (43, "shift_tongue_tip", "MW", "6.1", _RIGHT, "translation"),
    (44, "raise_tongue_tip", "MNS", "6.1", _UP, "translation"),
    (45, "thrust_tongue_tip", "MW", "6.1", _FWD, "translation"),
    (46, "raise_tongue", "MNS", "6.2", _UP, "translation"),
    (47, "tongue_roll", "AU", "6.3", None, "rotation"),
    (48, "head_pitch", "AU", "7.1", None, "rotation"),
    (49, "head_yaw", "AU", "7.1", None, "rotation"),
    (50, "head_roll", "AU", "7.1", None, "rotation"),
    (51, "lower_t_midlip_o", "MNS", "8.1", _DOWN, "translation"),
    (52, "raise_b_midlip_o", "MNS", "8.2", _UP, "translation"),
    (53, "stretch_l_cornerlip_o", "MW", "8.3", _LEFT, "translation"),
    (54, "stretch_r_cornerlip_o", "MW", "8.4", _RIGHT, "translation"),
    (55, "lower_t_lip_lm_o", "MNS", "8.5", _DOWN, "translation"),
    (56, "lower_t_lip_rm_o", "MNS", "8.6", _DOWN, "translation"),
    (57, "raise_b_lip_lm_o", "MNS", "8.7", _UP, "translation"),
    (58, "raise_b_lip_rm_o", "MNS", "8.8", _UP, "translation"),
    (59, "raise_l_cornerlip_o", "MNS", "8.3", _UP, "translation"),
    (60, "raise_r_cornerlip_o", "MNS", "8.4", _UP, "translation"),
    (61, "stretch_l_nose", "ENS", "9.1", _LEFT, "translation"),
    (62, "stretch_r_nose", "ENS", "9.2", _RIGHT, "translation"),
    (63, "raise_nose", "ENS", "9.3", _UP, "translation"),
    (64, "bend_nose", "ENS", "9.3", _RIGHT, "translation"),
    (65, "raise_l_ear", "ENS", "10.1", _UP, "translation"),
    (66, "raise_r_ear", "ENS", "10.2", _UP, "translation"),
    (67, "pull_l_ear", "ENS", "10.3", _LEFT, "translation"),
    (68, "pull_r_ear", "ENS", "10.4", _RIGHT, "translation"),
]

FAPS: dict[int, FAP] = {row[0]: FAP(*row) for row in _FAP_ROWS}
FAP_BY_NAME: dict[str, FAP] = {f.name: f for f in FAPS.values()}
N_FAPS = len(FAPS)

# FAP 2 (expression_select): 1..6 in the standard's order.
EXPRESSIONS = ("joy", "sadness", "anger", "fear", "disgust", "surprise")

# FAP 1 (viseme_select): 0 = none, 1..14 with their phonemes.
VISEMES = {
    0: ("none", "none"), 1: ("p_b_m", "p, b, m"), 2: ("f_v", "f, v"), 3: ("T_D", "th (thin, this)"),
    4: ("t_d", "t, d"), 5: ("k_g", "k, g"), 6: ("tS_dZ_S", "ch, j, sh"), 7: ("s_z", "s, z"),
    8: ("n_l", "n, l"), 9: ("r", "r"), 10: ("A", "a (car)"), 11: ("e", "e (bed)"),
    12: ("I", "i (tip)"), 13: ("Q", "o (top)"), 14: ("U", "u (book)"),
}
