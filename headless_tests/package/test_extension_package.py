"""The built Linux zip passes Blender's validation, installs and enables as an extension in a clean
user config under the running bpy (5.0.1 on Python 3.11 or 5.2.3 on Python 3.13: ./ha test runs both),
registers every operator, imports scipy from the wheel it bundles for this Python and the scan readers'
plyfile and trimesh from theirs (not the environment's), and runs the sample workflow from the installed copy.

The zip is built once per session with tools/build_extension.py (reused while it is newer than every
file it is built from; the first build downloads the two ~37 MB scipy wheels into the wheel cache).
Installing runs in child processes with their own BLENDER_USER_RESOURCES, so the extension, its
sidebar panels and its site-packages never reach the bpy module the other tests use.
"""

import importlib.util
import json
import os
import pathlib
import subprocess
import sys
import tomllib
import zipfile

import numpy as np
import pytest

ROOT = pathlib.Path(__file__).resolve().parents[2]
_spec = importlib.util.spec_from_file_location("build_extension", ROOT / "tools" / "build_extension.py")
build_extension = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(build_extension)

DIST = ROOT / "dist"
MANIFEST = tomllib.loads((ROOT / "blender_manifest.toml").read_text(encoding="utf-8"))
EXT_MODULE = f"bl_ext.user_default.{MANIFEST['id']}"
RESULT_MARK = "HEADADAPT_RESULT "

# Files the Linux zip is made from: when any is newer than the zip, it is rebuilt.
SOURCE_GLOBS = ("blender_manifest.toml", "__init__.py", "headadapt_addon/**/*", "assets/**/*",
                "tools/build_extension.py")

# The scipy the zip bundles for the Python running these tests (None: this Python has no wheel set).
THIS_PYTHON = "{}.{}".format(*sys.version_info[:2])
WHEEL_SET = next((ws for ws in build_extension.WHEEL_SETS if ws.python == THIS_PYTHON), None)

INSTALL = """
import json, sys
import bpy
zip_path = sys.argv[1]
result = bpy.ops.extensions.package_install_files(filepath=zip_path, repo="user_default", enable_on_install=True)
module = sys.modules.get(EXT_MODULE)
panels = sorted(
    name for name in dir(bpy.types)
    if isinstance(getattr(bpy.types, name), type) and issubclass(getattr(bpy.types, name), bpy.types.Panel)
    and getattr(getattr(bpy.types, name), "bl_category", None) == "HeadAdapt"
)
operators = {}
for name in dir(bpy.ops.headadapt):
    cls = getattr(bpy.types, "HEADADAPT_OT_" + name, None)
    operators["headadapt." + name] = getattr(cls, "__module__", None)
repo = next(r for r in bpy.context.preferences.extensions.repos if r.module == "user_default")
# what Blender's window does by itself (auto-save preferences): the add-on stays enabled on restart
saved = bpy.ops.wm.save_userpref()
print(RESULT_MARK + json.dumps({
    "result": sorted(result),
    "saved": sorted(saved),
    "enabled": EXT_MODULE in bpy.context.preferences.addons,
    "module_file": getattr(module, "__file__", None),
    "repo_dir": repo.directory,
    "extensions_dir": bpy.utils.user_resource("EXTENSIONS"),
    "panels": panels,
    "operators": operators,
}))
"""

