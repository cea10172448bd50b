"""The scan-like test heads (tools/testheads.py, style "scan"): only what scanners see is on the scan,
the eyeballs are, big holes are, clicks are people's (spread as specified, never at a template
vertex, none in a hole), and a seed always makes the same head."""
import numpy as np
import pytest
from scipy.spatial import cKDTree

from headadapt_addon.core import mpeg4
from headadapt_addon.core.adapt import calibration
from headadapt_addon.core.mesh import spatial

MM = 1e-3


@pytest.fixture(scope="module")
def heads(testheads):
    return [testheads.make_head(seed, style="scan") for seed in (2, 5)]


@pytest.fixture(scope="module")
def clean_head(testheads):
    """Seed 2's head without the noise (the same geometry: every per-head draw is made either way)."""
    return testheads.make_head(2, style="scan", noise_mm=0.0)


def _unplace(head, x):
    """Scan frame -> template frame (metres)."""
    s, r, t = head.similarity
    return (np.asarray(x) - t) @ r / s


def _region(tpl, *names):
    return np.isin(tpl.region, [tpl.region_names.index(n) for n in names])


@pytest.mark.slow
def test_a_seed_makes_the_same_head(testheads, heads):
    testheads._scan_geometry.cache_clear()          # made again from scratch, not from the cache
    again = testheads.make_head(2, style="scan")
    first = heads[0]
    np.testing.assert_array_equal(first.scan_verts, again.scan_verts)
    np.testing.assert_array_equal(first.scan_tris, again.scan_tris)
    np.testing.assert_array_equal(first.true_template, again.true_template)
    assert first.fdp_clicks.keys() == again.fdp_clicks.keys()
    for k in first.fdp_clicks:
        np.testing.assert_array_equal(first.fdp_clicks[k], again.fdp_clicks[k])
    assert first.meta == again.meta and first.markers.keys() == again.markers.keys()
    other = testheads.make_head(5, style="scan")
    assert len(other.scan_verts) != len(first.scan_verts) or not np.allclose(other.scan_verts, first.scan_verts)


def test_no_surface_a_scanner_cannot_see(tpl, clean_head):
    head = clean_head
    q = spatial.MeshQuery(head.scan_verts, head.scan_tris, backend="bvh")
    d = q.closest_points(head.true_template)[2] / head.similarity[0]
    # the mouth's inside and the eye sockets beyond their own edge (vertices of a quad outside the
    # region are the lips' or lids' edge, which is seen)
    for names in (("mouth_interior",), ("eye_socket_l", "eye_socket_r")):
        region = _region(tpl, *names)
        edge = np.zeros(len(region), bool)
        edge[tpl.skin.quads[~region[tpl.skin.quads].all(axis=1)].ravel()] = True
        inner = region & ~edge
        assert inner.sum() > 100, names
        assert np.mean(d[inner] < 1 * MM) < 0.05, (names, np.mean(d[inner] < 1 * MM))   # 0-3.4 % on seeds 0-5, 100
    # the seen face is most of the face, and the vertices said to be on the scan are on it
    face = _region(tpl, *("forehead", "nose", "cheek_l", "cheek_r", "upper_lip", "lower_lip", "chin_jaw"))
    assert head.true_on_scan[face].mean() > 0.8
    assert np.all(d[head.true_on_scan] < 2 * MM)


def test_the_eyeballs_front_is_on_the_scan_and_its_back_is_not(tpl, clean_head):
    head = clean_head
    s = head.similarity[0]
    tree = cKDTree(_unplace(head, head.scan_verts))
    for eye, pupil in (("eye_l", "3.5"), ("eye_r", "3.6")):
        ev = _unplace(head, head.true_parts[eye])
        centre = ev.mean(axis=0)
        d, _ = tree.query(ev)
        front, back = ev[:, 1] < centre[1] - 0.005, ev[:, 1] > centre[1]   # the template looks along -y
        assert (d[front] < 1e-6).sum() >= 5, (eye, (d[front] < 1e-6).sum())
        assert np.all(d[back] > 1 * MM), eye
        q = spatial.MeshQuery(head.scan_verts, head.scan_tris, backend="bvh")
        assert q.closest_points(head.true_fdps[pupil][None])[2][0] / s < 0.5 * MM, pupil
        assert pupil in head.fdp_clicks


