"""Issue 17, the artist's session: the panels accept what the batch accepts and say why a button is
greyed; one options object for both; the Report table read row by row; progress while working;
Adapt replaces its last result; the batch's .blend is recognised; bad landmarks refused."""
import json

import numpy as np
import pytest

import headadapt_addon
from headadapt_addon.batch import SAMPLE_DIR
from headadapt_addon.core import meshio
from headadapt_addon.core.mesh.spatial import MeshQuery


def _sample_scan(name="scan"):
    import bpy

    from headadapt_addon.blender import bridge

    v, t = meshio.read_mesh(SAMPLE_DIR / "scan.ply")
    obj = bpy.data.objects.new(name, bridge.new_mesh(name, v, t))
    bpy.context.scene.collection.objects.link(obj)
    bpy.context.scene.headadapt.scan = obj
    return obj


def _from_the_button(ctx, run, operator, reports):
    """A long operator's run started as Modal.invoke starts it from a button (headless, bpy.ops runs
    execute: waited for): (the operator as modal() sees it, event(kind) -> modal()'s answer to a
    stand-in event of that kind). Reports go to the list reports."""
    from types import SimpleNamespace

    from headadapt_addon.ui import jobs

    wm = ctx.window_manager
    op = SimpleNamespace(_run=run, _timer=wm.event_timer_add(0.25, window=ctx.window),
                         report=lambda kind, text: reports.append((kind, text)))
    wm.progress_begin(0, 100)
    jobs._RUNNING.append(run)
    run.job.start()
    return op, lambda kind: operator.modal(op, ctx, SimpleNamespace(type=kind))


def _progress_shown(event, s):
    """Timer events until the run's progress shows (each answered: still running); whether it showed."""
    import time
    deadline = time.time() + 60
    while not s.progress_text and time.time() < deadline:
        assert event("TIMER") == {"RUNNING_MODAL"}
        time.sleep(0.01)
    return s.progress_text.startswith("HeadAdapt: ")


def _to_the_end(event):
    """Timer events until the run ends: its last answer."""
    import time
    deadline = time.time() + 120
    while (answer := event("TIMER")) == {"RUNNING_MODAL"} and time.time() < deadline:
        time.sleep(0.02)
    return answer


@pytest.fixture
def progress(monkeypatch):
    """Every progress step the long operators show, as (fraction, message, the scene's progress text)."""
    from headadapt_addon.ui import jobs

    seen = []
    original = jobs.show_progress

    def record(context, fraction, message):
        original(context, fraction, message)
        seen.append((fraction, message, context.scene.headadapt.progress_text))

    monkeypatch.setattr(jobs, "show_progress", record)
    return seen


def _greyed_because(op):
    """The poll message of a greyed operator (bpy.ops raises it), or None when it can run."""
    if op.poll():
        return None
    with pytest.raises(RuntimeError) as err:
        op()
    return str(err.value).split("poll()", 1)[1].strip()


def test_buttons_enable_on_the_batch_minimum_and_say_why_when_greyed(ui_scene):
    import bpy

    from headadapt_addon.blender import landmarks
    from headadapt_addon.core import mpeg4

    ops = bpy.ops.headadapt
    with bpy.context.temp_override(**ui_scene):
        for op in (ops.calibrate, ops.suggest_landmarks, ops.adapt):
            assert "no scan selected" in _greyed_because(op).lower()
        assert "no suggestions yet" in _greyed_because(ops.accept_suggestions).lower()
        assert "no head in the scene" in _greyed_because(ops.import_fap).lower()
        assert "no head in the scene" in _greyed_because(ops.bake_expressions).lower()
        scan = _sample_scan()
        assert "no landmarks on 'scan'" in _greyed_because(ops.adapt).lower()
        assert "no landmarks on the scan to export" in _greyed_because(ops.export_landmarks).lower()
        clicks = meshio.read_landmarks(SAMPLE_DIR / "landmarks.json")
        # three clicks: the batch's minimum is four (calibration.MIN_FDPS)
        landmarks.set_landmarks(scan, {k: clicks[k] for k in ("3.7", "3.12", "9.3")})
        for op in (ops.calibrate, ops.suggest_landmarks, ops.adapt):
            assert "at least 4" in _greyed_because(op), op
        # the 8 front clicks, none of the paper's ear or hairline FDPs: as the batch, all three run
        landmarks.set_landmarks(scan, {k: clicks[k] for k in mpeg4.CLICKS_8})
        assert not set(mpeg4.CLICKS_8) >= set(mpeg4.CALIBRATION_FDPS)
        for op in (ops.calibrate, ops.suggest_landmarks, ops.adapt):
            assert _greyed_because(op) is None, op
        # the paper's method does need its 8: the message names them and the way out
        bpy.context.scene.headadapt.calibration = "paper"
        why = _greyed_because(ops.adapt)
        assert "paper's calibration needs FDP 2.1" in why and "10.9" in why and "Least squares" in why
        bpy.context.scene.headadapt.calibration = "auto"
        # a NaN that got into the stored landmarks: greyed, the FDP named
        bad = {k: clicks[k] for k in mpeg4.CLICKS_8}
        bad["9.3"] = np.array([np.nan, 0.0, 0.0])
        landmarks.set_landmarks(scan, bad)
        assert "FDP 9.3" in _greyed_because(ops.adapt) and "NaN" in _greyed_because(ops.calibrate)
        # one spot clicked twice
        landmarks.set_landmarks(scan, {**{k: clicks[k] for k in mpeg4.CLICKS_8}, "9.15": clicks["9.3"]})
        assert "same spot" in _greyed_because(ops.adapt)


def test_the_panels_and_the_batch_build_the_same_options(ui_scene):
    import bpy

    from headadapt_addon import batch
    from headadapt_addon.core.adapt import AdaptOptions
    from headadapt_addon.ui import state

    s = bpy.context.scene.headadapt
    # the core's defaults, with the batch's spatial backend (Embree's rays where embreex is installed)
    assert state.adapt_options(s) == batch.adapt_options() == AdaptOptions(backend=batch.spatial_backend())
    s.max_levels, s.calibration, s.drop_flagged = 2, "umeyama", False
    assert state.adapt_options(s) == batch.adapt_options(2, "umeyama", keep_flagged=True)
    assert state.adapt_options(s, levels=0).max_levels == 0


def test_landmark_file_with_nan_is_refused_by_the_operator(ui_scene, tmp_path):
    import bpy

    from headadapt_addon.blender import landmarks

    with bpy.context.temp_override(**ui_scene):
        scan = _sample_scan()
        landmarks.set_landmarks(scan, {"3.7": [1.0, 2.0, 3.0]})
        path = tmp_path / "nan.json"
        path.write_text('{"points": {"3.7": [NaN, 0, 0], "3.12": [1, 2, 3], "9.3": [0, 1, 0], "2.10": [0, 0, 1]}}')
        with pytest.raises(RuntimeError, match=r"nan.json: FDP 3.7 must be three finite numbers \[x, y, z\], got \[nan"):
            bpy.ops.headadapt.import_landmarks(filepath=str(path))
        assert list(landmarks.get_landmarks(scan)) == ["3.7"]          # unchanged


def test_calibrate_names_a_unit_error_and_wrong_names(ui_scene):
    import bpy

    from headadapt_addon.blender import landmarks

    clicks = meshio.read_landmarks(SAMPLE_DIR / "landmarks.json")
    with bpy.context.temp_override(**ui_scene):
        scan = _sample_scan()
        s = bpy.context.scene.headadapt
        # the clicks in cm on a scan in mm: the calibration alone fits them (a similarity finds any
        # scale), but they are not on the scan; refused, the unit named, no tick
        landmarks.set_landmarks(scan, {k: v / 10.0 for k, v in clicks.items()})
        with pytest.raises(RuntimeError, match="another unit"):
            bpy.ops.headadapt.calibrate()
        assert s.calibration_rms_mm < 0 and "headadapt_calibration" not in scan
        # FDPs given each other's names (nose tip and chin, eye and mouth corners): judged against the
        # head's width, refused
        wrong = dict(clicks)
        for a, b in (("9.3", "2.10"), ("3.7", "8.4"), ("3.12", "8.3")):
            wrong[a], wrong[b] = clicks[b], clicks[a]
        landmarks.set_landmarks(scan, {k: wrong[k] for k in ("9.3", "2.10", "3.7", "8.4", "3.12", "8.3",
                                                             "3.11", "3.8")})
        with pytest.raises(RuntimeError, match="head's width.*wrong names"):
            bpy.ops.headadapt.calibrate()
        assert s.calibration_rms_mm < 0
        # the right clicks: a tick, the RMS a small part of the head's width
        landmarks.set_landmarks(scan, clicks)
        assert bpy.ops.headadapt.calibrate() == {"FINISHED"}
        assert 0 <= s.calibration_rms_mm < 10 and "headadapt_calibration" in scan