# A fresh start with the same user config: Blender puts the extensions' site-packages ahead of the
# interpreter's own, so `import scipy` must resolve to the bundled wheel. Then the sample workflow
# through the installed add-on's operators (template, scan, landmarks, calibrate, adapt, bake, save,
# reload), then uninstall.
RESTART = """
import importlib, json, os, sys
import bpy
import numpy as np
# the bpy module starts on factory preferences; Blender's window loads the user's, as here
steps = {"read_userpref": bpy.ops.wm.read_userpref()}
enabled_at_start = EXT_MODULE in bpy.context.preferences.addons and EXT_MODULE in sys.modules
import scipy, scipy.spatial, scipy.sparse.linalg
extensions_dir = bpy.utils.user_resource("EXTENSIONS")
site = os.path.join(extensions_dir, ".local", "lib", "python%d.%d" % sys.version_info[:2], "site-packages")
distance, index = scipy.spatial.cKDTree(np.eye(3)).query([0.9, 0.1, 0.0])
installed = os.listdir(site) if os.path.isdir(site) else []
# the scan readers from the bundled plyfile and trimesh wheels
meshio = importlib.import_module(EXT_MODULE + ".headadapt_addon.core.meshio")
scan_counts = [len(a) for a in meshio.read_mesh(os.path.join(os.path.dirname(importlib.import_module(EXT_MODULE).__file__),
                                                            "assets", "sample_scan", "scan.ply"))]
import plyfile, trimesh

ext = importlib.import_module(EXT_MODULE)
sample = os.path.join(os.path.dirname(ext.__file__), "assets", "sample_scan")
blend = sys.argv[1]
bpy.ops.wm.read_homefile(use_empty=False)
for obj in list(bpy.data.objects):
    bpy.data.objects.remove(obj)
win = bpy.context.window_manager.windows[0]
area = next(a for a in win.screen.areas if a.type == "VIEW_3D")
with bpy.context.temp_override(window=win, screen=win.screen, area=area):
    steps["add_template"] = bpy.ops.headadapt.add_template()
    steps["ply_import"] = bpy.ops.wm.ply_import(filepath=os.path.join(sample, "scan.ply"))
    scan = bpy.context.selected_objects[0]
    bpy.context.view_layer.objects.active = scan
    steps["use_active_as_scan"] = bpy.ops.headadapt.use_active_as_scan()
    steps["import_landmarks"] = bpy.ops.headadapt.import_landmarks(filepath=os.path.join(sample, "landmarks.json"))
    steps["calibrate"] = bpy.ops.headadapt.calibrate()
    steps["adapt"] = bpy.ops.headadapt.adapt()
    steps["bake_expressions"] = bpy.ops.headadapt.bake_expressions(sets={"expression"})
    steps["load_sample_scan"] = bpy.ops.headadapt.load_sample_scan()       # the shipped scan, from the zip
    sample_scan = [bpy.context.scene.headadapt.scan.name, len(bpy.context.scene.headadapt.scan.data.vertices)]
    bpy.context.scene.headadapt.scan = scan
    steps["save"] = bpy.ops.wm.save_as_mainfile(filepath=blend)
# the bake's helper process (core/skin/parallel.py) starts from the installed copy too
bake = importlib.import_module(EXT_MODULE + ".headadapt_addon.core.skin.bake")
template = importlib.import_module(EXT_MODULE + ".headadapt_addon.core.template").load_template()
helper_keys = bake.bake(template, kinds=("expression", "viseme", "fap"))[1]["helper_keys"]
scipy_files = sorted({m.__file__ for name, m in list(sys.modules.items())
                      if (name == "scipy" or name.startswith("scipy.")) and getattr(m, "__file__", None)})
steps["open"] = bpy.ops.wm.open_mainfile(filepath=blend)
settings = bpy.context.scene.headadapt
root = settings.result_root
skin = next(o for o in root.children_recursive if o.get("headadapt_part") == "skin")
report = json.loads(settings.report_json)

repo_index = [r.module for r in bpy.context.preferences.extensions.repos].index("user_default")
uninstall = bpy.ops.extensions.package_uninstall(repo_index=repo_index, pkg_id=PKG_ID)
repo_dir = bpy.context.preferences.extensions.repos[repo_index].directory
print(RESULT_MARK + json.dumps({
    "enabled_at_start": enabled_at_start,
    "site": site,
    "site_on_path": site in sys.path,
    "site_before_interpreter": [p for p in sys.path if p.endswith("site-packages")][:1] == [site],
    "site_dist_info": sorted(n for n in installed if n.endswith(".dist-info")),
    "scan_counts": scan_counts,
    "sample_scan": sample_scan,
    "reader_files": [plyfile.__file__, trimesh.__file__],
    "scipy_file": scipy.__file__,
    "scipy_version": scipy.__version__,
    "scipy_files": scipy_files,
    "numpy_version": np.__version__,
    "nearest": [float(distance), int(index)],
    "steps": {k: sorted(v) for k, v in steps.items()},
    "result_root": root.name,
    "skin_keys": [k.name for k in skin.data.shape_keys.key_blocks],
    "levels": len(report["levels"]),
    "best_rms_mm": report["levels"][report["best_level"]]["E_d_rms_mm"],
    "outcome_ok": report["outcome"]["ok"],
    "uninstall": sorted(uninstall),
    "still_installed": os.path.exists(os.path.join(repo_dir, PKG_ID)),
    "helper_keys": helper_keys,
}))
"""


def _newest_source_mtime():
    newest = 0.0
    for pattern in SOURCE_GLOBS:
        for path in ROOT.glob(pattern):
            if path.is_file() and "__pycache__" not in path.parts:
                newest = max(newest, path.stat().st_mtime)
    return newest


