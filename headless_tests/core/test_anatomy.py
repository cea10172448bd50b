"""Anatomy transfer (paper sec 6.2) on adapted generated heads: muscles, skull, eyes, FAPUs."""
import numpy as np
import pytest

from headadapt_addon.core import anatomy
from headadapt_addon.core.mesh import geometry, spatial
from headadapt_addon.core.mesh.inside import winding_numbers

# every test here stands on generated or real heads adapted and transferred (10-20 s)
pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def transferred(legacy_heads):
    return [legacy_heads(seed) for seed in (3, 4, 7)]     # 7: thin lids on the orbit's rim


def fit_sphere(points):
    """Least-squares sphere (centre, radius) through points (n,3)."""
    a = np.c_[2 * points, np.ones(len(points))]
    b = np.sum(points ** 2, axis=1)
    sol = np.linalg.lstsq(a, b, rcond=None)[0]
    return sol[:3], float(np.sqrt(sol[3] + sol[:3] @ sol[:3]))


def test_muscle_ends_lie_on_their_surfaces_and_in_their_regions(tpl, transferred):
    for _, _, ana in transferred:
        skin_q = spatial.MeshQuery(ana.parts["skin"], tpl.skin.tris, backend="numpy")
        for m, ref in zip(ana.muscles, tpl.meta["muscles"]):
            _, face, d = skin_q.closest_points(m["insertion"][None])
            assert d[0] < 1e-9, m["name"]
            names = {tpl.region_names[r] for r in tpl.region[tpl.skin.tris[ref["insertion"]["face"]]]}
            assert names & set(m["regions"]), (m["name"], names)
            bone = ref["attachment"]["part"]
            bone_q = spatial.MeshQuery(ana.parts[bone], tpl.parts[bone].tris, backend="numpy")
            assert bone_q.closest_points(m["attachment"][None])[2][0] < 1e-9, m["name"]


def test_the_skull_stays_inside_the_adapted_skin(tpl, transferred):
    visible = ~tpl.hidden
    bone_t = tpl.skull_tris
    for _, _, ana in transferred:
        for bone in ("cranium", "mandible"):
            w = winding_numbers(ana.parts[bone], ana.parts["skin"], tpl.skin.tris)
            assert w.min() > 0.5, (bone, w.min())
        # and the converse: no visible skin vertex of the adapted head lies inside the bone
        w = winding_numbers(ana.parts["skin"][visible], np.vstack([ana.parts["cranium"], ana.parts["mandible"]]), bone_t)
        assert w.max() < 0.5, np.flatnonzero(visible)[w > 0.5]


def test_the_skull_keeps_its_shape(tpl, transferred):
    # pressing each bone point under its own skin point folded ~85 cranium triangles (orbit
    # floors, cheeks) on these heads; relaxed, at most a handful stay turned; clearing the lids off
    # the orbit's rim turned 9 over on head 7 until bone.relax_cleared relaxed them too (0 now)
    for _, _, ana in transferred:
        for bone in ("cranium", "mandible"):
            folds = geometry.folded(tpl.parts[bone].verts, ana.parts[bone], tpl.parts[bone].tris)
            assert len(folds) <= 2, (bone, len(folds))


def test_eyes_sit_in_their_sockets(tpl, transferred):
    for side in ("l", "r"):
        socket = tpl.region_mask(f"eye_socket_{side}")
        base = tpl.parts[f"eye_{side}"].verts.mean(axis=0) - fit_sphere(tpl.skin.verts[socket])[0]
        for _, _, ana in transferred:
            centre = ana.parts[f"eye_{side}"].mean(axis=0)
            socket_centre, _ = fit_sphere(ana.parts["skin"][socket])
            # the eye keeps its place in the socket: within 2.5 mm of the template's own offset. The eye
            # follows the bone's map, the hidden lining the lids; since each level's ICP rounds fit the lids
            # fully, head 7's thin lids on the orbit's rim take the lining 1.9 and 2.3 mm off (1.15 before;
            # centring the eye on the lining instead moved it against the orbit and put skin in the bone)
            assert np.linalg.norm(centre - socket_centre - base) < 2.5e-3, side


