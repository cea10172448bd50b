"""Issue 17, done when: every real scan in ../shared/scans, adapted from its landmark file through
bpy.ops (the add-on registered from source, the scan a mesh object, its landmarks set as the picker
sets them, Calibrate then Adapt) gives the batch's skin: the same vertices within 1e-6 of the head's
size. None of these landmark files has the paper's FDPs 2.1, 11.1, 10.9 and 10.10 (Fran cannot have
ears): the panels used to stay greyed on all four."""
import json
import pathlib

import numpy as np
import pytest

from headadapt_addon import batch
from headadapt_addon.core import meshio

pytestmark = pytest.mark.slow          # each scan is adapted twice (5-20 s each)

DATA = pathlib.Path(__file__).resolve().parents[1] / "data"
SCANS = {
    "demosthenes": ("demosthenes/demosthenes-low-res.obj", "demosthenes_fdps.json"),
    "fran": ("fran_cyberware/fran_cut.obj", "fran_fdps.json"),
    "nefertiti": ("nefertiti/nefertiti-lowres.obj", "nefertiti_fdps.json"),
    "headsq_ct": ("headsq_ct/headsq_skin.obj", "headsq_ct_fdps.json"),
}


@pytest.mark.parametrize("name", list(SCANS))
def test_a_real_scan_adapts_through_the_panels_as_in_the_batch(name, shared_scans, ui_scene, tmp_path, tpl):
    import bpy

    from headadapt_addon.blender import bridge, landmarks
    from headadapt_addon.core import adapt, anatomy, mpeg4

    scan_path, marks_path = shared_scans / SCANS[name][0], DATA / SCANS[name][1]
    # the batch, as from the command line (its default options): its adapted skin (the fit, scan frame)
    report = batch.run_adapt(scan_path, marks_path, tmp_path / "batch", log=lambda *_a: None,
                             warn=lambda *_a: None)
    fit_batch = meshio.read_mesh(tmp_path / "batch" / "adapted_head.obj")[0]
    verts, tris = meshio.read_mesh(scan_path)[:2]
    points, _meta = meshio.read_landmark_file(marks_path)
    assert not set(mpeg4.CALIBRATION_FDPS) <= set(points)     # the paper's 8 are not all there
    with bpy.context.temp_override(**ui_scene):
        obj = bpy.data.objects.new(name, bridge.new_mesh(name, verts, tris))
        bpy.context.scene.collection.objects.link(obj)
        bpy.context.view_layer.objects.active = obj
        assert bpy.ops.headadapt.use_active_as_scan() == {"FINISHED"}
        landmarks.set_landmarks(obj, points)
        for op in (bpy.ops.headadapt.calibrate, bpy.ops.headadapt.suggest_landmarks, bpy.ops.headadapt.adapt):
            assert op.poll(), op
        assert bpy.ops.headadapt.calibrate() == {"FINISHED"}
        assert bpy.ops.headadapt.adapt() == {"FINISHED"}
        root = bpy.context.scene.headadapt.result_root
        assert root.name == f"{name} adapted"
        skin = bpy.data.objects[f"{name} skin"]
        got = bridge.mesh_arrays(skin, world=True)[0]       # the result overlays the scan object (at the origin)
        ours = json.loads(bpy.context.scene.headadapt.report_json)
    size = float(np.ptp(verts, axis=0).max())
    # the panels' report is the batch's, level by level
    assert ours["best_level"] == report["best_level"] >= 1 and ours["dropped_fdps"] == report["dropped_fdps"]
    for a, b in zip(ours["levels"], report["levels"], strict=True):
        assert a["pairs"] == b["pairs"] and a["E"] == pytest.approx(b["E"], rel=1e-9), (a, b)
    # the same fit: the batch's skin as adapt gives it, then carried (as the panels' result and the
    # batch's .blend do) through the anatomy transfer, which keeps the skin clear of the bone
    result = adapt.adapt(tpl, batch.as_blender_stores(verts), tris, points, batch.adapt_options())
    assert float(np.abs(result.verts_scan - fit_batch).max()) < 1e-6 * size
    want = result.to_scan(anatomy.transfer(tpl, result).parts["skin"])
    err = float(np.abs(got - want).max())
    assert err < 1e-6 * size, (name, err, size)


def test_the_batch_obj_is_the_blend_s_skin_on_a_carved_scan(shared_scans, tmp_path):
    """The OBJ was written before the anatomy's transfer, which seats the eye sockets' hidden lining on
    the eyes and lifts visible skin off the bone: on Nefertiti the .blend's skin lay up to 7.7 mm from
    the OBJ. A studio taking the OBJ as the neutral and the keys from the .blend got two heads."""
    import subprocess
    import sys

    scan, marks = SCANS["nefertiti"]
    out = tmp_path / "o"
    proc = subprocess.run([sys.executable, "-m", "headadapt_addon.batch", "adapt", "--scan", str(shared_scans / scan),
                           "--landmarks", str(DATA / marks), "--out", str(out), "--blend", str(out / "head.blend")],
                          capture_output=True, text=True, cwd=batch.ROOT)
    assert proc.returncode == 0, proc.stderr
    probe = ("import bpy, sys, numpy as np; bpy.ops.wm.open_mainfile(filepath=sys.argv[1]);"
             "skin = next(o for o in bpy.data.objects if o.get('headadapt_part') == 'skin');"
             "m = np.array(skin.matrix_world); v = np.array([list(p.co) for p in skin.data.vertices]);"
             "np.save(sys.argv[2], v @ m[:3, :3].T + m[:3, 3])")
    subprocess.run([sys.executable, "-c", probe, str(out / "head.blend"), str(tmp_path / "skin.npy")], check=True,
                   cwd=batch.ROOT)
    obj = np.array([line.split()[1:4] for line in (out / "adapted_head.obj").read_text().splitlines()
                    if line.startswith("v ")], float)
    report = json.loads((out / "report.json").read_text())
    assert np.abs(np.load(tmp_path / "skin.npy") - obj).max() < 1e-3          # mm: float32 in the .blend
    assert report["stage_seconds"]["transfer"] > 0 and "preview" not in report["stage_seconds"]
    assert sum(report["stage_seconds"].values()) <= report["total_seconds"]    # each stage counted once