@pytest.fixture(scope="session")
def linux_zip():
    zip_path = DIST / f"{MANIFEST['id']}-{MANIFEST['version']}-linux_x64.zip"
    if zip_path.is_file() and zip_path.stat().st_mtime > _newest_source_mtime():
        return zip_path
    proc = subprocess.run(
        [sys.executable, str(ROOT / "tools" / "build_extension.py"), "--platforms", "linux-x64", "--out", str(DIST)],
        capture_output=True, text=True, cwd=ROOT,
    )
    if proc.returncode != 0:
        if "pip could not fetch" in proc.stderr:
            pytest.skip(f"scipy wheel unavailable (offline?):\n{proc.stderr}")
        pytest.fail(f"tools/build_extension.py failed:\n{proc.stdout}{proc.stderr}")
    assert zip_path.is_file(), proc.stdout
    return zip_path


def _run_blender(code, args, user_dir, cwd):
    env = dict(os.environ, BLENDER_USER_RESOURCES=str(user_dir))
    env.pop("PYTHONPATH", None)
    prelude = f"EXT_MODULE = {EXT_MODULE!r}; PKG_ID = {MANIFEST['id']!r}; RESULT_MARK = {RESULT_MARK!r}\n"
    proc = subprocess.run([sys.executable, "-c", prelude + code, *map(str, args)],
                          capture_output=True, text=True, env=env, cwd=cwd, timeout=600)
    lines = [line for line in proc.stdout.splitlines() if line.startswith(RESULT_MARK)]
    assert proc.returncode == 0 and lines, f"exit {proc.returncode}\n{proc.stdout}\n{proc.stderr}"
    return json.loads(lines[-1][len(RESULT_MARK):]), proc.stdout + proc.stderr


def _version(text):
    return tuple(int(part) for part in text.split("."))


def _platform_of(wheel):
    """The Blender platform a wheel's platform tag is for."""
    tag = wheel.removesuffix(".whl").split("-")[-1]
    arch = "arm64" if tag.endswith("arm64") else "x64" if tag.endswith(("x86_64", "amd64")) else tag
    system = "windows" if tag.startswith("win") else "macos" if tag.startswith("macosx") else \
        "linux" if "manylinux" in tag else tag
    return f"{system}-{arch}"


def test_the_package_s_version_is_the_manifest_s():
    """report.json records headadapt_addon.__version__, and folder --resume keeps only results of the same
    version: it must move with the extension's version."""
    import headadapt_addon
    assert headadapt_addon.__version__ == MANIFEST["version"]


def test_this_blender_and_its_python_are_inside_what_the_extension_supports():
    import bpy

    assert _version(MANIFEST["blender_version_min"]) <= bpy.app.version < _version(MANIFEST["blender_version_max"])
    assert WHEEL_SET is not None, f"no scipy wheel is bundled for Python {THIS_PYTHON} (tools/build_extension.py)"
    # the tracked manifest (rewritten by a full build) lists each Python's wheel once for every platform
    assert sorted(MANIFEST["platforms"]) == list(build_extension.ALL_PLATFORMS)
    assert len(MANIFEST["wheels"]) == (len(build_extension.WHEEL_SETS) * len(build_extension.ALL_PLATFORMS)
                                       + len(build_extension.PURE_WHEELS))
    assert {f"./wheels/{n}-{v}-py3-none-any.whl" for n, v in build_extension.PURE_WHEELS} <= set(MANIFEST["wheels"])
    for ws in build_extension.WHEEL_SETS:
        prefix = f"./wheels/scipy-{ws.version}-{ws.abi}-{ws.abi}-"
        platforms = sorted(_platform_of(w) for w in MANIFEST["wheels"] if w.startswith(prefix))
        assert platforms == list(build_extension.ALL_PLATFORMS), (ws.python, MANIFEST["wheels"])