def test_a_blend_written_by_the_batch_is_recognised(ui_scene):
    """The batch does not register the add-on: its .blend has no scene settings, only tagged objects."""
    import bpy

    from headadapt_addon.blender import scene
    from headadapt_addon.core.template import bundled_template

    with bpy.context.temp_override(**ui_scene):
        assert not bpy.ops.headadapt.import_fap.poll()
        root = scene.add_template(bundled_template(), bpy.context.scene.collection, name="HA Adapted head")
        root["headadapt_part"] = "result_root"           # as blendout.build_result_objects tags it
        assert bpy.context.scene.headadapt.result_root is None
        assert scene.head_root(bpy.context) == root
        assert bpy.ops.headadapt.import_fap.poll() and bpy.ops.headadapt.bake_expressions.poll()


class _Layout:
    """A stand-in UILayout that keeps its structure: rows, columns and boxes are children."""

    def __init__(self, kind="layout"):
        self.kind, self.children, self.enabled = kind, [], True

    def _child(self, kind):
        node = _Layout(kind)
        self.children.append(node)
        return node

    def row(self, **_kw):
        return self._child("row")

    def column(self, **_kw):
        return self._child("column")

    def box(self, **_kw):
        return self._child("box")

    def grid_flow(self, **_kw):
        return self._child("grid")

    def label(self, text="", icon=None, **_kw):
        self.children.append(("label", text, icon))

    def operator(self, *_a, **_kw):
        return type("OpProps", (), {})()

    def prop(self, *_a, **_kw):
        pass

    def template_icon(self, icon_value=0, **_kw):
        self.children.append(("icon", f"icon {icon_value}", icon_value))

    def rows(self):
        """[[label text, ...] per row] anywhere under this layout, in drawing order."""
        out = []
        for child in self.children:
            if isinstance(child, _Layout):
                if child.kind == "row":
                    out.append([c[1] for c in child.children if isinstance(c, tuple)])
                out += child.rows()
        return out

    def labels(self):
        out = []
        for child in self.children:
            out += child.labels() if isinstance(child, _Layout) else [child[1:]]
        return out


def test_report_table_reads_row_by_row_with_units(ui_scene):
    import bpy

    from headadapt_addon.ui import panels

    rep = {"levels": [{"level": 0, "pairs": 74, "E_d": 7.1, "E_d_rms_mm": 2.61, "E_m": 3.2, "E": 7.13,
                       "seconds": 0.52},
                      {"level": 1, "pairs": 912, "E_d": 0.4, "E_d_rms_mm": 0.61, "E_m": 1.1, "E": 0.411,
                       "seconds": 2.04}],
           "best_level": 1, "stopped_because": "last level reached", "flagged_fdps": {"5.1": "far off"},
           "dropped_fdps": ["5.1"],
           "outcome": {"folds_left": 0, "seen_rms_mm": 0.6, "seen_vertices": 2000, "marker_rms_mm": 1.05,
                       "warnings": [], "ok": True}}
    bpy.context.scene.headadapt.report_json = json.dumps(rep)
    layout = _Layout()
    panels.draw_report(layout, bpy.context)
    rows = layout.rows()
    assert rows[0] == ["Level", "Pairs", "E_d mm²", "RMS mm", "E_m mm²", "E mm²", "Time s"]
    assert rows[1] == ["0", "74", "7.100", "2.61", "3.20", "7.130", "0.5"]
    assert rows[2] == ["1*", "912", "0.400", "0.61", "1.10", "0.411", "2.0"]      # the best level starred
    # a default-width sidebar: the essentials, which fit (seven columns were cut to their first letters)
    # (a 230-pixel sidebar cut "RMS mm" to "RMS ...": the units go on a line below)
    assert panels.report_rows(rep, wide=False) == [["Level", "Pairs", "RMS", "Time"], ["0", "74", "2.61", "0.5"],
                                                   ["1*", "912", "0.61", "2.0"]]
    texts = [t for t, _icon in layout.labels()]
    assert ("Dropped clicks: 5.1", "X") in layout.labels()
    assert "marker RMS 1.05 mm" in texts                                  # the held-out markers' error
    # no markers given: no E_m column; nothing dropped
    for lv in rep["levels"]:
        lv["E_m"] = None
    rep["dropped_fdps"], rep["outcome"]["marker_rms_mm"] = [], None
    bpy.context.scene.headadapt.report_json = json.dumps(rep)
    layout = _Layout()
    panels.draw_report(layout, bpy.context)
    assert layout.rows()[0] == ["Level", "Pairs", "E_d mm²", "RMS mm", "E mm²", "Time s"]
    assert all(len(r) == 6 for r in layout.rows())
    assert ("Dropped clicks: none", "CHECKMARK") in layout.labels()


@pytest.mark.slow
def test_adapt_reports_progress_and_replaces_its_last_result(ui_scene, progress):
    import bpy

    from headadapt_addon.blender import landmarks

    seen = progress
    with bpy.context.temp_override(**ui_scene):
        scan = _sample_scan("Anna")
        landmarks.set_landmarks(scan, meshio.read_landmarks(SAMPLE_DIR / "landmarks.json"))
        assert bpy.ops.headadapt.adapt(levels=1) == {"FINISHED"}
        # progress: rising fractions, each shown as the status text while it runs, cleared after
        fractions = [f for f, _m, _t in seen]
        assert len(seen) >= 4 and fractions == sorted(fractions) and fractions[-1] == 1.0
        assert any("level 1" in m for _f, m, _t in seen)
        assert all(t.startswith("HeadAdapt: ") and m in t for _f, m, t in seen)
        assert bpy.context.scene.headadapt.progress_text == ""
        root = bpy.context.scene.headadapt.result_root
        assert root.name == "Anna adapted"
        names = {o.name for o in root.children_recursive}
        assert {"Anna skin", "Anna cranium", "Anna mandible"} <= names
        n_objects, n_meshes = len(bpy.data.objects), len(bpy.data.meshes)
        # again: the last result is replaced, same names, nothing piles up
        assert bpy.ops.headadapt.adapt(levels=0) == {"FINISHED"}
        assert (len(bpy.data.objects), len(bpy.data.meshes)) == (n_objects, n_meshes)
        assert bpy.context.scene.headadapt.result_root.name == "Anna adapted"
        assert "Anna skin" in bpy.data.objects and "Anna skin.001" not in bpy.data.objects
        assert len([c for c in bpy.data.collections if c.name.startswith("HeadAdapt result")]) == 1
        # keep earlier results: a second hierarchy beside the first
        bpy.context.scene.headadapt.keep_results = True
        assert bpy.ops.headadapt.adapt(levels=0) == {"FINISHED"}
        assert len(bpy.data.objects) == 2 * n_objects - 1                 # the scan once


