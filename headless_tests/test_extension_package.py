"""The built Linux zip passes Blender's validation, installs and enables as an extension in a clean
user config, and its bundled scipy is the one Blender's Python imports.

The zip is built once per session with tools/build_extension.py (reused while it is newer than every
file it is built from; the first build downloads the ~37 MB scipy wheel into the wheel cache).
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

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
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
repo = next(r for r in bpy.context.preferences.extensions.repos if r.module == "user_default")
print(RESULT_MARK + json.dumps({
    "result": sorted(result),
    "enabled": EXT_MODULE in bpy.context.preferences.addons,
    "module_file": getattr(module, "__file__", None),
    "repo_dir": repo.directory,
    "extensions_dir": bpy.utils.user_resource("EXTENSIONS"),
    "panels": panels,
}))
"""

# A fresh start with the same user config: Blender puts the extensions' site-packages ahead of the
# interpreter's own, so `import scipy` must resolve to the bundled wheel. Then uninstall.
RESTART = """
import json, os, sys
import bpy
import numpy as np
import scipy, scipy.spatial, scipy.sparse.linalg
extensions_dir = bpy.utils.user_resource("EXTENSIONS")
site = os.path.join(extensions_dir, ".local", "lib", "python%d.%d" % sys.version_info[:2], "site-packages")
distance, index = scipy.spatial.cKDTree(np.eye(3)).query([0.9, 0.1, 0.0])
repo_index = [r.module for r in bpy.context.preferences.extensions.repos].index("user_default")
uninstall = bpy.ops.extensions.package_uninstall(repo_index=repo_index, pkg_id=PKG_ID)
repo_dir = bpy.context.preferences.extensions.repos[repo_index].directory
print(RESULT_MARK + json.dumps({
    "site": site,
    "site_on_path": site in sys.path,
    "site_before_interpreter": [p for p in sys.path if p.endswith("site-packages")][:1] == [site],
    "scipy_file": scipy.__file__,
    "scipy_version": scipy.__version__,
    "nearest": [float(distance), int(index)],
    "uninstall": sorted(uninstall),
    "still_installed": os.path.exists(os.path.join(repo_dir, PKG_ID)),
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


def test_linux_zip_passes_blender_validation(linux_zip):
    tool, tags = build_extension.find_blender_ext()
    proc = subprocess.run([sys.executable, str(tool), "validate", f"--valid-tags={tags}", str(linux_zip)],
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout + proc.stderr


def test_linux_zip_ships_the_addon_the_template_and_only_the_linux_wheel(linux_zip):
    with zipfile.ZipFile(linux_zip) as archive:
        names = archive.namelist()
        manifest = tomllib.loads(archive.read("blender_manifest.toml").decode("utf-8"))
    wheels = [name for name in names if name.endswith(".whl")]
    assert len(wheels) == 1 and wheels[0].startswith("wheels/scipy-1.13.1-cp311-cp311-manylinux"), wheels
    assert manifest["build"]["generated"]["platforms"] == ["linux-x64"]
    assert manifest["blender_version_min"] == "4.2.0"
    assert {"__init__.py", "headadapt_addon/__init__.py", "headadapt_addon/ui.py",
            "assets/template/template.npz", "assets/template/template.json"} <= set(names)
    dev_only = [name for name in names if name.split("/")[0] in {"headless_tests", "tools", "docs", ".venv", ".ci"}
                or name in {"assets/build_template.py", "ha", "requirements.txt", "pytest.ini"}
                or "__pycache__" in name or name.endswith(".pyc")]
    assert dev_only == []


def test_linux_zip_installs_and_enables_in_clean_user_config(linux_zip, tmp_path):
    user_dir = tmp_path / "blender-user"
    installed, log = _run_blender(INSTALL, [linux_zip], user_dir, tmp_path)
    assert installed["result"] == ["FINISHED"], log
    assert installed["enabled"], log
    assert pathlib.Path(installed["module_file"]).parent == pathlib.Path(installed["repo_dir"]) / MANIFEST["id"]
    assert str(user_dir) in installed["repo_dir"]
    assert "HEADADAPT_PT_template" in installed["panels"], installed["panels"]

    # Blender restarted on that config: the bundled scipy (not the interpreter's) is imported; uninstall.
    restarted, log = _run_blender(RESTART, [], user_dir, tmp_path)
    site = pathlib.Path(restarted["site"])
    assert restarted["site_on_path"] and restarted["site_before_interpreter"], log
    assert pathlib.Path(restarted["scipy_file"]).is_relative_to(site), restarted["scipy_file"]
    assert restarted["scipy_version"] == "1.13.1"
    assert restarted["nearest"] == [pytest.approx(0.1 * 2 ** 0.5), 0]
    assert restarted["uninstall"] == ["FINISHED"] and not restarted["still_installed"], log