def test_big_holes_under_the_chin_in_a_cheek_and_at_the_back(heads):
    for head in heads:
        s = head.similarity[0]
        q = spatial.MeshQuery(head.scan_verts, head.scan_tris, backend="bvh")
        kinds = {h["kind"].split("_")[0]: h for h in head.holes}
        sizes = {"under": (15, 20), "cheek": (10, 15), "back": (25, 40)}
        for kind, (lo, hi) in sizes.items():
            hole = kinds[kind]
            r = hole["radius"] / s / MM
            assert lo <= r <= hi, (kind, r)
            # no scan within most of the radius of its centre (the centre lies on the true skin;
            # triangles go by their centroids, and the skin curves away from the cutting sphere)
            assert q.closest_points(hole["centre"][None])[2][0] / s > 0.6 * r * MM, kind
        assert 1 <= sum(h["kind"] == "small" for h in head.holes) <= 4


def test_clicks_in_holes_are_omitted_and_the_click_sets_are_whole(tpl, testheads, heads):
    omitted = []
    for head in heads:
        for k, ref in tpl.meta["fdps"].items():
            if ref["part"] not in testheads.SCANNED_PARTS:
                continue
            p = head.true_fdps[k]
            if any(np.linalg.norm(p - h["centre"]) < h["radius"] for h in head.holes):
                assert k not in head.fdp_clicks and k not in head.markers, k
                omitted.append(k)
        assert sorted(head.clicks_8) == sorted(mpeg4.CLICKS_8)      # holes never hide the click sets
        assert sorted(head.clicks_11) == sorted(mpeg4.CLICKS_11)
        assert len(head.markers) >= 12 and not set(head.markers) & set(mpeg4.CLICKS_11)
        for k, p in head.markers.items():                           # markers are the truth itself
            np.testing.assert_allclose(p, head.true_fdps[k])
    assert omitted, "no FDP fell in a hole on these heads: the check checked nothing"


def test_clicks_are_never_at_a_template_vertex(testheads, heads):
    for head in heads:
        s = head.similarity[0]
        tree = cKDTree(np.vstack([head.true_parts[n] for n in testheads.SCANNED_PARTS]))
        d, _ = tree.query(np.array(list(head.fdp_clicks.values())))
        assert d.min() / s > 0.05 * MM, d.min() / s / MM
        # and they are on the scan
        q = spatial.MeshQuery(head.scan_verts, head.scan_tris, backend="bvh")
        assert q.closest_points(np.array(list(head.fdp_clicks.values())))[2].max() / s < 1e-6


@pytest.mark.slow
def test_clicks_spread_as_people_disagree(tpl, testheads):
    """20 draws of people's clicks (2 heads x 10 click seeds): about 2 mm std per tangent axis, 3 mm
    along the lid and lip lines (the snap to a curved scan takes a little off)."""
    generic, line = [], []
    for seed in (2, 5):
        for click_seed in range(10):
            head = testheads.make_head(seed, style="scan", click_seed=click_seed)
            for k in ("2.10", "9.3", "4.1", "4.2", "5.3", "5.4", "9.15", "8.1", "8.2", "8.3", "8.4"):
                if k not in head.fdp_clicks:        # in a hole on this head
                    continue
                ref = tpl.meta["fdps"][k]
                c = _unplace(head, head.true_parts["skin"])[tpl.skin.tris[ref["face"]]]
                n = np.cross(c[1] - c[0], c[2] - c[0])
                n /= np.linalg.norm(n)
                e1 = np.array([1.0, 0.0, 0.0]) - n[0] * n
                e1 /= np.linalg.norm(e1)
                e2 = np.cross(n, e1)
                off = _unplace(head, head.fdp_clicks[k]) - _unplace(head, head.true_fdps[k])
                (line if k in testheads.LINE_FDPS else generic).append([off @ e1 / MM, off @ e2 / MM])
    generic, line = np.array(generic), np.array(line)
    assert len(generic) >= 100 and len(line) == 80
    g = generic.std(axis=0)
    assert np.all((1.4 < g) & (g < 2.6)), g
    along, across = line.std(axis=0)
    assert 2.2 < along < 3.8 and 1.2 < across < 2.6 and along > across, (along, across)