@pytest.mark.slow
def test_adapt_from_a_button_works_on_a_thread_and_esc_leaves_the_scene_as_it_was(ui_scene):
    """The button's modal path with stand-in events: a timer shows progress, Esc cancels."""
    from types import SimpleNamespace

    import bpy

    from headadapt_addon.blender import landmarks
    from headadapt_addon.ui import jobs, operators, runs

    with bpy.context.temp_override(**ui_scene):
        ctx, s = bpy.context, bpy.context.scene.headadapt
        scan = _sample_scan()
        landmarks.set_landmarks(scan, meshio.read_landmarks(SAMPLE_DIR / "landmarks.json"))
        before = sorted(o.name for o in bpy.data.objects)
        reports = []

        def start(levels):
            return _from_the_button(ctx, runs.AdaptRun(ctx, levels), operators.HEADADAPT_OT_adapt, reports)

        op, event = start(3)
        assert event("MOUSEMOVE") == {"PASS_THROUGH"}             # the viewport stays usable
        assert _progress_shown(event, s)
        # Ctrl-Z while it runs is held (it undid Calibrate, and the finished run was then thrown away)
        ctrl_z = SimpleNamespace(type="Z", value="PRESS", ctrl=True, oskey=False)
        assert operators.HEADADAPT_OT_adapt.modal(op, ctx, ctrl_z) == {"RUNNING_MODAL"}
        assert reports[-1] == ({"WARNING"}, "Adapt is running: Esc cancels it; undo waits until it has ended")
        assert event("ESC") == {"CANCELLED"}
        assert op._run.job.wait(60) and isinstance(op._run.job.error, jobs.Cancelled)
        assert sorted(o.name for o in bpy.data.objects) == before and s.result_root is None
        assert s.progress_text == "" and s.report_json == ""
        assert reports[-1] == ({"WARNING"}, "Adapt cancelled: the scene is as it was")
        # left to run, the same path ends with the result
        op, event = start(1)
        answer = _to_the_end(event)
        assert answer == {"FINISHED"} and s.result_root.name == "scan adapted" and s.progress_text == ""
        assert reports[-1][0] == {"INFO"} and reports[-1][1].startswith("adapted: best level")
        # a click moved while it runs: the result is made (it stands for the clicks it started from) and
        # the report says it is not the moved clicks' (before: said nothing)
        clicks = landmarks.get_landmarks(scan)
        op, event = start(1)
        landmarks.set_landmarks(scan, dict(clicks, **{"9.3": clicks["9.3"] + 1.0}))
        assert _to_the_end(event) == {"FINISHED"} and s.result_root.name == "scan adapted"
        assert reports[-1][0] == {"WARNING"} and "the clicks changed while Adapt ran" in reports[-1][1]


def test_a_running_adapt_greys_adapt_and_bake_and_a_scan_removed_meanwhile_changes_nothing(ui_scene):
    """Pressed twice, Adapt ran twice at once; Bake could start beside it. Now both are greyed while
    one runs, and again usable once it ends or another file is loaded (its operator gone). A scan
    deleted (or undone) while Adapt runs: before, a ReferenceError traceback after the previous
    result had been removed; now an error report and the scene as it was."""

    import bpy

    from headadapt_addon.blender import landmarks
    from headadapt_addon.ui import jobs, operators, runs

    with bpy.context.temp_override(**ui_scene):
        ctx, s = bpy.context, bpy.context.scene.headadapt
        assert bpy.ops.headadapt.add_template() == {"FINISHED"}          # a head: Bake is usable
        scan = _sample_scan()
        landmarks.set_landmarks(scan, meshio.read_landmarks(SAMPLE_DIR / "landmarks.json"))
        assert bpy.ops.headadapt.adapt.poll() and bpy.ops.headadapt.bake_expressions.poll()
        # a button's start, as Modal.invoke makes it (headless, bpy.ops runs execute: waited for; the
        # real window's invoke is test_blender_binary's)
        started = runs.AdaptRun(ctx, 1)
        jobs._RUNNING.append(started)
        started.job.start()
        assert jobs.busy() == "Adapt"
        assert not bpy.ops.headadapt.adapt.poll() and not bpy.ops.headadapt.bake_expressions.poll()
        assert bpy.ops.headadapt.calibrate.poll()                          # a quick button stays
        running = list(jobs._RUNNING)
        operators._forget_kept()                                           # as loading a file does
        assert jobs.busy() == "" and bpy.ops.headadapt.adapt.poll()
        assert running[0].job.wait(60) and isinstance(running[0].job.error, jobs.Cancelled)
        # a scan removed while the run works: nothing written, said so
        before = sorted(o.name for o in bpy.data.objects)
        reports = []
        op, event = _from_the_button(ctx, runs.AdaptRun(ctx, 1), operators.HEADADAPT_OT_adapt, reports)
        bpy.data.objects.remove(scan)
        answer = _to_the_end(event)
        assert answer == {"CANCELLED"} and reports[-1][0] == {"ERROR"} and "removed while it ran" in reports[-1][1]
        assert sorted(o.name for o in bpy.data.objects) == sorted(n for n in before if n != "scan")
        assert s.result_root is None and s.progress_text == ""


def test_suggest_from_a_button_works_on_a_thread_esc_cancels_and_a_click_moved_meanwhile_writes_nothing(ui_scene):
    """Suggest the Rest runs an adaptation (about 1 s at 31k vertices, 2 s as a first press on 1M): it
    blocked Blender's window with no progress and no way out. From a button now: on a thread, its
    progress shown, Adapt and Bake greyed while it runs, Esc leaves the scan as it was; a click moved
    while it ran leaves the suggestions unwritten (they came from the clicks before)."""

    import bpy

    from headadapt_addon.blender import landmarks
    from headadapt_addon.core import mpeg4
    from headadapt_addon.ui import jobs, operators, runs

    clicks = meshio.read_landmarks(SAMPLE_DIR / "landmarks.json")
    eight = {k: clicks[k] for k in mpeg4.CLICKS_8}
    with bpy.context.temp_override(**ui_scene):
        ctx, s = bpy.context, bpy.context.scene.headadapt
        scan = _sample_scan()
        landmarks.set_landmarks(scan, eight)
        reports = []

        def start():
            operators._forget_kept()                 # judged anew each time: the run is long enough to watch
            return _from_the_button(ctx, runs.SuggestRun(ctx), operators.HEADADAPT_OT_suggest_landmarks, reports)

        op, event = start()
        assert jobs.busy() == "Suggest the Rest"
        assert not bpy.ops.headadapt.adapt.poll() and not bpy.ops.headadapt.suggest_landmarks.poll()
        assert event("MOUSEMOVE") == {"PASS_THROUGH"}             # the viewport stays usable
        assert _progress_shown(event, s)
        assert event("ESC") == {"CANCELLED"}
        assert op._run.job.wait(60) and isinstance(op._run.job.error, jobs.Cancelled)
        assert landmarks.SUGGESTED_PROP not in scan and landmarks.get_landmarks(scan).keys() == eight.keys()
        assert reports[-1] == ({"WARNING"}, "Suggest the Rest cancelled: the scene is as it was")
        assert jobs.busy() == "" and s.progress_text == "" and bpy.ops.headadapt.adapt.poll()
        # a click moved while it runs: nothing suggested, said so
        op, event = start()
        landmarks.set_landmarks(scan, dict(eight, **{"9.3": eight["9.3"] + 1.0}))
        assert _to_the_end(event) == {"CANCELLED"} and landmarks.SUGGESTED_PROP not in scan
        assert reports[-1][0] == {"WARNING"} and "clicks changed while Suggest the Rest ran" in reports[-1][1]
        # left to run, the same path ends with the suggestions, as bpy.ops gives them
        landmarks.set_landmarks(scan, eight)
        op, event = start()
        assert _to_the_end(event) == {"FINISHED"} and s.progress_text == "" and jobs.busy() == ""
        assert reports[-1][0] == {"INFO"} and reports[-1][1].startswith("suggested ")
        threaded = landmarks.get_landmarks(scan, landmarks.SUGGESTED_PROP)
        del scan[landmarks.SUGGESTED_PROP]
        assert bpy.ops.headadapt.suggest_landmarks() == {"FINISHED"}
        waited = landmarks.get_landmarks(scan, landmarks.SUGGESTED_PROP)
        assert len(threaded) > 40 and threaded.keys() == waited.keys()
        assert all(np.array_equal(threaded[k], waited[k]) for k in waited)


