"""Every operator through bpy.ops on the bundled template and sample scan: results, undo, bad input."""
import json
import pathlib
import tempfile

import numpy as np
import pytest

from headadapt_addon.batch import SAMPLE_DIR
from headadapt_addon.core import meshio


def _add_scan(name="scan", with_faces=True, path=SAMPLE_DIR / "scan.ply"):
    import bpy

    from headadapt_addon.blender import bridge

    v, t = meshio.read_mesh(path)
    mesh = bridge.new_mesh(name, v, t) if with_faces else bridge.new_mesh(name, v, np.zeros((0, 3), int))
    obj = bpy.data.objects.new(name, mesh)
    bpy.context.scene.collection.objects.link(obj)
    bpy.context.view_layer.objects.active = obj
    obj.select_set(True)
    return obj


def _verts(obj):
    from headadapt_addon.blender import bridge
    return bridge.mesh_arrays(obj, world=False)[0]


@pytest.mark.slow
def test_the_whole_workflow_runs_through_bpy_ops(ui_scene, capfd):
    import bpy

    from headadapt_addon.blender import landmarks

    with bpy.context.temp_override(**ui_scene):
        assert bpy.ops.headadapt.add_template() == {"FINISHED"}
        scan = _add_scan()
        before = _verts(scan)
        assert bpy.ops.headadapt.use_active_as_scan() == {"FINISHED"}
        assert bpy.ops.headadapt.import_landmarks(filepath=str(SAMPLE_DIR / "landmarks.json")) == {"FINISHED"}
        clicks = landmarks.get_landmarks(scan)
        assert len(clicks) == len(meshio.read_landmarks(SAMPLE_DIR / "landmarks.json"))
        # keep only the calibration FDPs, let the add-on suggest the rest
        keep = {k: clicks[k] for k in ("2.1", "11.1", "3.7", "3.12", "8.3", "8.4", "10.9", "10.10")}
        landmarks.set_landmarks(scan, keep)
        assert bpy.ops.headadapt.suggest_landmarks() == {"FINISHED"}
        suggested = landmarks.get_landmarks(scan, landmarks.SUGGESTED_PROP)
        err = [np.linalg.norm(suggested[k] - clicks[k]) for k in suggested if k in clicks]
        assert len(err) > 50 and np.median(err) < 6.0          # mm on the sample scan
        assert bpy.ops.headadapt.accept_suggestions() == {"FINISHED"}
        landmarks.set_landmarks(scan, clicks)
        for suffix in (".json", ".pp"):
            path = pathlib.Path(tempfile.mkdtemp()) / f"l{suffix}"
            assert bpy.ops.headadapt.export_landmarks(filepath=str(path)) == {"FINISHED"}
            back = meshio.read_landmarks(path)
            assert all(np.array_equal(back[k], clicks[k]) for k in clicks)
        assert bpy.ops.headadapt.clear_landmark(fdp="9.3") == {"FINISHED"}
        assert "9.3" not in landmarks.get_landmarks(scan)
        # the modal picker starts (Blender reports a started modal operator as PASS_THROUGH to Python)
        assert bpy.ops.headadapt.pick_landmarks("INVOKE_DEFAULT") & {"RUNNING_MODAL", "PASS_THROUGH"}
        landmarks.set_landmarks(scan, clicks)
        assert bpy.ops.headadapt.calibrate() == {"FINISHED"}
        assert 0 <= bpy.context.scene.headadapt.calibration_rms_mm < 10
        capfd.readouterr()
        assert bpy.ops.headadapt.adapt() == {"FINISHED"}
        said = capfd.readouterr()
        root = bpy.context.scene.headadapt.result_root
        assert root is not None and root.users_collection[0].name.startswith("HeadAdapt result")
        skin = next(o for o in root.children_recursive if o.get("headadapt_part") == "skin")
        assert "HeadAdapt distance" in skin.data.color_attributes
        rep = json.loads(bpy.context.scene.headadapt.report_json)
        assert rep["levels"][rep["best_level"]]["E_d_rms_mm"] < 1.0
        assert rep["unfolded"]["folded_left"] == 0 and rep["calibration"]["scan_pieces_turned"] == 0
        # the operator's INFO report states the seen-skin RMS and the folds left (Blender prints reports)
        out = rep["outcome"]
        info = next(s for s in (said.out + said.err).splitlines() if s.startswith("Info: adapted:"))
        assert "fit ok" in info and "0 folded triangles left" in info, info
        assert f"seen-skin RMS {out['seen_rms_mm']:.2f} mm over {out['seen_vertices']} vertices" in info, info
        np.testing.assert_array_equal(_verts(scan), before)     # the scan is never changed