def test_faces_differ_from_the_template_by_several_mm(tpl, testheads, heads):
    face = testheads.face_mask(tpl)
    rms = []
    for head in heads:
        v = _unplace(head, head.true_template)
        sim = calibration.umeyama(v[face], tpl.skin.verts[face])
        rms.append(np.sqrt(np.mean(np.sum((sim.apply(v[face]) - tpl.skin.verts[face]) ** 2, axis=1))) / MM)
    assert min(rms) > 3.0, rms
    assert {h.meta["unit"] for h in heads} == {"mm", "m"}      # both units come up (seeds 2 and 5)


def test_a_head_turned_on_its_neck(tpl, testheads, heads):
    """neck_tilt turns the head on its neck as a person sits in a scanner: the head moves rigidly,
    the neck's cut stays, the skin between bends without folding."""
    from headadapt_addon.core.mesh import geometry

    turned = testheads.make_head(2, style="scan", neck_tilt=10.0)
    before, after = _unplace(heads[0], heads[0].true_template), _unplace(turned, turned.true_template)
    face = testheads.face_mask(tpl)
    rigid = calibration.umeyama(before[face], after[face])
    assert np.abs(rigid.apply(before[face]) - after[face]).max() < 1e-9        # the head: a rigid move
    angle = np.degrees(np.arccos(np.clip((np.trace(rigid.rotation) - 1) / 2, -1, 1)))
    assert angle > 1.0, angle                                                   # ... that turned it
    neck = _region(tpl, "neck")
    cut = neck & (before[:, 2] <= np.percentile(before[neck, 2], 2))
    assert np.abs(after[cut] - before[cut]).max() < 1e-9                       # the neck's cut stays
    assert len(geometry.folded(before, after, tpl.skin.tris)) == 0
    assert ("neck_tilt_std_deg", 10.0) in turned.meta["targets"]


@pytest.mark.slow
def test_a_phones_coarse_scan_and_sloppier_people(tpl, testheads, heads):
    """bench adapt's --coarse and --click-noise-mm families: a scan of about 4,000 vertices with the
    clicks on it and the panel's 8 among them; people who disagree twice as much click about twice as
    far from the truth."""
    first = heads[0]
    coarse = testheads.make_head(2, style="scan", **testheads.PHONE_SCAN)
    assert 3000 < len(coarse.scan_verts) < 6000 < len(first.scan_verts)
    s = coarse.similarity[0]
    q = spatial.MeshQuery(coarse.scan_verts, coarse.scan_tris)
    assert q.closest_points(np.array(list(coarse.fdp_clicks.values())))[2].max() / s < 1e-6
    assert set(mpeg4.CLICKS_8) <= set(coarse.fdp_clicks)

    sloppy = testheads.make_head(2, style="scan", click_noise_mm=4.0)    # 6 mm along the lines
    names = [k for k in first.fdp_clicks if tpl.meta["fdps"][k]["part"] == "skin"]
    off = [np.linalg.norm([_unplace(h, h.fdp_clicks[k]) - _unplace(h, h.true_fdps[k]) for k in names], axis=1)
           for h in (first, sloppy)]
    ratio = np.median(off[1]) / np.median(off[0])
    assert 1.6 < ratio < 2.4, ratio
