"""Clicks as people make them, on scan-like generated heads (tools/testheads.py): right clicks are
never dropped, a slip of the hand is, swapped left/right labels are put right and named."""
import numpy as np
import pytest

from headadapt_addon.core import adapt, mpeg4
from headadapt_addon.core.mesh import spatial

MM = 1000.0


def _light(testheads, seed):
    """A scan-like head with a lighter remesh (one subdivision, no decimation): same anatomy, holes,
    noise, pose and clicks, generated in a fifth of the time."""
    return testheads.make_head(seed, style="scan", subdiv=1, decimate=1.0)


def _correspondence(tpl, testheads, head):
    """clicks -> (the adapted face's correspondence RMS on the seen face, mm of the true head; the result)."""
    seen = testheads.face_mask(tpl) & head.true_on_scan

    def corr(clicks):
        res = adapt.adapt(tpl, head.scan_verts, head.scan_tris, clicks)
        d = (res.verts_scan - head.true_template)[seen]
        return float(np.sqrt(np.mean(np.sum(d ** 2, axis=1)))) / head.similarity[0] * MM, res
    return corr


@pytest.mark.slow
def test_no_right_click_is_dropped_on_fifty_heads(tpl, testheads):
    flagged = {}
    for seed in range(200, 250):
        head = _light(testheads, seed)
        res = adapt.adapt(tpl, head.scan_verts, head.scan_tris, head.clicks_8, adapt.AdaptOptions(max_levels=0))
        handed = res.calibration_info["handedness"]
        if res.flagged or handed["swapped"] or handed["relabelled"]:
            flagged[seed] = (res.flagged, handed["swapped"], handed["relabelled"])
    assert not flagged, flagged


@pytest.mark.slow
@pytest.mark.parametrize("seed", [250, 251, 252])
def test_a_click_20_mm_off_is_found_and_dropped(tpl, testheads, seed):
    head = _light(testheads, seed)
    clicks = dict(head.clicks_8)
    q = spatial.MeshQuery(head.scan_verts, head.scan_tris, backend=testheads.BACKEND)
    unit = head.similarity[0]
    rng = np.random.default_rng(seed)
    name = ["8.3", "3.12", "2.10"][seed % 3]
    # 20 mm away on the surface: push along a direction across the surface until the snapped click
    # lies 20 mm from the right one
    normal = q.closest_points(clicks[name][None])[0][0] - clicks[name]
    direction = rng.normal(size=3)
    direction -= direction @ normal * normal / max(normal @ normal, 1e-30)
    direction /= np.linalg.norm(direction)
    p = clicks[name]
    for reach in np.linspace(20.0, 60.0, 41):
        p = q.closest_points((clicks[name] + direction * reach * 1e-3 * unit)[None])[0][0]
        if np.linalg.norm(p - clicks[name]) / unit * MM >= 20.0:
            break
    clicks[name] = p
    res = adapt.adapt(tpl, head.scan_verts, head.scan_tris, clicks, adapt.AdaptOptions(max_levels=0))
    assert set(res.dropped) == {name}, (name, res.flagged)
    assert any(w.startswith(f"FDP {name}:") for w in res.outcome["warnings"])


def test_labels_from_the_viewer_s_side_are_put_right_and_named(tpl, testheads):
    head = _light(testheads, 253)
    swapped = {(mpeg4.FDPS[k].mirror or k): v for k, v in head.clicks_8.items()}
    res = adapt.adapt(tpl, head.scan_verts, head.scan_tris, swapped, adapt.AdaptOptions(max_levels=0))
    assert res.calibration_info["handedness"]["all"] and not res.dropped
    assert any("viewer's side" in w for w in res.outcome["warnings"])


@pytest.mark.parametrize("a, b", [("3.7", "3.8"), ("3.11", "3.7"), ("8.4", "2.10")])
def test_two_labels_exchanged_are_put_back_and_named(tpl, testheads, a, b):
    """Two labels that are not a left/right pair exchanged (one eye's outer corner and the other's
    inner, one eye's corners, a mouth corner and the chin): both clicks agree with the scan, so
    neither is dropped; the labels are put back and the fit is the one from the right labels."""
    head = _light(testheads, 254)
    clicks = dict(head.clicks_8)
    clicks[a], clicks[b] = head.clicks_8[b], head.clicks_8[a]
    options = adapt.AdaptOptions(max_levels=0)
    res = adapt.adapt(tpl, head.scan_verts, head.scan_tris, clicks, options)
    right = adapt.adapt(tpl, head.scan_verts, head.scan_tris, head.clicks_8, options)
    handed = res.calibration_info["handedness"]
    assert sorted(map(sorted, handed["relabelled"])) == [sorted((a, b))] and not handed["swapped"]
    assert not res.dropped and not right.dropped
    assert any(f"FDP {min(a, b)}" in w and "look swapped" in w for w in res.outcome["warnings"])
    np.testing.assert_array_equal(res.verts, right.verts)