def test_rigid_parts_stay_rigid_and_fapus_are_remeasured(tpl, transferred):
    for _head, _, ana in transferred:
        for name, sim in ana.rigid.items():
            v0, v1 = tpl.parts[name].verts, ana.parts[name]
            d0 = np.linalg.norm(v0[1:] - v0[0], axis=1)
            d1 = np.linalg.norm(v1[1:] - v1[0], axis=1)
            np.testing.assert_allclose(d1, sim.scale * d0, rtol=1e-9)
            assert 0.8 < sim.scale < 1.25, (name, sim.scale)
        for unit in ("IRISD", "ES", "ENS", "MNS", "MW"):
            assert ana.fapus[unit] > 0 and ana.fapus[unit] != tpl.meta["fapus"][unit]
        # the sphincter round the mouth scales with the mouth width
        oris = next(s for s in ana.sphincters if s["name"] == "orbicularis_oris")
        ratio = np.linalg.norm(oris["axes"][0]) / np.linalg.norm(tpl.meta["sphincters"][0]["axes"][0])
        assert ratio == pytest.approx(ana.fapus["MW"] / tpl.meta["fapus"]["MW"], rel=1e-9)


def test_bone_mapped_into_the_mouth_comes_out_through_its_lining(tpl):
    """A mandible point the map puts 1 mm into the mouth bag goes back into the tissue, nearby."""
    bag = np.flatnonzero(tpl.region == tpl.region_names.index("mouth_interior"))
    skin = tpl.skin.verts
    normals = geometry.vertex_normals(skin, tpl.skin.tris)
    mandible = tpl.parts["mandible"].verts
    gap = np.linalg.norm(mandible[:, None] - skin[bag][None], axis=2)
    i, j = np.unravel_index(np.argmin(gap), gap.shape)        # the mandible point nearest the bag
    mapped = mandible.copy()
    mapped[i] = skin[bag[j]] + 0.001 * normals[bag[j]]        # 1 mm into the mouth
    assert winding_numbers(mapped[[i]], skin, tpl.skin.tris)[0] < 0.5
    kept = anatomy.keep_inside(tpl, mandible, mapped, skin)
    assert winding_numbers(kept[[i]], skin, tpl.skin.tris)[0] > 0.5
    assert np.linalg.norm(kept[i] - mapped[i]) < 0.005


def test_a_row_of_skin_inside_the_bone_presses_it_no_deeper_than_one_needs(tpl):
    """bone.clear_visible_skin on the template: six neighbouring visible vertices of the nose put 0.5
    mm inside the cranium come out of it, and the bone under them moves by about what one of them
    needs (each bone vertex the largest step any of them asks, not their sum: summed, the six pressed
    the nose's bone 3.8 mm)."""
    from scipy.spatial import cKDTree

    from headadapt_addon.core.anatomy.bone import clear_visible_skin

    skin, cr, md = (tpl.parts[k].verts for k in ("skin", "cranium", "mandible"))
    bone = np.vstack([cr, md])
    query = spatial.MeshQuery(bone, tpl.skull_tris)
    nose = np.flatnonzero(tpl.region_mask("nose") & ~tpl.hidden)
    first = nose[np.argmin(query.closest_points(skin[nose])[2])]
    row = nose[cKDTree(skin[nose]).query(skin[first], k=6)[1]]
    moved = skin.copy()
    near = query.closest_points(skin[row])[0]
    inward = (near - skin[row]) / np.linalg.norm(near - skin[row], axis=1, keepdims=True)
    moved[row] = near + 0.0005 * inward
    assert (winding_numbers(moved[row], bone, tpl.skull_tris) > 0.5).all()
    cleared = np.vstack(clear_visible_skin(tpl, moved, cr, md))
    assert (winding_numbers(moved[row], cleared, tpl.skull_tris) < 0.5).all()
    press = np.linalg.norm(cleared - bone, axis=1)
    assert 0.0005 < press.max() < 0.0015, press.max()


