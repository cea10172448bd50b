"""The outcome's scan not reached (outcome.scan_beyond): scan points by the face and ears lying far
outside the adapted skin, which the seen-skin RMS cannot show, are counted and warned of."""
import types

import numpy as np
import pytest

from headadapt_addon.core.adapt import AdaptOptions, adapt
from headadapt_addon.core.adapt.options import FACE_REGIONS
from headadapt_addon.core.adapt.outcome import fit_outcome, scan_beyond
from headadapt_addon.core.mesh import geometry


def _fit(tpl, scan_verts):
    """What scan_beyond reads of a Fit: the template skin as the adapted skin, the scan given."""
    v, t = tpl.skin.verts, tpl.skin.tris
    scan = types.SimpleNamespace(verts=scan_verts, vertex_normals=geometry.vertex_normals(scan_verts, t))
    return types.SimpleNamespace(tpl=tpl, scan=scan, tris=t, options=AdaptOptions()), v


@pytest.mark.parametrize("push_mm, counted", [(8.0, True), (3.0, False), (-8.0, False), (0.0, False)])
def test_scan_beyond_counts_scan_far_outside_the_skin(tpl, push_mm, counted):
    """The scan is the skin itself with the ears pushed along their normals: 8 mm out is scan the fit
    did not reach; 3 mm out is under beyond_mm, 8 mm in lies inside the skin (a CT's inner surfaces)."""
    v = tpl.skin.verts
    ears = tpl.region_mask("ear_l", "ear_r")
    scan = v + (push_mm / 1000.0) * ears[:, None] * geometry.vertex_normals(v, tpl.skin.tris)
    fit, verts = _fit(tpl, scan)
    pct = scan_beyond(fit, verts)
    if counted:
        near = tpl.region_mask(*FACE_REGIONS, "ear_l", "ear_r")
        share = 100.0 * ears.sum() / near.sum()
        assert 0.5 * share < pct <= share + 1.0, (pct, share)   # the ears' pushed points, about all of them
    else:
        assert pct == 0.0


def test_the_outcome_warns_of_scan_not_reached_and_still_trusts_the_fit(tpl):
    o = AdaptOptions()
    dist = np.full(len(tpl.skin.verts), 0.0002)           # 0.2 mm: a close fit
    face = np.ones(len(dist), bool)
    calm = fit_outcome(dist, face, 0, None, {}, o, beyond=0.3)
    far = fit_outcome(dist, face, 0, None, {}, o, beyond=4.2)
    assert calm["scan_beyond_pct"] == 0.3 and not calm["warnings"] and calm["ok"]
    assert far["scan_beyond_pct"] == 4.2 and far["ok"]
    assert len(far["warnings"]) == 1 and far["warnings"][0].startswith("4.2% of the scan by the face and ears")


@pytest.mark.slow
def test_an_ear_rim_left_outside_is_reported_on_a_generated_head(tpl, testheads):
    """Tuning head 11 (8 clicks): the adapted left ear leaves the scan's ear rim 9-13 mm out; head 0
    has nothing of the kind."""
    from headadapt_addon.core import mpeg4

    out = {}
    for seed in (11, 0):
        head = testheads.make_head(seed, style="scan")
        clicks = {k: head.fdp_clicks[k] for k in mpeg4.CLICKS_8 if k in head.fdp_clicks}
        out[seed] = adapt(tpl, head.scan_verts, head.scan_tris, clicks, AdaptOptions()).outcome
    assert out[11]["scan_beyond_pct"] > 1.5 and any("outside the adapted skin" in w for w in out[11]["warnings"])
    assert out[0]["scan_beyond_pct"] < 0.5 and not any("outside the adapted skin" in w for w in out[0]["warnings"])