def test_calibrate_from_a_button_works_on_a_thread_esc_cancels_and_a_click_moved_meanwhile_writes_nothing(
        ui_scene, monkeypatch):
    """Calibrate prepares the scan (a dense scan clustered, its normals, its spatial tree: 1 s at 1M
    vertices, more on the larger scans the readers take) and blocked Blender's window meanwhile, with no
    progress and no way out. From a button now: on a thread, its progress shown, Adapt greyed while it
    runs; Esc leaves the scan as it was; a click moved while it ran leaves the calibration unwritten;
    left to run, the calibration bpy.ops writes; refused clicks take an earlier tick off. (The judging
    is held at a gate until the test has seen the run going: the sample calibrates in 0.1 s.)"""
    import threading

    import bpy

    from headadapt_addon.blender import landmarks
    from headadapt_addon.ui import jobs, operators, runs

    gate = threading.Event()
    judge = runs.judge_clicks

    def held(clicks):
        assert gate.wait(60)
        return judge(clicks)

    monkeypatch.setattr(runs, "judge_clicks", held)
    clicks = meshio.read_landmarks(SAMPLE_DIR / "landmarks.json")
    with bpy.context.temp_override(**ui_scene):
        ctx, s = bpy.context, bpy.context.scene.headadapt
        scan = _sample_scan()
        landmarks.set_landmarks(scan, clicks)
        reports = []

        def start():
            gate.clear()
            operators._forget_kept()                 # judged anew each time
            return _from_the_button(ctx, runs.CalibrateRun(ctx), operators.HEADADAPT_OT_calibrate, reports)

        op, event = start()
        assert jobs.busy() == "Calibrate" and not bpy.ops.headadapt.adapt.poll()
        assert event("MOUSEMOVE") == {"PASS_THROUGH"}             # the viewport stays usable
        assert _progress_shown(event, s) and "calibrating" in s.progress_text
        assert event("ESC") == {"CANCELLED"}
        gate.set()
        assert op._run.job.wait(60) and isinstance(op._run.job.error, jobs.Cancelled)
        assert "headadapt_calibration" not in scan and s.calibration_rms_mm < 0
        assert reports[-1] == ({"WARNING"}, "Calibrate cancelled: the scene is as it was")
        assert jobs.busy() == "" and s.progress_text == "" and bpy.ops.headadapt.adapt.poll()
        # a click moved while it runs: nothing written, said so
        op, event = start()
        landmarks.set_landmarks(scan, dict(clicks, **{"9.3": clicks["9.3"] + 1.0}))
        gate.set()
        assert _to_the_end(event) == {"CANCELLED"} and "headadapt_calibration" not in scan
        assert reports[-1][0] == {"WARNING"} and "clicks changed while Calibrate ran" in reports[-1][1]
        # left to run: the calibration, as bpy.ops writes it
        landmarks.set_landmarks(scan, clicks)
        op, event = start()
        gate.set()
        assert _to_the_end(event) == {"FINISHED"} and s.progress_text == "" and jobs.busy() == ""
        assert reports[-1][0] == {"INFO"} and reports[-1][1].startswith("calibrated (")
        threaded = (s.calibration_rms_mm, scan["headadapt_calibration"])
        assert 0 <= threaded[0] < 10
        del scan["headadapt_calibration"]
        s.calibration_rms_mm = -1.0
        assert bpy.ops.headadapt.calibrate() == {"FINISHED"}
        assert (s.calibration_rms_mm, scan["headadapt_calibration"]) == threaded
        # clicks in another unit, from the button: refused, the cause said, the earlier tick taken off
        landmarks.set_landmarks(scan, {k: v / 10.0 for k, v in clicks.items()})
        op, event = start()
        gate.set()
        assert _to_the_end(event) == {"CANCELLED"} and reports[-1][0] == {"ERROR"}
        assert "another unit" in reports[-1][1] and s.calibration_rms_mm < 0


@pytest.mark.slow
def test_bake_reports_progress_and_esc_leaves_no_shape_keys(ui_scene, progress):

    import bpy

    from headadapt_addon.ui import jobs, operators, runs

    seen = progress
    with bpy.context.temp_override(**ui_scene):
        ctx, s = bpy.context, bpy.context.scene.headadapt
        assert bpy.ops.headadapt.add_template() == {"FINISHED"}
        root = s.template_root
        skin = next(o for o in root.children_recursive if o.get("headadapt_part") == "skin")
        # from a button (modal, stand-in events): Esc while it bakes leaves no key behind
        reports = []
        op, event = _from_the_button(ctx, runs.BakeRun(root, ("expression",), True),
                                     operators.HEADADAPT_OT_bake_expressions, reports)
        run = op._run
        assert _progress_shown(event, s)
        assert event("ESC") == {"CANCELLED"}
        assert run.job.wait(120) and isinstance(run.job.error, jobs.Cancelled)
        assert skin.data.shape_keys is None and s.progress_text == ""
        assert reports[-1] == ({"WARNING"}, "Bake cancelled: the scene is as it was")
        # through bpy.ops: progress per key, rising to the end, each shown as the status text
        seen.clear()
        assert bpy.ops.headadapt.bake_expressions(sets={"expression"}) == {"FINISHED"}
        fractions = [f for f, _m, _t in seen]
        assert fractions == sorted(fractions) and fractions[-1] == 1.0
        assert {"baking joy", "baking surprise"} <= {m for _f, m, _t in seen}
        assert all(t.startswith("HeadAdapt: ") and m in t for _f, m, t in seen)
        assert "joy" in skin.data.shape_keys.key_blocks and s.progress_text == ""


def test_suggest_refuses_clicks_in_another_unit_or_under_wrong_names(ui_scene, capfd):
    """Suggest the Rest judges the clicks as Calibrate does: the cause named, nothing suggested. A click
    its fit judges wrong is named in a warning."""
    import bpy

    from headadapt_addon.blender import landmarks
    from headadapt_addon.core import mpeg4

    clicks = meshio.read_landmarks(SAMPLE_DIR / "landmarks.json")
    eight = {k: clicks[k] for k in mpeg4.CLICKS_8}
    with bpy.context.temp_override(**ui_scene):
        scan = _sample_scan()
        landmarks.set_landmarks(scan, {k: v / 10.0 for k, v in eight.items()})      # cm on a mm scan
        with pytest.raises(RuntimeError, match="another unit"):
            bpy.ops.headadapt.suggest_landmarks()
        assert landmarks.SUGGESTED_PROP not in scan
        wrong = dict(eight)
        for a, b in (("9.3", "2.10"), ("3.7", "8.4"), ("3.12", "8.3")):
            wrong[a], wrong[b] = eight[b], eight[a]
        landmarks.set_landmarks(scan, wrong)
        with pytest.raises(RuntimeError, match="wrong names"):
            bpy.ops.headadapt.suggest_landmarks()
        assert landmarks.SUGGESTED_PROP not in scan
        landmarks.set_landmarks(scan, eight)
        assert bpy.ops.headadapt.suggest_landmarks() == {"FINISHED"}
        suggested = landmarks.get_landmarks(scan, landmarks.SUGGESTED_PROP)
        assert len(suggested) > 40 and not set(suggested) & set(eight)
    # the chin clicked 25 mm up on the lips: the suggestions come from a fit that judged it wrong, and
    # the report says so (a warning naming the FDP), before the artist builds on it
    verts, tris = meshio.read_mesh(SAMPLE_DIR / "scan.ply")
    up = (eight["9.3"] - eight["2.10"]) / np.linalg.norm(eight["9.3"] - eight["2.10"])
    slip = dict(eight, **{"2.10": MeshQuery(verts, tris).closest_points((eight["2.10"] + 25.0 * up)[None])[0][0]})
    with bpy.context.temp_override(**ui_scene):
        landmarks.set_landmarks(scan, slip)
        capfd.readouterr()
        assert bpy.ops.headadapt.suggest_landmarks() == {"FINISHED"}
        said = capfd.readouterr()
        # and the Landmarks panel marks that click, with the reason, until it is moved
        from headadapt_addon.ui import panels

        def chin_row():
            layout = _Layout()
            panels.draw_landmarks(layout, bpy.context)
            labels = layout.labels()
            at = next(i for i, (t, _i) in enumerate(labels) if t.startswith("2.10  "))
            return labels[at][1], labels[at + 1][0]

        icon, under = chin_row()
        assert icon == "ERROR" and under.startswith("The fit judges it wrong: ") and " mm from where" in under
        landmarks.set_landmarks(scan, eight)                    # the chin clicked right: no mark
        assert chin_row()[0] == "CHECKMARK"
        landmarks.set_landmarks(scan, slip)                     # back where it was judged: marked again
        assert chin_row()[0] == "ERROR"
        del scan[landmarks.FLAGGED_PROP]                        # Adapt marks it too
        assert bpy.ops.headadapt.adapt(levels=1) == {"FINISHED"} and chin_row()[0] == "ERROR"
        landmarks.set_landmarks(scan, eight)
        assert bpy.ops.headadapt.suggest_landmarks() == {"FINISHED"}   # judged right: the mark is gone
        assert landmarks.FLAGGED_PROP not in scan
    printed = (said.out + said.err).splitlines()
    assert any(s.startswith("Warning: suggested") and "judges a click wrong: FDP 2.10" in s for s in printed), printed