def test_adapt_after_calibrate_fits_the_scan_calibrate_prepared(ui_scene):
    """Calibrate's prepared scan is kept for the Adapt of the same scan, clicks and options (and for
    the Adapt after that): the report says so and the head is the one an Adapt alone makes, to the
    bit. A click moved since is calibrated anew."""
    import bpy

    from headadapt_addon.blender import landmarks

    def adapted(levels=-1):
        assert bpy.ops.headadapt.adapt(levels=levels) == {"FINISHED"}
        root = bpy.context.scene.headadapt.result_root
        skin = next(o for o in root.children_recursive if o.get("headadapt_part") == "skin")
        rep = json.loads(bpy.context.scene.headadapt.report_json)
        return _verts(skin), rep["calibration"].get("scan_prepared_before", False)

    with bpy.context.temp_override(**ui_scene):
        scan = _add_scan()
        assert bpy.ops.headadapt.use_active_as_scan() == {"FINISHED"}
        assert bpy.ops.headadapt.import_landmarks(filepath=str(SAMPLE_DIR / "landmarks.json")) == {"FINISHED"}
        bpy.context.scene.headadapt.max_levels = 1
        alone, reused = adapted()
        assert not reused
        assert bpy.ops.headadapt.calibrate() == {"FINISHED"}
        for _ in range(2):
            verts, reused = adapted()
            assert reused and np.array_equal(verts, alone)
        assert adapted(levels=0)[1]                          # Level 0 Only: the same calibration
        clicks = landmarks.get_landmarks(scan)
        clicks["9.3"] = clicks["9.3"] + 0.5                 # the nose tip half a millimetre off
        landmarks.set_landmarks(scan, clicks)
        verts, reused = adapted()
        assert not reused and not np.array_equal(verts, alone)


@pytest.mark.slow
def test_adapt_warns_when_the_fit_cannot_be_trusted_and_the_report_panel_says_why(ui_scene, tmp_path, capfd):
    """Level 0 only on the sample scan with a fringe over the forehead and a wrong click (the real
    untrustworthy fit of test_adapt.fringe_scan): the operator finishes (the result is there to
    look at) but reports a WARNING naming why, and the Report panel shows the outcome and each warning."""
    import bpy

    from headadapt_addon.ui import panels as ui
    from headless_tests.blender.test_addon_ui import _Recorder
    from headless_tests.core.test_adapt import fringe_scan

    scan_path, marks = fringe_scan(tmp_path)
    with bpy.context.temp_override(**ui_scene):
        scan = _add_scan(path=scan_path)
        bpy.context.scene.headadapt.scan = scan
        assert bpy.ops.headadapt.import_landmarks(filepath=str(marks)) == {"FINISHED"}
        capfd.readouterr()
        assert bpy.ops.headadapt.adapt(levels=0) == {"FINISHED"}
        said = capfd.readouterr()
        rep = json.loads(bpy.context.scene.headadapt.report_json)
        out = rep["outcome"]
        assert out["ok"] is False and bpy.context.scene.headadapt.result_root is not None
        printed = (said.out + said.err).splitlines()
        assert not any(s.startswith("Info: adapted") for s in printed), printed
        warning = next(s for s in printed if s.startswith("Warning: adapted:"))
        assert "fit NOT trustworthy" in warning and "did not reach the scan" in warning, warning
        assert "FDP 5.1:" in warning and "(dropped)" in warning, warning
        rec = _Recorder()
        ui.draw_report(rec, bpy.context)
    labels = [(kw.get("text", ""), kw.get("icon")) for name, _a, kw in rec.calls if name == "label"]
    texts = [t for t, _icon in labels]
    assert ("Fit NOT trustworthy", "ERROR") in labels
    assert f"{out['folds_left']} folded triangles left" in texts
    assert f"seen-skin RMS {out['seen_rms_mm']:.2f} mm over {out['seen_vertices']} vertices" in texts
    flowed = " ".join(texts)
    for w in out["warnings"]:
        assert w in flowed, w
    assert sum(icon == "ERROR" for _t, icon in labels) == 1 + len(out["warnings"])