def test_linux_zip_passes_blender_validation(linux_zip):
    tool, tags = build_extension.find_blender_ext()
    proc = subprocess.run([sys.executable, str(tool), "validate", f"--valid-tags={tags}", str(linux_zip)],
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout + proc.stderr


def test_linux_zip_ships_the_addon_the_template_and_the_linux_wheel_for_each_python(linux_zip):
    with zipfile.ZipFile(linux_zip) as archive:
        names = archive.namelist()
        manifest = tomllib.loads(archive.read("blender_manifest.toml").decode("utf-8"))
    wheels = sorted(name for name in names if name.endswith(".whl"))
    pure = sorted(f"wheels/{n}-{v}-py3-none-any.whl" for n, v in build_extension.PURE_WHEELS)
    scipy = [w for w in wheels if w not in pure]
    expected = [f"wheels/scipy-{ws.version}-{ws.abi}-{ws.abi}-" for ws in build_extension.WHEEL_SETS]
    assert sorted(set(wheels) - set(scipy)) == pure, wheels
    assert len(scipy) == len(expected) and all(w.startswith(e) for w, e in zip(scipy, expected)), wheels
    assert all("manylinux" in w and w.endswith("x86_64.whl") for w in scipy), wheels
    assert manifest["build"]["generated"]["platforms"] == ["linux-x64"]
    assert sorted(manifest["build"]["generated"]["wheels"]) == sorted("./" + w for w in wheels)
    assert (manifest["blender_version_min"], manifest["blender_version_max"]) == ("4.2.13", "5.3.0")
    assert {"__init__.py", "headadapt_addon/__init__.py", "headadapt_addon/ui/panels.py",
            "assets/template/template.npz", "assets/template/template.json",
            "assets/sample_scan/scan.ply", "assets/sample_scan/landmarks.json"} <= set(names)
    dev_only = [name for name in names if name.split("/")[0] in {"headless_tests", "tools", "docs", ".venv", ".ci"}
                or name.startswith(".venv")
                or name in {"assets/build_template.py", "ha", "requirements.txt", "requirements-blender52.txt",
                            "pyproject.toml"}
                or "__pycache__" in name or name.endswith(".pyc")]
    assert dev_only == []


def _expected_operators():
    import bpy

    from headadapt_addon.ui import operators, picker

    return sorted(cls.bl_idname for mod in (operators, picker) for cls in mod.classes if issubclass(cls, bpy.types.Operator))


@pytest.mark.slow
def test_linux_zip_installs_registers_and_runs_the_workflow_in_a_clean_user_config(linux_zip, tmp_path):
    user_dir = tmp_path / "blender-user"
    installed, log = _run_blender(INSTALL, [linux_zip], user_dir, tmp_path)
    assert installed["result"] == ["FINISHED"] and installed["saved"] == ["FINISHED"], log
    assert installed["enabled"], log
    assert pathlib.Path(installed["module_file"]).parent == pathlib.Path(installed["repo_dir"]) / MANIFEST["id"]
    assert str(user_dir) in installed["repo_dir"]
    assert "HEADADAPT_PT_template" in installed["panels"], installed["panels"]
    expected = _expected_operators()
    assert len(expected) == 15 and sorted(installed["operators"]) == expected, installed["operators"]
    # each one is the installed copy's class, not the source tree's
    assert all(module.startswith(EXT_MODULE + ".") for module in installed["operators"].values()), installed["operators"]

    # Blender restarted on that config: the wheel for this Python (and no other) was installed and is
    # imported ahead of the environment's scipy; the sample workflow runs; uninstall.
    restarted, log = _run_blender(RESTART, [tmp_path / "workflow.blend"], user_dir, tmp_path)
    assert restarted["enabled_at_start"], log
    site = pathlib.Path(restarted["site"])
    assert site.parent.name == f"python{THIS_PYTHON}"
    assert restarted["site_on_path"] and restarted["site_before_interpreter"], log
    assert restarted["site_dist_info"] == sorted([f"scipy-{WHEEL_SET.version}.dist-info"] + [
        f"{n}-{v}.dist-info" for n, v in build_extension.PURE_WHEELS]), restarted["site_dist_info"]
    assert all(pathlib.Path(f).is_relative_to(site) for f in restarted["reader_files"]), restarted["reader_files"]
    assert restarted["scan_counts"] == [32918, 65141]
    assert pathlib.Path(restarted["scipy_file"]).is_relative_to(site), restarted["scipy_file"]
    assert restarted["scipy_version"] == WHEEL_SET.version
    assert restarted["scipy_files"] and all(pathlib.Path(f).is_relative_to(site) for f in restarted["scipy_files"])
    assert restarted["nearest"] == [pytest.approx(0.1 * 2 ** 0.5), 0]

    assert restarted["steps"] == {step: ["FINISHED"] for step in (
        "read_userpref", "add_template", "ply_import", "use_active_as_scan", "import_landmarks", "calibrate", "adapt",
        "bake_expressions", "load_sample_scan", "save", "open")}, log
    assert restarted["sample_scan"] == ["sample scan", 32918]
    assert restarted["result_root"] == "scan adapted"          # named after the scan object
    assert {"Basis", "joy", "surprise"} <= set(restarted["skin_keys"]) and "viseme_A" not in restarted["skin_keys"]
    assert restarted["levels"] > 1 and restarted["best_rms_mm"] < 1.0 and restarted["outcome_ok"], restarted
    assert restarted["uninstall"] == ["FINISHED"] and not restarted["still_installed"], log
    assert restarted["helper_keys"] > 0, log              # a second core baked some of the 76 keys


# Issue 17, done when: the real scans through the installed extension's operators. Each scan and its
# landmark file are read as the batch reads them (the installed meshio), made a mesh object, its
# landmarks set as the picker sets them, then Calibrate and Adapt; the adapted skin (world, scan
# frame) goes to an .npy per scan for the parent to compare with the batch's.
REAL_SCANS = """
import importlib, json, os, sys
import bpy
import numpy as np
bpy.ops.wm.read_userpref()
meshio = importlib.import_module(EXT_MODULE + ".headadapt_addon.core.meshio")
bridge = importlib.import_module(EXT_MODULE + ".headadapt_addon.blender.bridge")
landmarks = importlib.import_module(EXT_MODULE + ".headadapt_addon.blender.landmarks")
out_dir, jobs = sys.argv[1], json.loads(sys.argv[2])
done = {}
for name, (scan_path, marks_path) in jobs.items():
    bpy.ops.wm.read_homefile(use_empty=False)
    for obj in list(bpy.data.objects):
        bpy.data.objects.remove(obj)
    win = bpy.context.window_manager.windows[0]
    area = next(a for a in win.screen.areas if a.type == "VIEW_3D")
    verts, tris = meshio.read_mesh(scan_path)[:2]
    points, _meta = meshio.read_landmark_file(marks_path)
    with bpy.context.temp_override(window=win, screen=win.screen, area=area):
        obj = bpy.data.objects.new(name, bridge.new_mesh(name, verts, tris))
        bpy.context.scene.collection.objects.link(obj)
        bpy.context.view_layer.objects.active = obj
        steps = {"use_active_as_scan": sorted(bpy.ops.headadapt.use_active_as_scan())}
        landmarks.set_landmarks(obj, points)
        steps["calibrate"] = sorted(bpy.ops.headadapt.calibrate())
        steps["adapt"] = sorted(bpy.ops.headadapt.adapt())
        skin = bpy.data.objects[name + " skin"]
        np.save(os.path.join(out_dir, name + ".npy"), bridge.mesh_arrays(skin, world=True)[0])
        report = json.loads(bpy.context.scene.headadapt.report_json)
    done[name] = {"steps": steps, "best_level": report["best_level"]}
print(RESULT_MARK + json.dumps(done))
"""


@pytest.mark.slow
def test_installed_extension_adapts_every_real_scan_as_the_batch(linux_zip, tmp_path, shared_scans, tpl):
    from headadapt_addon import batch
    from headadapt_addon.core import adapt, anatomy, meshio

    data = ROOT / "headless_tests" / "data"
    jobs = {"demosthenes": ("demosthenes/demosthenes-low-res.obj", "demosthenes_fdps.json"),
            "fran": ("fran_cyberware/fran_cut.obj", "fran_fdps.json"),
            "nefertiti": ("nefertiti/nefertiti-lowres.obj", "nefertiti_fdps.json"),
            "headsq_ct": ("headsq_ct/headsq_skin.obj", "headsq_ct_fdps.json")}
    jobs = {k: (str(shared_scans / scan), str(data / marks)) for k, (scan, marks) in jobs.items()}
    user_dir = tmp_path / "blender-user"
    installed, log = _run_blender(INSTALL, [linux_zip], user_dir, tmp_path)
    assert installed["enabled"], log
    done, log = _run_blender(REAL_SCANS, [tmp_path, json.dumps(jobs)], user_dir, tmp_path)
    for name, (scan, marks) in jobs.items():
        assert done[name]["steps"] == {s: ["FINISHED"] for s in ("use_active_as_scan", "calibrate", "adapt")}, log
        verts, tris = meshio.read_mesh(scan)[:2]
        points, _meta = meshio.read_landmark_file(marks)
        # the batch's fit (its rounding, its options), carried through the anatomy as the panels' result is
        result = adapt.adapt(tpl, batch.as_blender_stores(verts), tris, points, batch.adapt_options())
        want = result.to_scan(anatomy.transfer(tpl, result).parts["skin"])
        got = np.load(tmp_path / f"{name}.npy")
        size = float(np.ptp(verts, axis=0).max())
        assert done[name]["best_level"] == result.best_level
        assert float(np.abs(got - want).max()) < 1e-6 * size, (name, float(np.abs(got - want).max()), size)