def test_a_visible_skin_vertex_a_sliver_inside_the_bone_is_lifted_out_and_a_deep_one_is_not(tpl):
    """lift.lift_visible_skin, the transfer's last guarantee, on the template: a visible forehead
    vertex pushed 0.2 mm into the cranium comes out along its normal by under 0.5 mm; one pushed
    3 mm in is left where it is and named (a fit gone wrong, not a sliver of rim)."""
    from headadapt_addon.core.anatomy.lift import lift_visible_skin

    skin, cr, md = (tpl.parts[k].verts for k in ("skin", "cranium", "mandible"))
    bone = np.vstack([cr, md])
    query = spatial.MeshQuery(bone, tpl.skull_tris)
    forehead = np.flatnonzero(tpl.region_mask("forehead") & ~tpl.hidden)
    q, _, dist = query.closest_points(skin[forehead])
    a, b = forehead[np.argsort(dist)[[0, 1]]]            # the two visible vertices nearest the bone
    moved = skin.copy()
    for v, depth in ((a, 0.0002), (b, 0.003)):
        p = query.closest_points(skin[v][None])[0][0]
        inward = (p - skin[v]) / np.linalg.norm(p - skin[v])
        moved[v] = p + depth * inward
    assert (winding_numbers(moved[[a, b]], bone, tpl.skull_tris) > 0.5).all()
    lifted, out, still = lift_visible_skin(tpl, moved, cr, md)
    assert list(out) == [a] and list(still) == [b]
    assert winding_numbers(lifted[[a]], bone, tpl.skull_tris)[0] < 0.5
    assert 0.0 < np.linalg.norm(lifted[a] - moved[a]) < 0.0005
    assert np.array_equal(np.delete(lifted, a, axis=0), np.delete(moved, a, axis=0))


def test_a_visible_skin_vertex_a_millimetre_inside_the_bone_comes_out_with_its_neighbours(tpl):
    """lift.lift_visible_skin beyond the 0.5 mm sliver: a visible forehead vertex 1.2 mm inside the
    cranium (a statue's lid on the orbit's rim ends so on some processors) comes out through the bone's
    nearest face with the skin round it along, no skin triangle turned over, every vertex that moved
    within the bump's fading rings, and no visible vertex left inside."""
    from headadapt_addon.core.anatomy.lift import lift_visible_skin

    skin, cr, md = (tpl.parts[k].verts for k in ("skin", "cranium", "mandible"))
    bone = np.vstack([cr, md])
    query = spatial.MeshQuery(bone, tpl.skull_tris)
    forehead = np.flatnonzero(tpl.region_mask("forehead") & ~tpl.hidden)
    v = forehead[np.argmin(query.closest_points(skin[forehead])[2])]
    p = query.closest_points(skin[v][None])[0][0]
    moved = skin.copy()
    moved[v] = p + 0.0012 * (p - skin[v]) / np.linalg.norm(p - skin[v])
    assert winding_numbers(moved[[v]], bone, tpl.skull_tris)[0] > 0.5
    lifted, out, still = lift_visible_skin(tpl, moved, cr, md)
    visible = ~tpl.hidden
    assert len(still) == 0 and v in out
    assert (winding_numbers(lifted[visible], bone, tpl.skull_tris) > 0.5).sum() == 0
    assert len(geometry.folded(tpl.skin.verts, lifted, tpl.skin.tris)) == 0
    assert 0.0012 < np.linalg.norm(lifted[v] - moved[v]) < 0.002 + 1e-6
    assert 1 < len(out) < 200                             # its neighbours came along, not the whole skin