@pytest.mark.slow
def test_undo_restores_the_scene_after_adapt(ui_scene):
    import bpy

    with bpy.context.temp_override(**ui_scene):
        scan = _add_scan()
        bpy.context.scene.headadapt.scan = scan
        bpy.ops.headadapt.import_landmarks(filepath=str(SAMPLE_DIR / "landmarks.json"))
        bpy.ops.ed.undo_push(message="before adapt")
        n_objects = len(bpy.data.objects)
        assert bpy.ops.headadapt.adapt(levels=1) == {"FINISHED"}
        assert len(bpy.data.objects) > n_objects
        assert "UNDO" in bpy.types.HEADADAPT_OT_adapt.bl_options
        bpy.ops.ed.undo_push(message="Adapt")   # what the UI does after an operator flagged UNDO
        bpy.ops.ed.undo()
        assert len(bpy.data.objects) == n_objects
        assert not any(c.name.startswith("HeadAdapt result") for c in bpy.data.collections if c.users)


def test_bad_input_gets_a_clear_report_and_changes_nothing(ui_scene, tmp_path):
    import bpy

    from headadapt_addon.blender import landmarks

    with bpy.context.temp_override(**ui_scene):
        # no scan: the operators that need one cannot run
        assert not bpy.ops.headadapt.calibrate.poll()
        assert not bpy.ops.headadapt.adapt.poll()
        # a scan with no faces
        empty = _add_scan("points", with_faces=False)
        with pytest.raises(RuntimeError, match="no faces"):
            bpy.ops.headadapt.use_active_as_scan()
        assert bpy.context.scene.headadapt.scan is None
        # missing calibration FDPs
        scan = _add_scan()
        bpy.context.scene.headadapt.scan = scan
        landmarks.set_landmarks(scan, {"3.7": [0.0, 0.0, 0.0]})
        assert not bpy.ops.headadapt.calibrate.poll() and not bpy.ops.headadapt.adapt.poll()
        # a landmark file made for another template
        other = tmp_path / "other.json"
        other.write_text(json.dumps({"points": {"3.7": [1, 2, 3]}, "template_sha256": "0" * 64}))
        with pytest.raises(RuntimeError, match="another template"):
            bpy.ops.headadapt.import_landmarks(filepath=str(other))
        assert list(landmarks.get_landmarks(scan)) == ["3.7"]
        # an unwritable output path
        blocker = tmp_path / "file"
        blocker.write_text("")
        with pytest.raises(RuntimeError, match="cannot write"):
            bpy.ops.headadapt.export_landmarks(filepath=str(blocker / "sub" / "l.json"))
        assert empty.name in bpy.data.objects


