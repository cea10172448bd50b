"""The skin's closest points on its bone kept from look to look (core/skin/recall.py): the kept answers
are the fresh ones to the bit, only points that moved are asked again, and an equilibrium with them is
the one without."""
import numpy as np
import pytest

from headadapt_addon.core.mesh.spatial import MeshQuery
from headadapt_addon.core.skin import drive, recall
from headadapt_addon.core.skin.build import build
from headadapt_addon.core.template import load_template


@pytest.fixture(scope="module")
def tpl():
    return load_template()


class Counted:
    def __init__(self, query):
        self.query, self.asked = query, []

    def closest_points(self, pts):
        self.asked.append(len(pts))
        return self.query.closest_points(pts)


def test_kept_answers_are_the_fresh_ones_and_only_moved_points_are_asked(tpl):
    query = MeshQuery(tpl.parts["cranium"].verts, tpl.parts["cranium"].tris, backend="numpy")
    skin = tpl.skin.verts.copy()
    counted = Counted(query)
    kept = recall.KeptClosest(counted, len(skin))
    rng = np.random.default_rng(3)
    first = np.flatnonzero(skin[:, 2] > np.median(skin[:, 2]))
    second = np.sort(rng.choice(len(skin), 600, replace=False))
    for step, idx in enumerate((first, first, second, second)):
        if step == 3:
            skin[second[:50]] += 0.001                 # some of the last ask's points moved
        got = kept(skin[idx], idx)
        for a, b in zip(got, query.closest_points(skin[idx])):
            np.testing.assert_array_equal(a, b)
    # the first ask asks every point, the second (the same points, unmoved) none, the third only the
    # points never asked before, the fourth only the 50 moved
    assert counted.asked == [len(first), len(np.setdiff1d(second, first)), 50], counted.asked


def test_an_equilibrium_with_kept_answers_is_the_one_without(tpl, monkeypatch):
    model = build(tpl)
    recipes = [r for name, kind, r in drive.shape_key_recipes()
               if kind == "expression" or (kind == "viseme" and r.keys() & {"jaw_open"})][:8]
    assert any("jaw_open" in r for r in recipes)
    kept = [model.equilibrium(r) for r in recipes]
    assert model.__dict__.get("_kept_closest") is not None        # the contact looks used it
    real = recall.closest_on_bone
    import headadapt_addon.core.skin.contact as contact
    monkeypatch.setattr(contact, "closest_on_bone", lambda m, pts, local, idx: real(m, pts, local, None))
    fresh = [build(tpl).equilibrium(r) for r in recipes]
    for a, b in zip(kept, fresh):
        np.testing.assert_array_equal(a, b)