@pytest.mark.slow
def test_markers_and_the_head_turn_follow_the_adapted_head(ui_scene, tmp_path):
    """Held-out marker objects sit on the adapted skin, not at the template's positions; a .fap's head
    rotation turns the adapted head about its own head pivot (FDP 7.1), which stays where it is."""
    import bpy
    import mathutils

    from headadapt_addon.blender import animation, landmarks, scene
    from headadapt_addon.core import mpeg4
    from headadapt_addon.core.fapfile import FapAnimation, write_fap
    from headadapt_addon.core.template import bundled_template

    tpl = bundled_template()
    with bpy.context.temp_override(**ui_scene):
        scan = _sample_scan()
        landmarks.set_landmarks(scan, meshio.read_landmarks(SAMPLE_DIR / "landmarks.json"))
        assert bpy.ops.headadapt.adapt(levels=1) == {"FINISHED"}
        root = bpy.context.scene.headadapt.result_root
        objs = scene.template_objects(root)
        skin = objs["skin"]
        skin_verts = np.array([v.co for v in skin.data.vertices])
        moved = []
        markers = [o for o in root.children_recursive if "headadapt_marker" in o]
        assert len(markers) == len(tpl.meta["markers"])
        for o in markers:
            ref = tpl.meta["markers"][o["headadapt_marker"]]
            on_skin = np.asarray(ref["bary"]) @ skin_verts[tpl.skin.tris[ref["face"]]]
            assert np.allclose(np.array(o.location), on_skin, atol=1e-6), o.name
            moved.append(np.linalg.norm(np.array(o.location) - tpl.marker_points()[o["headadapt_marker"]]))
        assert max(moved) > 1e-3                            # the sample head is not the template's
        # the head turns about the adapted head pivot (root frame), not about the root's origin
        pivot = animation.head_pivot(root)
        assert np.linalg.norm(pivot - np.asarray(tpl.meta["head_pivot"])) < 0.05
        skin["headadapt_keys"] = json.dumps({"joy": {"kind": "expression", "parts": ["skin"], "fap_units": 0}})
        n = 3
        vals = np.full((n, mpeg4.N_FAPS + 1), np.nan)
        vals[:, 48], vals[:, 49], vals[:, 50] = [0, 0, 20000], [0, 10000, 20000], [0, 0, -15000]
        write_fap(tmp_path / "turn.fap", FapAnimation("turn", 25.0, np.arange(n), vals,
                                                      np.full((n, 4), np.nan), np.full((n, 6), np.nan)))
        bpy.context.scene.frame_set(1)
        rest = root.matrix_world @ mathutils.Vector(pivot)
        nose = next(o for o in root.children_recursive if o.get("headadapt_fdp") == "9.3")
        nose_rest = nose.matrix_world.translation.copy()
        rest_turn = root.matrix_basis.to_3x3().normalized()   # the root carries the scan's placement
        assert bpy.ops.headadapt.import_fap(filepath=str(tmp_path / "turn.fap")) == {"FINISHED"}
        for frame in (1, 2, 3):
            bpy.context.scene.frame_set(frame)
            assert (root.matrix_world @ mathutils.Vector(pivot) - rest).length < 1e-4 * root.matrix_world.median_scale
        # the turn is the head's own (pitch, roll, yaw) after its placement: frame 3's 0.2, -0.15, 0.2 rad
        turn = rest_turn.transposed() @ root.matrix_basis.to_3x3().normalized()
        assert np.allclose(turn, mathutils.Euler((0.2, -0.15, 0.2), "XYZ").to_matrix(), atol=1e-5)
        # the face turns: the nose tip moves by about its distance from the pivot times the angle
        assert (nose.matrix_world.translation - nose_rest).length > 0.1 * (nose_rest - rest).length


@pytest.mark.slow
def test_the_result_is_worth_looking_at_without_setup(ui_scene):
    """After Adapt: the heat map shown (Solid shading by the skin's colour attribute) with a legend in
    mm beside the head and in the Display panel, the scan as wire, the helpers hidden (no dashed
    relationship lines either); each toggle does what it says."""
    import bpy

    from headadapt_addon.blender import landmarks, view
    from headadapt_addon.ui import panels

    with bpy.context.temp_override(**ui_scene):
        s = bpy.context.scene.headadapt
        space = ui_scene["area"].spaces.active
        assert (space.shading.color_type, space.overlay.show_relationship_lines) == ("MATERIAL", True)
        # the template alone: its colours kept (no heat map to show), its helpers hidden
        assert bpy.ops.headadapt.add_template() == {"FINISHED"}
        assert space.shading.color_type == "MATERIAL"
        assert all(o.hide_get() for o in s.template_root.children_recursive if "headadapt_fdp" in o)
        scan = _sample_scan()
        landmarks.set_landmarks(scan, meshio.read_landmarks(SAMPLE_DIR / "landmarks.json"))
        assert bpy.ops.headadapt.adapt(levels=0) == {"FINISHED"}
        root = s.result_root
        skin = next(o for o in root.children_recursive if o.get("headadapt_part") == "skin")
        assert skin.data.color_attributes.active_color.name == view.HEAT_ATTRIBUTE
        assert (space.shading.type, space.shading.color_type) == ("SOLID", "VERTEX")
        assert not space.overlay.show_relationship_lines
        assert scan.display_type == "WIRE"
        # the legend beside the head: a colour bar blue (0 mm) at the bottom to red (3 mm) at the top
        bar = next(o for o in root.children_recursive if o.get("headadapt_part") == "legend")
        colours = np.array([c.color[:] for c in bar.data.color_attributes[view.HEAT_ATTRIBUTE].data])
        z = np.array([v.co.z for v in bar.data.vertices])
        assert colours[z.argmin()][2] > 0.9 > colours[z.argmin()][0]          # blue
        assert colours[z.argmax()][0] > 0.9 > colours[z.argmax()][2]          # red
        labels = sorted(o.data.body for o in root.children_recursive if o.get("headadapt_part") == "legend_label")
        assert labels == ["0 mm", "1.5 mm", "3 mm+", "distance to scan"]
        # beside the head (on the viewer's left of the face: the template's -X), not on it
        skin_x = min(v.co.x for v in skin.data.vertices)
        assert max(v.co.x for v in bar.data.vertices) < skin_x
        # the helpers hidden: 82 FDPs, the markers, 27 muscle curves
        helpers = {k: [o for o in root.children_recursive if o.get("headadapt_part") in parts]
                   for k, parts in view.HELPERS.items()}
        assert len(helpers["fdps"]) == 83 and len(helpers["muscles"]) == 28
        assert all(o.hide_get() and o.hide_render for group in helpers.values() for o in group)
        # the Display panel: the toggles and the legend's values in mm
        layout = _Layout()
        panels.draw_display(layout, bpy.context)
        assert ["0", "1", "1.5", "3+ mm"] == [t for t, _i in layout.labels()][:4]      # "1.5 mm3 mm+" ran together
        assert tuple(s.legend_0) == pytest.approx(view.heat_colours([0.0])[0, :3])
        # toggles
        s.show_fdps = True
        assert all(not o.hide_get() for o in helpers["fdps"]) and all(o.hide_get() for o in helpers["muscles"])
        s.show_muscles = True
        assert all(not o.hide_get() for o in helpers["muscles"])
        s.scan_as_wire = False
        assert scan.display_type == "TEXTURED"
        s.show_heat_map = False
        assert space.shading.color_type == "MATERIAL"
        s.show_heat_map = True
        assert space.shading.color_type == "VERTEX"