@pytest.mark.slow
@pytest.mark.parametrize("seed", [202, 212, 222])
def test_every_fdp_clicked_keeps_the_top_of_the_skull(tpl, testheads, seed):
    """With every FDP clicked, the top of the skull (11.4), a dome the coarse fit places loosely, lay
    20-33 mm from where the fit put it on these heads and was dropped as a wrong click, and the adapted
    11.4 ended about 20 mm from the truth (a stranger's head 101: 36 mm, dropped, 'fit ok'). The loose
    FDPs have wider limits (clicks.LOOSE_FDPS)."""
    head = _light(testheads, seed)
    assert "11.4" in head.fdp_clicks
    res = adapt.adapt(tpl, head.scan_verts, head.scan_tris, head.fdp_clicks, adapt.AdaptOptions(max_levels=0))
    assert not res.dropped, res.flagged


@pytest.mark.slow
def test_a_hairline_click_between_the_brows_is_still_dropped(tpl, testheads):
    head = _light(testheads, 202)
    clicks = dict(head.fdp_clicks)
    between_brows = 0.5 * (clicks["4.1"] + clicks["4.2"])
    q = spatial.MeshQuery(head.scan_verts, head.scan_tris, backend=testheads.BACKEND)
    clicks["11.1"] = q.closest_points(between_brows[None])[0][0]            # the hairline clicked between the brows
    res = adapt.adapt(tpl, head.scan_verts, head.scan_tris, clicks, adapt.AdaptOptions(max_levels=0))
    assert res.dropped == ["11.1"], res.flagged


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 5])
def test_a_right_click_on_the_skull_does_not_pull_the_face(tpl, testheads, seed):
    """More right clicks should not make the face worse. Added to the panel's 11 clicks, a right click
    on the top of the skull (11.4) or the hairline (11.1), where a head differs from the template more
    than one similarity follows, leaned calibration's least-squares similarity away from the face: the
    face's correspondence worse by 1.07 and 1.04 mm (11.4) and 0.67 and 0.62 mm (11.1) on these two
    heads. Calibration now leans on the face's clicks (clicks.calibrated_on), the levels take the others."""
    head = _light(testheads, seed)
    corr = _correspondence(tpl, testheads, head)
    base = {k: head.fdp_clicks[k] for k in mpeg4.CLICKS_11 if k in head.fdp_clicks}
    alone, first = corr(base)
    for far in ("11.4", "11.1"):
        more, res = corr({**base, far: head.fdp_clicks[far]})
        assert more < alone + 0.45, (far, alone, more)
        assert res.calibration_info["not_leaned_on"] == [far] and not res.dropped
        np.testing.assert_array_equal(res.similarity.matrix4(), first.similarity.matrix4())


@pytest.mark.slow
@pytest.mark.parametrize("seed", [3, 6])
def test_every_suggestion_accepted_keeps_the_fit(tpl, testheads, seed):
    """Suggest the Rest proposes the FDPs the 8 clicks leave out, and the artist may accept them all.
    Proposed where the level-0 RBF of the clicks put them (until stop 59), the 66 of them took these
    heads' face from 4.20 to 9.35 and from 4.55 to 8.23 mm off the truth: a thin-plate map through 8
    points is a poor guess of the rest, and 66 poor guesses outvote 8 good clicks. Proposed where the
    adaptation puts them, accepting them keeps the fit."""
    from headadapt_addon.core.adapt import suggest

    head = _light(testheads, seed)
    corr = _correspondence(tpl, testheads, head)
    eight = {k: head.fdp_clicks[k] for k in mpeg4.CLICKS_8}
    alone, _ = corr(eight)
    proposed = suggest.suggest_fdps(tpl, head.scan_verts, head.scan_tris, eight)
    assert len(proposed) == 66 and not set(proposed) & set(eight)
    accepted, res = corr({**eight, **proposed})
    assert accepted < alone + 0.3 and not res.dropped, (alone, accepted, res.dropped)