@pytest.mark.slow
def test_batch_writes_a_blend_that_reopens_with_the_report(tmp_path):
    import subprocess
    import sys

    out = tmp_path / "o"
    proc = subprocess.run([sys.executable, "-m", "headadapt_addon.batch", "adapt", "--scan", str(SAMPLE_DIR / "scan.ply"),
                           "--landmarks", str(SAMPLE_DIR / "landmarks.json"), "--out", str(out), "--levels", "1",
                           "--blend", str(out / "head.blend")], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert not list(out.glob(".*")), list(out.glob(".*"))          # no temporary or backup file left behind
    # the bake (20-50 s) prints its progress: a line per tenth, ending at 100%
    baking = [line for line in proc.stdout.splitlines() if line.strip().startswith("baking")]
    assert 5 <= len(baking) <= 11 and "100.0%" in baking[-1], proc.stdout
    check = ("import bpy, json, sys; bpy.ops.wm.open_mainfile(filepath=sys.argv[1]);"
             "root = bpy.data.objects['HA Adapted head']; rep = json.loads(root['headadapt_report']);"
             "scan = bpy.data.objects['scan'];"
             "print('OK', len(rep['levels']), 'HeadAdapt report' in bpy.data.texts, 'headadapt_landmarks' in scan,"
             " len([o for o in root.children_recursive if o.type == 'MESH']));"   # 8 parts, the heat legend
             "cam = bpy.context.scene.camera; print('VIEW', cam.name, cam.type,"
             " [o.type for o in bpy.data.objects if o.type == 'LIGHT']);"
             "skin = next(o for o in root.children_recursive if o.get('headadapt_part') == 'skin');"
             "kb = skin.data.shape_keys.key_blocks; print('KEYS', len(kb), 'joy' in kb, 'open_jaw' in kb,"
             " 'viseme_A' in kb, rep['bake']['keys'], bpy.context.scene.frame_end);"
             "views = [s for sc in bpy.data.screens for a in sc.areas for s in a.spaces if s.type == 'VIEW_3D'];"
             "print('SHOW', len(views) > 0, all(v.shading.color_type == 'VERTEX' for v in views),"
             " scan.display_type, all(o.hide_get() for o in root.children_recursive if 'headadapt_fdp' in o));"
             "from headadapt_addon.core.skin import arkit;"
             "eye = next(o for o in root.children_recursive if o.get('headadapt_part') == 'eye_l');"
             "print('ARKIT', [u for u in arkit.UNITS if u not in kb], sorted(set(kb.keys()) & {u.lower() for u in arkit.UNITS}),"
             " 'eyeLookUpLeft' in eye.data.shape_keys.key_blocks, 'eyeLookUpRight' in eye.data.shape_keys.key_blocks)")
    res = subprocess.run([sys.executable, "-c", check, str(out / "head.blend")], capture_output=True, text=True)
    assert "OK 2 True True 9" in res.stdout, res.stdout + res.stderr
    assert "VIEW HeadAdapt camera CAMERA ['LIGHT']" in res.stdout, res.stdout       # renders without setup
    assert "SHOW True True WIRE True" in res.stdout, res.stdout     # heat map on, scan as wire, FDPs hidden
    # shape keys: Basis + 6 expressions + 14 visemes + the skin FAPs; the preview action plays the six
    keys = res.stdout.split("KEYS")[1].split()
    assert int(keys[0]) > 1 + 6 + 14 + 40 and keys[1:4] == ["True", "True", "True"], res.stdout
    assert int(keys[5]) >= 6 * 30
    # ARKit's 52, each under its exact name (none missing, none lowercased), the gaze turning the eye
    assert "ARKIT [] [] True False" in res.stdout, res.stdout
    # opened where the add-on is enabled, the panels show the batch's scan, result and report, and their
    # display buttons act on it (before: "Pick the scanned head", "Adapt first", FDPs never shown)
    adopt = ("import bpy, sys, headadapt_addon; headadapt_addon.register();"
             "bpy.ops.wm.open_mainfile(filepath=sys.argv[1]); s = bpy.context.scene.headadapt;"
             "print('ADOPT', s.result_root and s.result_root.name, s.scan and s.scan.name, len(s.report_json) > 100);"
             "s.show_fdps = True;"
             "print('FDPS', sum(not o.hide_get() for o in s.result_root.children_recursive if 'headadapt_fdp' in o));"
             # the OBJ is the .blend's skin (it was the fit's, before the transfer moved the sockets' lining)
             "import numpy as np; skin = next(o for o in s.result_root.children_recursive if o.get('headadapt_part') == 'skin');"
             "m = np.array(skin.matrix_world); v = np.array([list(p.co) for p in skin.data.shape_keys.key_blocks[0].data]);"
             "obj = np.array([l.split()[1:4] for l in open(sys.argv[2]) if l.startswith('v ')], float);"
             "print('OBJ', np.abs(v @ m[:3, :3].T + m[:3, 3] - obj).max() < 1e-3);"
             # the sample is in mm: the scene says so (it opened as a 250 m head)
             "u = bpy.context.scene.unit_settings; print('UNIT', u.length_unit, round(u.scale_length, 6))")
    res = subprocess.run([sys.executable, "-c", adopt, str(out / "head.blend"), str(out / "adapted_head.obj")],
                         capture_output=True, text=True)
    assert "ADOPT HA Adapted head scan True" in res.stdout and "FDPS 82" in res.stdout, res.stdout + res.stderr
    assert "OBJ True" in res.stdout and "UNIT MILLIMETERS 0.001" in res.stdout, res.stdout + res.stderr


@pytest.mark.slow
def test_expressions_panel_bakes_the_template_and_imports_a_fap_file(ui_scene, tmp_path):
    import bpy
    from mathutils import Vector

    from headadapt_addon.core import mpeg4
    from headadapt_addon.core.fapfile import FapAnimation, write_fap
    from headadapt_addon.core.template import bundled_template

    def tpl_head_pivot():
        return bundled_template().meta["head_pivot"]

    with bpy.context.temp_override(**ui_scene):
        with pytest.raises(RuntimeError, match="poll"):
            bpy.ops.headadapt.bake_expressions()                      # no head yet: greyed out
        bpy.ops.headadapt.add_template()
        assert bpy.ops.headadapt.bake_expressions(sets={"expression", "fap", "arkit"}) == {"FINISHED"}
        root = bpy.context.scene.headadapt.template_root
        skin = next(o for o in root.children_recursive if o.get("headadapt_part") == "skin")
        kb = skin.data.shape_keys.key_blocks
        assert "joy" in kb and "open_jaw" in kb and "viseme_A" not in kb
        from headadapt_addon.core.skin import arkit
        assert [u for u in arkit.UNITS if u not in kb] == [] and len(arkit.UNITS) == 52   # ARKit's exact names
        info = json.loads(skin["headadapt_keys"])
        assert {n for n, k in info.items() if k["kind"] == "arkit"} == set(arkit.UNITS)
        jaw = next(o for o in root.children_recursive if o.get("headadapt_part") == "mandible")
        assert "jawOpen" in jaw.data.shape_keys.key_blocks
        jaw = next(o for o in root.children_recursive if o.get("headadapt_part") == "mandible")
        assert "open_jaw" in jaw.data.shape_keys.key_blocks          # the mandible follows the jaw
        # the preview plays the six expressions one after another
        sc = bpy.context.scene
        peaks = []
        assert skin.data.shape_keys.animation_data.action is not None
        for frame in range(sc.frame_start, sc.frame_end + 1, 5):
            sc.frame_set(frame)
            peaks.append(max(mpeg4.EXPRESSIONS, key=lambda n: kb[n].value) if max(kb[n].value for n in mpeg4.EXPRESSIONS) > 0.5 else None)
        order = [p for i, p in enumerate(peaks) if p and (i == 0 or peaks[i - 1] != p)]
        assert order == list(mpeg4.EXPRESSIONS)
        # at rest every key is 0 and the head is the head: Blender 5 gives a key made by shape_key_add
        # the value 1, which left every unkeyed key on (the sample's rest face up to 87 mm off)
        sc.frame_set(sc.frame_start)
        parts = [o for o in root.children_recursive if o.type == "MESH" and o.data.shape_keys]
        on = {(o.name, k.name) for o in parts for k in o.data.shape_keys.key_blocks[1:] if k.value != 0.0}
        assert not on, sorted(on)[:5]
        dg = bpy.context.evaluated_depsgraph_get()
        shown = np.array([v.co for v in skin.evaluated_get(dg).to_mesh().vertices])
        assert np.abs(shown - np.array([v.co for v in kb["Basis"].data])).max() < 1e-6
        # a .fap file: open_jaw ramps 0 -> 512 MNS over 3 frames, head_yaw turns the root
        n = 3
        vals = np.full((n, mpeg4.N_FAPS + 1), np.nan)
        vals[:, 3] = [0, 256, 512]
        vals[:, 48] = [0, 0, 10000]
        vals[:, 49] = [0, 0, 20000]
        write_fap(tmp_path / "t.fap", FapAnimation("t", 25.0, np.arange(n), vals, np.full((n, 4), np.nan),
                                                   np.full((n, 6), np.nan)))
        sc.frame_set(1)
        rest = np.array(root.matrix_world @ Vector(tpl_head_pivot()))
        at_rest = root.matrix_basis.copy()
        assert bpy.ops.headadapt.import_fap(filepath=str(tmp_path / "t.fap")) == {"FINISHED"}
        sc.frame_set(3)
        # the head turns about its pivot (FDP 7.1, the top of the spine), which stays put
        assert np.allclose(np.array(root.matrix_world @ Vector(tpl_head_pivot())), rest, atol=1e-5)
        assert root.rotation_euler[0] == pytest.approx(0.1, abs=1e-5)
        info = json.loads(skin["headadapt_keys"])
        assert kb["open_jaw"].value == pytest.approx(512 / info["open_jaw"]["fap_units"], rel=1e-4)
        assert root.rotation_euler[2] == pytest.approx(0.2, abs=1e-5)
        # a broken .fap: a clear error, nothing keyed
        (tmp_path / "bad.fap").write_text("2.1 bad 25 1\n1 0 1\n0 5\n")
        with pytest.raises(RuntimeError, match="bad.fap, line 2"):
            bpy.ops.headadapt.import_fap(filepath=str(tmp_path / "bad.fap"))
        # a second file replaces what was keyed before it, wherever the timeline stands: the bake's
        # preview (joy...) and the first file's head turn are gone, the head back at its rest pose
        nothing = np.full((2, 6), np.nan)
        jaw = np.full((2, mpeg4.N_FAPS + 1), np.nan)
        jaw[:, 3] = [0, 5 * info["open_jaw"]["fap_units"]]          # 5 times the key: beyond its slider's 3
        write_fap(tmp_path / "jaw.fap", FapAnimation("jaw", 25.0, np.arange(2), jaw, nothing[:, :4], nothing))
        sc.frame_set(3)
        assert bpy.ops.headadapt.import_fap(filepath=str(tmp_path / "jaw.fap")) == {"FINISHED"}
        assert (sc.frame_start, sc.frame_end) == (1, 2)
        for frame in (1, 2, 17, 47):
            sc.frame_set(frame)
            assert [n for n in mpeg4.EXPRESSIONS if kb[n].value != 0] == [] and np.allclose(root.matrix_basis, at_rest)
        sc.frame_set(2)
        assert kb["open_jaw"].value == pytest.approx(5.0, rel=1e-4) and kb["open_jaw"].slider_max >= 5.0
        # a root in quaternions turns too, about the pivot; a key asked past Blender's 10 is cut at 10
        root.rotation_mode = "QUATERNION"
        jaw[:, 3] = [0, 1e6 * info["open_jaw"]["fap_units"]]
        jaw[:, 49] = [0, 30000]                                     # head_yaw 0.3 rad
        write_fap(tmp_path / "yaw.fap", FapAnimation("yaw", 25.0, np.arange(2), jaw, nothing[:, :4], nothing))
        assert bpy.ops.headadapt.import_fap(filepath=str(tmp_path / "yaw.fap")) == {"FINISHED"}
        sc.frame_set(2)
        assert kb["open_jaw"].value == pytest.approx(10.0)
        assert np.allclose(np.array(root.matrix_world @ Vector(tpl_head_pivot())), rest, atol=1e-5)
        assert root.rotation_quaternion.angle == pytest.approx(0.3, abs=1e-5)
        # a file with no frames is refused, the scene as it was
        (tmp_path / "empty.fap").write_text("2.1 empty 12 0\n")
        with pytest.raises(RuntimeError, match="empty.fap: the file holds no frames"):
            bpy.ops.headadapt.import_fap(filepath=str(tmp_path / "empty.fap"))
        assert sc.render.fps == 25 and (sc.frame_start, sc.frame_end) == (1, 2) and kb["open_jaw"].value == 10.0