def test_fdp_labels_are_depth_tested_and_thinned(ui_scene):
    """The picker's labels: a point round the back of the head is not labelled through it, and labels
    closer than 14 px are thinned (the active FDP and the 8 clicks kept first)."""
    import bpy

    from headadapt_addon.blender import landmarks
    from headadapt_addon.core import mpeg4

    clicks = meshio.read_landmarks(SAMPLE_DIR / "landmarks.json")
    with bpy.context.temp_override(**ui_scene):
        scan = _sample_scan()
        verts = np.array([v.co for v in scan.data.vertices])
        centre = 0.5 * (verts.min(axis=0) + verts.max(axis=0))
        size = float(np.ptp(verts, axis=0).max())
        nose = clicks["9.3"]
        ahead = (nose - centre) / np.linalg.norm(nose - centre)
        pts = {"9.3": nose}
        assert landmarks.seen_from(scan, pts, centre + 5 * size * ahead) == {"9.3": True}
        assert landmarks.seen_from(scan, pts, centre - 5 * size * ahead) == {"9.3": False}     # from behind
        # both eye corners seen from the front, neither from behind
        eyes = {k: clicks[k] for k in ("3.7", "3.12")}
        assert all(landmarks.seen_from(scan, eyes, centre + 5 * size * ahead).values())
        assert not any(landmarks.seen_from(scan, eyes, centre - 5 * size * ahead).values())
    # thinning: three labels on one spot keep one (the active first), a far one stays
    spots = {"2.1": (100, 100), "9.3": (105, 103), "3.7": (300, 100), "8.3": (108, 98)}
    assert landmarks.thinned(spots, first=("2.1",)) == ["2.1", "3.7"]
    assert landmarks.thinned(spots) == ["3.7", "8.3"]      # the 8 clicks first, in their order: 8.3, not 2.1
    assert set(mpeg4.CLICKS_8) >= {"3.7", "9.3"}
    assert landmarks.thinned({k: (20.0 * i, 0.0) for i, k in enumerate(mpeg4.CLICKS_8)}) == list(mpeg4.CLICKS_8)