def test_a_neighbour_the_bump_pushes_into_the_bone_is_lifted_again_before_the_bump_is_judged(tpl, monkeypatch):
    """lift.lift_visible_skin on a lid at the orbit's rim, where the bone folds round the skin: taking
    a vertex 0.8 mm deep out through the bone's nearest face drags a neighbour a sliver into the bone
    (Nefertiti's left lid under numpy 2: vertex 3268 out, 3269 back in, so as many vertices stayed
    inside and the bump was refused). The drag is made here by wrapping the bump; the neighbour is
    lifted again before the count, and the bump kept: no visible vertex left inside, nothing folded."""
    from headadapt_addon.core.anatomy import lift

    skin, cr, md = (tpl.parts[k].verts for k in ("skin", "cranium", "mandible"))
    bone = np.vstack([cr, md])
    query = spatial.MeshQuery(bone, tpl.skull_tris)
    forehead = np.flatnonzero(tpl.region_mask("forehead") & ~tpl.hidden)
    v = forehead[np.argmin(query.closest_points(skin[forehead])[2])]
    ring = np.unique(tpl.skin.tris[np.any(tpl.skin.tris == v, axis=1)])
    u = ring[ring != v][0]
    p = query.closest_points(skin[v][None])[0][0]
    moved = skin.copy()
    moved[v] = p + 0.0008 * (p - skin[v]) / np.linalg.norm(p - skin[v])
    bump = lift._bump

    def dragging(tpl_, skin_, at, to, rings=3):
        out = bump(tpl_, skin_, at, to, rings)
        q = query.closest_points(out[u][None])[0][0]
        out[u] = q + 0.0001 * (q - out[u]) / np.linalg.norm(q - out[u])    # 0.1 mm into the bone
        return out

    monkeypatch.setattr(lift, "_bump", dragging)
    lifted, out, still = lift.lift_visible_skin(tpl, moved, cr, md)
    visible = ~tpl.hidden
    assert len(still) == 0 and v in out and u in out
    assert (winding_numbers(lifted[visible], bone, tpl.skull_tris) > 0.5).sum() == 0
    assert len(geometry.folded(tpl.skin.verts, lifted, tpl.skin.tris)) == 0


@pytest.fixture(scope="module")
def scan_like(tpl, testheads):
    # two scan-like heads (open eyes, their eyeballs scanned) whose lids' FDPs made eq 25 size the two
    # eyes 2.2 mm apart in radius
    from headadapt_addon.core import adapt

    out = []
    for seed in (301, 313):
        head = testheads.make_head(seed, style="scan")
        res = adapt.adapt(tpl, head.scan_verts, head.scan_tris, head.clicks_11)
        out.append((head, res, anatomy.transfer(tpl, res)))
    return out


def test_both_eyes_keep_one_size(tpl, scan_like):
    # the lids' opening says how open an eye is, not how big the eyeball is: both eyes keep the
    # template's size in the calibrated head
    for _, _, ana in scan_like:
        for eye in ("eye_l", "eye_r"):
            r0 = np.linalg.norm(tpl.parts[eye].verts - tpl.parts[eye].verts.mean(axis=0), axis=1)
            r = np.linalg.norm(ana.parts[eye] - ana.parts[eye].mean(axis=0), axis=1)
            np.testing.assert_allclose(r, r0, rtol=1e-9, err_msg=eye)


def test_an_open_eye_meets_the_scanned_eye(tpl, scan_like):
    # the generated heads' eyeballs are scanned: the front of each eye is where the generator's eye has
    # its front (along the gaze, mm of the true head). The old rule left these eyes up to 0.8 mm out
    # of the scanned eye or pushed them 1 mm behind it as if behind a closed lid: 0.85, 0.75, 1.28 and
    # 1.26 mm off; now at most 0.32
    for head, res, ana in scan_like:
        to_scan, mm = res.similarity.inverse(), 1000.0 / head.similarity[0]
        for eye in ("eye_l", "eye_r"):
            gaze = to_scan.rotation @ ana.rigid[eye].rotation @ np.asarray(tpl.meta["eyes"][eye]["gaze"])
            gaze /= np.linalg.norm(gaze)
            front = (to_scan.apply(ana.parts[eye]) @ gaze).max() - (head.true_parts[eye] @ gaze).max()
            assert abs(front * mm) < 0.5, (eye, front * mm)
