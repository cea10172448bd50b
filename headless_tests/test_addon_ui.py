"""The add-on's Blender side: landmark picking with synthetic rays, storage, panels, operators."""
from types import SimpleNamespace

import numpy as np
import pytest

import headadapt_addon
from headadapt_addon.core.template import load_template


@pytest.fixture
def addon(clean_scene):
    headadapt_addon.register()
    yield clean_scene
    headadapt_addon.unregister()


@pytest.fixture(scope="module")
def tpl():
    return load_template()


def _scan_object(tpl, scale=1000.0, name="scan"):
    """The template skin as a stand-in scan, in mm, moved away from the origin."""
    import bpy
    from headadapt_addon import bridge

    obj = bpy.data.objects.new(name, bridge.new_mesh(name, tpl.skin.verts * scale, tpl.skin.tris))
    bpy.context.scene.collection.objects.link(obj)
    obj.location = (0.3, -0.2, 0.1)
    bpy.context.view_layer.update()
    return obj


def test_clicks_place_fdps_on_the_surface_and_move_to_the_next(addon, tpl):
    from headadapt_addon import landmarks

    scan = _scan_object(tpl)
    m = np.array(scan.matrix_world)
    pts = {}
    for name in ("3.7", "9.3", "2.1"):
        target = tpl.fdp_points()[name] * 1000.0
        world = m[:3, :3] @ target + m[:3, 3]
        origin = world + np.array([0.0, -0.5, 0.0])          # looking from the front, as a viewport does
        pts, ok = landmarks.place(scan, pts, name, origin, world - origin)
        assert ok, name
        assert np.linalg.norm(pts[name] - target) < 0.5, name  # local (scan) coordinates, mm
    # a ray that misses changes nothing
    same, ok = landmarks.place(scan, pts, "3.12", np.array([5000.0, 5000.0, 5000.0]), np.array([0.0, 0.0, 1.0]))
    assert not ok and same == pts
    assert landmarks.next_missing(pts, after="2.1") == "2.2"
    assert landmarks.next_missing(pts, after="3.6") == "3.8"
    # ctrl-click near 9.3 removes it, a click far from every point removes nothing
    world = m[:3, :3] @ pts["9.3"] + m[:3, 3]
    pts2, removed = landmarks.remove_near(scan, pts, world + [0, -0.5, 0], [0, 1, 0], 5.0)
    assert removed == "9.3" and "9.3" not in pts2


def test_mirror_suggestion_lands_on_the_partner(addon, tpl):
    from headadapt_addon import landmarks

    true = {k: p * 1000 for k, p in tpl.fdp_points().items()}
    pts = {k: true[k] for k in ("3.7", "3.12", "8.3", "8.4", "2.1", "9.3", "11.1", "4.5")}
    guess = landmarks.mirror_suggestion(pts, "4.6")
    assert np.linalg.norm(guess - true["4.6"]) < 1.0


def test_landmarks_survive_save_and_reload(addon, tpl, tmp_path):
    import bpy
    from headadapt_addon import landmarks

    scan = _scan_object(tpl)
    pts = {k: p * 1000 for k, p in tpl.fdp_points().items()}
    landmarks.set_landmarks(scan, pts)
    path = tmp_path / "scene.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path))
    bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
    bpy.ops.wm.open_mainfile(filepath=str(path))
    back = landmarks.get_landmarks(bpy.data.objects["scan"])
    assert list(back) == list(pts)
    for k in pts:
        np.testing.assert_array_equal(back[k], pts[k])


class _Recorder:
    """Stands in for UILayout: records every call, returns itself for sub-layouts."""

    def __init__(self):
        self.calls = []
        self.enabled = True

    def __getattr__(self, name):
        def call(*args, **kwargs):
            self.calls.append((name, args, kwargs))
            if name in ("operator",):
                return type("OpProps", (), {})()
            return self
        return call


def test_every_panel_draws_on_empty_and_full_scenes(addon, tpl):
    import bpy
    from headadapt_addon import landmarks, ui

    def draw_all():
        texts = []
        for cls in ui.classes:
            rec = _Recorder()
            cls.draw(SimpleNamespace(layout=rec), bpy.context)   # the panel's own draw()
            texts += [kw.get("text", "") for name, _a, kw in rec.calls if name == "label"]
        return texts

    empty = draw_all()
    assert "Pick the scanned head" in empty and "No adaptation yet" in empty
    bpy.ops.headadapt.add_template()
    scan = _scan_object(tpl)
    bpy.context.scene.headadapt.scan = scan
    landmarks.set_landmarks(scan, {k: p * 1000 for k, p in tpl.fdp_points().items()})
    full = draw_all()
    assert any(t.startswith("In scene:") for t in full)
    assert "Calibration FDPs: all placed" in full