@pytest.mark.slow
def test_batch_preview_renders_the_scan_beside_the_head_front_and_side(tmp_path):
    """--preview out.png: one PNG (2 x 640 by 2 x 640), written atomically: a row per view (front, side),
    the scan on the left in plain grey, the head on the right with the heat map's blue and red; no
    quarter blank; a name that is not .png is refused (exit 2). The log is HeadAdapt's own: Blender's
    lines on its temporary files (each view's "Saved: '.../.preview.x/view00.png'", the .blend's "Saved
    copy as") and a headless GPU's context probes ("EGL Error (0x3009)", three a run, the picture
    fine) are left out."""
    import struct
    import subprocess
    import sys

    import bpy

    png = tmp_path / "pics" / "preview.png"
    cmd = [sys.executable, "-m", "headadapt_addon.batch", "adapt", "--scan", str(SAMPLE_DIR / "scan.ply"),
           "--landmarks", str(SAMPLE_DIR / "landmarks.json"), "--out", str(tmp_path / "o"), "--levels", "1"]
    proc = subprocess.run(cmd + ["--preview", str(png), "--blend", str(tmp_path / "o" / "head.blend")],
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    log = proc.stdout + proc.stderr
    assert "Saved" not in log and "EGL" not in log and ".preview." not in log, log
    assert f"headadapt: preview (scan beside the head with its heat map, front and side) in {png}" in proc.stdout
    assert (tmp_path / "o" / "head.blend").stat().st_size > 0
    assert sorted(p.name for p in png.parent.iterdir()) == ["preview.png"]      # no temporary left behind
    head = png.read_bytes()[:24]
    assert head[:8] == b"\x89PNG\r\n\x1a\n" and struct.unpack(">II", head[16:24]) == (1280, 1280)
    img = bpy.data.images.load(str(png))
    px = np.empty(1280 * 1280 * 4, dtype=np.float32)
    img.pixels.foreach_get(px)
    bpy.data.images.remove(img)
    rgb = px.reshape(1280, 1280, 4)[..., :3]               # Blender's rows: bottom (the side view) first
    blue = (rgb[..., 2] > 0.5) & (rgb[..., 0] < 0.25)
    red = (rgb[..., 0] > 0.5) & (rgb[..., 2] < 0.25) & (rgb[..., 1] < 0.3)
    grey = (rgb.min(axis=2) > 0.45) & (np.ptp(rgb, axis=2) < 0.05)
    left, right = slice(0, 640), slice(640, 1280)
    for row in (slice(0, 640), slice(640, 1280)):          # the side view, the front view
        scan, adapted = (row, left), (row, right)
        assert grey[scan].sum() > 20000 and blue[scan].sum() < 50, (grey[scan].sum(), blue[scan].sum())
        assert blue[adapted].sum() > 500 and red[adapted].sum() > 100, (blue[adapted].sum(), red[adapted].sum())
        assert rgb[scan].std() > 0.05 and rgb[adapted].std() > 0.05
    bad = subprocess.run(cmd + ["--overwrite", "--preview", str(tmp_path / "p.jpg")], capture_output=True, text=True)
    assert bad.returncode == 2 and bad.stderr.strip().count("\n") == 0 and "name a .png file" in bad.stderr


def test_the_preview_shows_the_blend_s_anatomy_and_leaves_the_stages_alone(clean_scene, tmp_path, monkeypatch):
    """With --blend and --preview the batch made the anatomy twice (the preview's own transfer), and the
    preview's transfer overwrote the stage "transfer" while its time was in "preview" too: the stages
    could sum past the run's total (a fresh clone's CI: 7.979 against 7.971 s, test_folder_mode). The
    preview now shows the anatomy it is given, and leaves the report's stages as they are."""
    from headadapt_addon.blender import blendout
    from headadapt_addon.core.adapt import AdaptOptions, adapt
    from headadapt_addon.core.anatomy import transfer
    from headadapt_addon.core.template import load_template

    tpl = load_template()
    verts, tris = meshio.read_mesh(SAMPLE_DIR / "scan.ply")[:2]
    clicks = meshio.read_landmarks(SAMPLE_DIR / "landmarks.json")
    result = adapt(tpl, verts, tris, clicks, AdaptOptions(max_levels=1))
    anatomy = transfer(tpl, result)

    def again(*_args, **_kwargs):
        raise AssertionError("the anatomy was transferred again")

    monkeypatch.setattr(blendout, "transfer", again)
    report = {"stage_seconds": {"transfer": 0.25}}
    blendout.write_preview(tmp_path / "p.png", tpl, result, verts, tris, clicks, report, anatomy=anatomy)
    assert report["stage_seconds"] == {"transfer": 0.25} and (tmp_path / "p.png").stat().st_size > 100_000


def test_blender_s_chatter_is_left_out_and_everything_else_passed_on(capfd):
    """blendout.without_chatter: at the file descriptors (where Blender's C code writes), the lines on
    HeadAdapt's temporary files and the GPU's probes are dropped, any other line is passed on to the
    stream it was written to, in order; when the block raises, nothing is dropped."""
    import os

    from headadapt_addon.blender import blendout

    chatter = (b"00:01.611  render           | Saved: '/w/out/.preview.tc2ys9kt/view00.png'\n",
               b'Info: Saved copy as ".head.pqccve4m.blend"\n',
               b"Saved: '/w/out/.p.2zqg10vj/view01.png'\n Time: 00:00.32 (Saving: 00:00.04)\n\n",  # Blender 3.x
               b'Info: Total files 0 | Changed 0 | Failed 0\nInfo: Saved ".h.31lz8as_.blend"\n',
               b"EGL Error (0x3009): EGL_BAD_MATCH: Arguments are inconsistent.\n"
               b"Managed to successfully fallback to surfaceless EGL rendering!\n")
    kept = (b"00:01.611  render           | Saved: '/w/out/mine.png'\n", b"Error: Not freed memory blocks: 2\n")
    capfd.readouterr()
    with blendout.without_chatter():
        for line in chatter[:4] + kept[:1]:
            os.write(1, line)
        os.write(2, chatter[4] + kept[1])
    out, err = capfd.readouterr()
    assert out == kept[0].decode() and err == kept[1].decode(), (out, err)
    with pytest.raises(ValueError), blendout.without_chatter():
        os.write(2, chatter[4])
        raise ValueError("the render failed")
    assert capfd.readouterr().err == chatter[4].decode()


@pytest.mark.slow
def test_save_picture_renders_the_scan_beside_the_result_and_leaves_the_scene_as_it_was(ui_scene, tmp_path):
    """The Report panel's Save Picture: greyed (saying why) until there is a result; then the batch's
    preview picture of the artist's scene (1280x1280 PNG), after which the scene's render and display
    settings, its objects and worlds, and the scan's wire display are as they were; not .png: refused."""
    import struct

    import bpy

    from headadapt_addon.blender import landmarks

    with bpy.context.temp_override(**ui_scene):
        sc = bpy.context.scene
        scan = _sample_scan()
        landmarks.set_landmarks(scan, meshio.read_landmarks(SAMPLE_DIR / "landmarks.json"))
        assert "adapt first" in _greyed_because(bpy.ops.headadapt.save_picture)
        assert bpy.ops.headadapt.adapt(levels=0) == {"FINISHED"}
        sc.render.image_settings.file_format = "JPEG"
        sc.render.resolution_x, sc.render.resolution_percentage = 1920, 50

        def state():
            return (sc.render.engine, sc.render.resolution_x, sc.render.resolution_y, sc.render.resolution_percentage,
                    sc.render.image_settings.file_format, sc.display.shading.color_type,
                    tuple(sc.display.shading.single_color), sc.camera, sc.world, scan.display_type, scan.hide_render,
                    sorted(o.name for o in bpy.data.objects), sorted(w.name for w in bpy.data.worlds),
                    sorted((o.name, o.hide_render) for o in sc.headadapt.result_root.children_recursive))

        before = state()
        assert scan.display_type == "WIRE"
        png = tmp_path / "pic.png"
        assert bpy.ops.headadapt.save_picture(filepath=str(png)) == {"FINISHED"}
        head = png.read_bytes()[:24]
        assert head[:8] == b"\x89PNG\r\n\x1a\n" and struct.unpack(">II", head[16:24]) == (1280, 1280)
        assert state() == before
        with pytest.raises(RuntimeError, match="name a .png file"):
            bpy.ops.headadapt.save_picture(filepath=str(tmp_path / "pic.jpg"))
        assert not (tmp_path / "pic.jpg").exists()


def test_the_preview_camera_frames_the_legend_s_text(clean_scene):
    """The preview's cameras frame the head's meshes and the heat legend's text labels (text objects):
    framed by the meshes alone, the labels beside a long, narrow head fell out of the picture (the
    1M bench head's preview lost the legend's left half)."""
    import bpy
    from bpy_extras.object_utils import world_to_camera_view
    from mathutils import Vector

    from headadapt_addon.blender import blendout, bridge

    root = bpy.data.objects.new("root", None)
    head = bpy.data.objects.new("head", bridge.new_mesh("head", np.array(       # a head's box, metres
        [(-0.08, -0.1, 0.0), (0.08, -0.1, 0.0), (0.08, 0.1, 0.3), (-0.08, 0.1, 0.3)]), np.array([(0, 1, 2, 3)])))
    label = bpy.data.objects.new("label", bpy.data.curves.new("label", "FONT"))     # as add_heat_legend's
    label.data.body, label.data.size, label.data.align_x = "1.5 mm", 0.009, "RIGHT"
    label.location = (-0.13, 0.0, 0.28)
    label.rotation_euler = (np.pi / 2, 0.0, 0.0)
    for obj in (root, head, label):
        clean_scene.collection.objects.link(obj)
    head.parent = label.parent = root
    bpy.context.view_layer.update()
    cam = bpy.data.objects.new("cam", bpy.data.cameras.new("cam"))
    clean_scene.collection.objects.link(cam)
    cam.data.lens = 85.0
    clean_scene.render.resolution_x = clean_scene.render.resolution_y = 640       # as render_preview's views
    blendout._aim(cam, root, (0.0, -1.0, 0.0))
    bpy.context.view_layer.update()
    for obj in (head, label):
        for corner in obj.bound_box:
            u, v, depth = world_to_camera_view(clean_scene, cam, obj.matrix_world @ Vector(corner))
            assert 0.0 <= u <= 1.0 and 0.0 <= v <= 1.0 and depth > 0, (obj.name, u, v)


def _view_region(ui_scene):
    return next(r for r in ui_scene["area"].regions if r.type == "WINDOW")


def test_the_picker_places_a_point_from_stand_in_events(ui_scene):
    """The picker's modal() with stand-in events inside temp_override: a click over the nose tip puts
    FDP 9.3 there and moves on along the guided order (the 8 clicks first); Ctrl-click removes it;
    the wheel passes through; Esc ends."""
    from types import SimpleNamespace

    import bpy
    from bpy_extras.view3d_utils import location_3d_to_region_2d
    from mathutils import Matrix, Vector

    from headadapt_addon.blender import landmarks
    from headadapt_addon.core import mpeg4
    from headadapt_addon.ui import picker

    clicks = meshio.read_landmarks(SAMPLE_DIR / "landmarks.json")
    region = _view_region(ui_scene)
    with bpy.context.temp_override(**ui_scene, region=region):
        ctx = bpy.context
        scan = _sample_scan()
        s = ctx.scene.headadapt
        assert s.active_fdp == mpeg4.CLICKS_8[0]               # the guided order starts with the 8 clicks
        verts = np.array([v.co for v in scan.data.vertices])
        centre = 0.5 * (verts.min(axis=0) + verts.max(axis=0))
        ahead = (clicks["9.3"] - centre) / np.linalg.norm(clicks["9.3"] - centre)
        # the scan placed (scaled, turned) so the factory view looks at its nose (headless, the view's
        # matrices are not recomputed: the view stays, the object moves; the picker works in world space)
        rv3d = ctx.region_data
        target = Vector(rv3d.view_location)
        to_eye = (rv3d.view_matrix.inverted().translation - target).normalized()
        turn = Vector(ahead).rotation_difference(to_eye).to_matrix().to_4x4()
        scan.matrix_world = (Matrix.Translation(target) @ turn @ Matrix.Scale(0.01, 4)
                             @ Matrix.Translation(-Vector(clicks["9.3"])))
        ctx.view_layer.update()
        nose_world = scan.matrix_world @ Vector(clicks["9.3"])
        xy = location_3d_to_region_2d(region, rv3d, nose_world)
        assert xy is not None and 0 < xy.x < region.width and 0 < xy.y < region.height
        reports = []
        op = SimpleNamespace(report=lambda kind, text: reports.append((kind, text)), done=[], undone=[])
        for name in ("finish", "status", "snapshot", "restore", "step_back"):
            setattr(op, name, getattr(picker.HEADADAPT_OT_pick_landmarks, name).__get__(op))

        def event(kind, value="PRESS", ctrl=False, at=None, shift=False):
            x, y = (int(round(xy.x)), int(round(xy.y))) if at is None else at       # in the region
            e = SimpleNamespace(type=kind, value=value, ctrl=ctrl, shift=shift, oskey=False, mouse_region_x=x,
                                mouse_region_y=y, mouse_x=region.x + x, mouse_y=region.y + y)
            return picker.HEADADAPT_OT_pick_landmarks.modal(op, ctx, e)

        s.active_fdp = "9.3"
        assert event("WHEELUPMOUSE") == {"PASS_THROUGH"}
        # a click on the toolbar or the header drawn over the view is theirs, not a pick behind them
        tools = next(r for r in ui_scene["area"].regions if r.type == "TOOLS")
        header = next(r for r in ui_scene["area"].regions if r.type == "HEADER")
        for r in (tools, header):
            assert r.width > 1 and r.height > 1
            at = (r.x - region.x + r.width // 2, r.y - region.y + r.height // 2)
            assert event("LEFTMOUSE", at=at) == {"PASS_THROUGH"} and event("M", at=at) == {"PASS_THROUGH"}
        assert landmarks.get_landmarks(scan) == {}
        assert event("LEFTMOUSE") == {"RUNNING_MODAL"}
        placed = landmarks.get_landmarks(scan)
        assert list(placed) == ["9.3"]
        size = float(np.ptp(verts, axis=0).max())
        assert np.linalg.norm(placed["9.3"] - clicks["9.3"]) < 0.01 * size        # under the mouse, on the scan
        hit = [(v.co - Vector(placed["9.3"])).length for v in scan.data.vertices]
        assert min(hit) < 0.02 * size                                             # local coordinates, on it
        assert s.active_fdp == "2.10"                            # the next of the 8 clicks after 9.3
        # Ctrl-Z inside the picker takes the click back (Blender's undo did nothing until the picker
        # ended, then took the whole session), Ctrl-Shift-Z puts it again
        assert event("Z", ctrl=True) == {"RUNNING_MODAL"}
        assert landmarks.get_landmarks(scan) == {} and s.active_fdp == "9.3"
        assert event("Z", ctrl=True, shift=True) == {"RUNNING_MODAL"}
        assert list(landmarks.get_landmarks(scan)) == ["9.3"] and s.active_fdp == "2.10"
        assert event("LEFTMOUSE", ctrl=True) == {"RUNNING_MODAL"}
        assert landmarks.get_landmarks(scan) == {} and reports[-1] == ({"INFO"}, "removed 9.3")
        assert event("ESC") == {"FINISHED"}


def test_the_picker_leaves_the_sidebar_s_clicks_to_the_sidebar():
    """over_view: the sidebar (drawn over the view, as Blender lays it out by default) and other editors
    are not the view; a hidden sidebar (1 pixel wide) does not count."""
    from types import SimpleNamespace as R

    from headadapt_addon.ui import picker

    view = R(type="WINDOW", x=0, y=0, width=1000, height=800)
    sidebar = R(type="UI", x=700, y=0, width=300, height=774)
    area = R(x=0, y=0, width=1000, height=800, regions=[view, sidebar])

    def at(x, y):
        return picker.over_view(area, R(mouse_x=x, mouse_y=y))

    assert at(400, 400) and not at(800, 400) and not at(1200, 400) and not at(400, -5)
    sidebar.width = 1
    assert at(800, 400)


def test_landmarking_guides_the_8_clicks_first_and_suggestions_one_by_one(ui_scene):
    """Load Sample Scan; the Landmarks panel lists the 8 clicks with the rest folded away; Suggest the
    Rest, then each suggestion accepted or rejected on its own (or all at once)."""
    import bpy

    from headadapt_addon.blender import landmarks
    from headadapt_addon.core import mpeg4
    from headadapt_addon.ui import panels

    clicks = meshio.read_landmarks(SAMPLE_DIR / "landmarks.json")
    with bpy.context.temp_override(**ui_scene):
        s = bpy.context.scene.headadapt
        assert bpy.ops.headadapt.load_sample_scan() == {"FINISHED"}
        scan = s.scan
        assert scan.name == "sample scan" and len(scan.data.polygons) > 1000 and not landmarks.get_landmarks(scan)
        layout = _Layout()
        panels.draw_landmarks(layout, bpy.context)
        texts = [t for t, _i in layout.labels()]
        assert "The 8 clicks: 0 of 8" in texts
        assert all(any(t.startswith(f"{k}  ") for t in texts) for k in mpeg4.CLICKS_8)
        assert not any(t.startswith("2.1  ") for t in texts)                 # the rest folded away
        # a picture of where the 8 clicks go, until they are placed
        icons = [i for t, i in layout.labels() if t.startswith("icon ")]
        picture = panels.reference_preview()
        w, h = picture.image_size                          # the 360x400 picture, as a 256 px preview
        assert h == 256 and abs(w / h - 360 / 400) < 0.01 and icons == [picture.icon_id]     # 0 without a GPU
        s.show_all_fdps = True
        layout = _Layout()
        panels.draw_landmarks(layout, bpy.context)
        assert sum(1 for t, _i in layout.labels() if "  " in t) == len(mpeg4.FDPS)
        # where people misplace a point, the panel says where to click it before they do: the
        # subnasale, which the real scans' clicks put on the nose's underside
        for fdp, hint in (("9.15", "Click in the corner where the nose's underside meets the upper lip"),
                          ("8.3", "Click where the slit between the lips ends"), ("9.3", None)):
            s.active_fdp = fdp
            layout = _Layout()
            panels.draw_landmarks(layout, bpy.context)
            shown = [(t, i) for t, i in layout.labels() if t.startswith("Click ")]
            assert (shown[0][0].startswith(hint[:20]) and shown[0][1] == "INFO") if hint else not shown, shown
            if hint:
                words = " ".join(t for t, _i in layout.labels()[layout.labels().index(shown[0]):][:6])
                assert hint in words, words
        s.active_fdp = mpeg4.CLICKS_8[0]
        # the 8 clicks, then the suggestions
        landmarks.set_landmarks(scan, {k: clicks[k] for k in mpeg4.CLICKS_8})
        assert bpy.ops.headadapt.suggest_landmarks() == {"FINISHED"}
        sug = landmarks.get_landmarks(scan, landmarks.SUGGESTED_PROP)
        layout = _Layout()
        panels.draw_landmarks(layout, bpy.context)
        assert (f"{len(sug)} suggested", None) in layout.labels()
        assert not [t for t, _i in layout.labels() if t.startswith("icon ")]      # the 8 placed: no picture
        assert bpy.ops.headadapt.accept_suggestions(fdp="2.1") == {"FINISHED"}
        assert bpy.ops.headadapt.reject_suggestions(fdp="11.1") == {"FINISHED"}
        pts = landmarks.get_landmarks(scan)
        left = landmarks.get_landmarks(scan, landmarks.SUGGESTED_PROP)
        assert set(pts) == set(mpeg4.CLICKS_8) | {"2.1"} and np.array_equal(pts["2.1"], sug["2.1"])
        assert set(left) == set(sug) - {"2.1", "11.1"}
        with pytest.raises(RuntimeError, match="11.1 is not among the suggestions"):
            bpy.ops.headadapt.accept_suggestions(fdp="11.1")
        assert bpy.ops.headadapt.reject_suggestions() == {"FINISHED"}         # the rest rejected at once
        assert landmarks.SUGGESTED_PROP not in scan and set(landmarks.get_landmarks(scan)) == set(pts)
        # with its landmarks, the sample is ready to calibrate and adapt
        assert bpy.ops.headadapt.load_sample_scan(with_landmarks=True) == {"FINISHED"}
        assert s.scan.name == "sample scan.001" and len(landmarks.get_landmarks(s.scan)) == len(clicks)
        assert bpy.ops.headadapt.calibrate() == {"FINISHED"}


def test_every_icon_the_panels_name_is_one_of_blenders():
    """The stand-in layouts accept any icon; Blender refuses an unknown one and the panel stops drawing
    there (a real window showed it): every icon named in ui/ must be in Blender's list."""
    import pathlib
    import re

    import bpy

    known = set(bpy.types.UILayout.bl_rna.functions["prop"].parameters["icon"].enum_items.keys())
    src = "".join(p.read_text() for p in (pathlib.Path(headadapt_addon.__file__).parent / "ui").glob("*.py"))
    used = set(re.findall(r'icon="([A-Z0-9_]+)"', src)) | set(re.findall(r'"([A-Z0-9_]+)" if ', src))
    used |= set(re.findall(r' else "([A-Z0-9_]+)"', src))
    assert len(used) > 15 and used <= known, sorted(used - known)
