"""Build HeadAdapt's per-platform extension zips with Blender's own extension tool.

    python tools/build_extension.py [--out dist] [--platforms linux-x64,windows-x64,macos-arm64,macos-x64]
                                    [--wheel-cache DIR]

1. Fetches the scipy wheels for each platform with ``pip download`` (the Python running this script):
   one per Python that Blender ships (``WHEEL_SETS``), and the pure-Python wheels of the scan readers
   (``PURE_WHEELS``: plyfile, trimesh; the same file for every platform and Python), into a cache
   (default ``$HEADADAPT_CACHE/wheels``, ``~/.cache/headadapt/wheels``), reused when present.
2. Copies them into ``./wheels/`` (gitignored).
3. With every platform requested (the default), rewrites ``platforms`` and ``wheels`` in
   ``blender_manifest.toml`` (sorted) and builds from the repository root; for a subset it leaves the
   tracked manifest alone and builds from a staging copy whose manifest lists only that subset.
4. Runs ``blender_ext.py build --split-platforms`` then ``blender_ext.py validate`` on every zip.

Each zip holds its platform's wheel for every Python: Blender 4.2 to 5.0 run Python 3.11 (scipy 1.13.1,
cp311), 5.1 and 5.2 run Python 3.13 (scipy 1.16.3, cp313, built for numpy 2). Blender installs only the
wheel whose platform and Python tags match the running Blender. numpy is never bundled (Blender's own is
used). Runs under plain Python: ``blender_ext.py`` is found in the ``bpy`` module's package (not imported).
"""

import argparse
import glob
import os
import pathlib
import re
import shutil
import subprocess
import sys
import tempfile
import tomllib

ROOT = pathlib.Path(__file__).resolve().parents[1]
MANIFEST = ROOT / "blender_manifest.toml"
WHEELS_DIR = ROOT / "wheels"


class WheelSet:
    """One scipy release for one Python, with the pip ``--platform`` tag each Blender platform's
    wheel is published under (the oldest OS that release supports)."""

    def __init__(self, version, python, blenders, pip_platform):
        self.name, self.version, self.python, self.blenders = "scipy", version, python, blenders
        self.pip_platform = dict(pip_platform)
        self.abi = "cp" + python.replace(".", "")

    @property
    def requirement(self):
        return f"{self.name}=={self.version}"

    def pattern(self):
        return f"{self.name}-{self.version}-{self.abi}-{self.abi}-*.whl"


WHEEL_SETS = (
    # Blender 4.2 LTS to 5.0: Python 3.11, numpy 1.26 (the scipy HeadAdapt has shipped since 0.1.0).
    WheelSet("1.13.1", "3.11", "Blender 4.2 to 5.0", {
        "linux-x64": "manylinux_2_17_x86_64",
        "macos-arm64": "macosx_12_0_arm64",
        "macos-x64": "macosx_10_9_x86_64",
        "windows-x64": "win_amd64",
    }),
    # Blender 5.1 and 5.2 LTS: Python 3.13, numpy 2.x (scipy 1.16.3 accepts numpy 1.25.2 to 2.5;
    # 1.17 dropped the manylinux2014 wheel).
    WheelSet("1.16.3", "3.13", "Blender 5.1 to 5.2", {
        "linux-x64": "manylinux_2_17_x86_64",
        "macos-arm64": "macosx_12_0_arm64",
        "macos-x64": "macosx_10_14_x86_64",
        "windows-x64": "win_amd64",
    }),
)
# The scan readers (headadapt_addon/core/readers.py): pure Python on numpy, one wheel for every zip.
# plyfile 1.1.4 and later require numpy 2 (Blender 4.2 to 5.0 ship numpy 1.26).
PURE_WHEELS = (("plyfile", "1.1.3"), ("trimesh", "4.5.3"))
PIP_PLATFORM = WHEEL_SETS[0].pip_platform
assert all(set(ws.pip_platform) == set(PIP_PLATFORM) for ws in WHEEL_SETS)
ALL_PLATFORMS = tuple(sorted(PIP_PLATFORM))

# Never copied into a staging tree (the manifest's own exclusions apply on top when building).
STAGING_IGNORE = shutil.ignore_patterns(
    ".git", ".venv*", ".pytest_cache", "__pycache__", "*.pyc", "dist", "out", "build", "wheels",
    "*.zip",
)


class BuildError(RuntimeError):
    """A step failed; the message says which and why."""


def default_wheel_cache():
    base = os.environ.get("HEADADAPT_CACHE") or os.path.join(os.path.expanduser("~"), ".cache", "headadapt")
    return pathlib.Path(base) / "wheels"


def find_blender_ext():
    """``(blender_ext.py, tags.py)`` from the newest Blender version inside the installed ``bpy`` module."""
    import importlib.util

    spec = importlib.util.find_spec("bpy")
    roots = list(spec.submodule_search_locations or []) if spec else []
    found = []
    for root in roots:
        for tool in glob.glob(os.path.join(root, "*", "scripts", "addons_core", "bl_pkg", "cli", "blender_ext.py")):
            version_dir = pathlib.Path(tool).parents[4]
            try:
                version = tuple(int(part) for part in version_dir.name.split("."))
            except ValueError:
                continue
            tags = version_dir / "scripts" / "modules" / "_bpy_internal" / "extensions" / "tags.py"
            found.append((version, pathlib.Path(tool), tags))
    if not found:
        raise BuildError(
            f"Blender's blender_ext.py not found: {sys.executable} has no bpy module "
            "(run with the project's Python: .venv/bin/python or ./ha python)"
        )
    _, tool, tags = max(found)
    return tool, tags


def fetch_wheel(platform, cache, wheel_set):
    """The cached scipy wheel of ``wheel_set`` for one Blender platform, downloading it with pip when absent."""
    pip_tag = wheel_set.pip_platform[platform]
    cache_dir = cache / pip_tag
    pattern = wheel_set.pattern()
    cached = sorted(cache_dir.glob(pattern))
    if len(cached) == 1:
        return cached[0]
    if len(cached) > 1:
        raise BuildError(f"{cache_dir} holds several wheels matching {pattern}; remove the stale ones")
    cache_dir.mkdir(parents=True, exist_ok=True)
    print(f"fetching {wheel_set.requirement} for {platform} ({pip_tag}, Python {wheel_set.python}: "
          f"{wheel_set.blenders}) into {cache_dir}", flush=True)
    command = [
        sys.executable, "-m", "pip", "download", "--quiet", "--only-binary=:all:", "--no-deps",
        "--python-version", wheel_set.python, "--implementation", "cp", "--abi", wheel_set.abi,
        "--platform", pip_tag, "--dest", str(cache_dir), wheel_set.requirement,
    ]
    result = subprocess.run(command, capture_output=True, text=True)
    cached = sorted(cache_dir.glob(pattern))
    if result.returncode != 0 or len(cached) != 1:
        raise BuildError(
            f"pip could not fetch {wheel_set.requirement} for {platform} (--platform {pip_tag}, "
            f"Python {wheel_set.python}):\n{result.stdout}{result.stderr}".rstrip()
        )
    return cached[0]


def fetch_pure_wheel(name, version, cache):
    """The cached ``NAME-VERSION-py3-none-any.whl``, downloading it with pip when absent."""
    cache_dir = cache / "py3-none-any"
    wheel = cache_dir / f"{name}-{version}-py3-none-any.whl"
    if wheel.is_file():
        return wheel
    cache_dir.mkdir(parents=True, exist_ok=True)
    print(f"fetching {name}=={version} (pure Python, every platform) into {cache_dir}", flush=True)
    result = subprocess.run([sys.executable, "-m", "pip", "download", "--quiet", "--only-binary=:all:", "--no-deps",
                             "--dest", str(cache_dir), f"{name}=={version}"], capture_output=True, text=True)
    if result.returncode != 0 or not wheel.is_file():
        raise BuildError(f"pip could not fetch {name}=={version}:\n{result.stdout}{result.stderr}".rstrip())
    return wheel


def fetch_wheels(platforms, cache):
    """Every platform's wheels, one scipy per Python in ``WHEEL_SETS`` and the ``PURE_WHEELS``:
    ``{platform: [wheel, ...]}``."""
    pure = [fetch_pure_wheel(name, version, cache) for name, version in PURE_WHEELS]
    return {platform: [fetch_wheel(platform, cache, ws) for ws in WHEEL_SETS] + pure for platform in platforms}


def sync_wheels(wheels, keep_names):
    """Copy ``wheels`` into ./wheels/; drop any wheel there whose name is not in ``keep_names``."""
    WHEELS_DIR.mkdir(exist_ok=True)
    for stale in WHEELS_DIR.glob("*.whl"):
        if stale.name not in keep_names:
            stale.unlink()
    for wheel in wheels:
        target = WHEELS_DIR / wheel.name
        if not target.exists() or target.stat().st_size != wheel.stat().st_size:
            shutil.copy2(wheel, target)


def _toml_list(key, values, multiline):
    if not multiline:
        return f"{key} = [{', '.join(_quote(v) for v in values)}]\n"
    return f"{key} = [\n" + "".join(f"  {_quote(v)},\n" for v in values) + "]\n"


def _quote(value):
    return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'


def manifest_with(text, platforms, wheel_names):
    """``text`` (a manifest) with its top-level ``platforms`` and ``wheels`` set, sorted."""
    platforms = sorted(platforms)
    wheel_paths = sorted(f"./wheels/{name}" for name in wheel_names)
    for key, block in (
        ("platforms", _toml_list("platforms", platforms, multiline=False)),
        ("wheels", _toml_list("wheels", wheel_paths, multiline=True)),
    ):
        pattern = re.compile(rf"^{key}\s*=\s*\[[^\]]*\]\s*?\n", re.MULTILINE)
        if pattern.search(text):
            text = pattern.sub(lambda _match, block=block: block, text, count=1)
        else:
            table = re.search(r"^\[", text, re.MULTILINE)
            at = table.start() if table else len(text)
            text = text[:at] + block + ("\n" if table else "") + text[at:]
    data = tomllib.loads(text)
    if data.get("platforms") != platforms or data.get("wheels") != wheel_paths:
        raise BuildError("rewriting blender_manifest.toml did not give the expected platforms/wheels")
    return text


def run_tool(tool, args, what):
    result = subprocess.run([sys.executable, str(tool), *args], capture_output=True, text=True)
    output = (result.stdout + result.stderr).strip()
    if result.returncode != 0 or "FATAL_ERROR" in output:
        raise BuildError(f"blender_ext.py {what} failed (exit {result.returncode}):\n{output}")
    return output


def build(out, platforms, cache):
    tool, tags = find_blender_ext()
    manifest_text = MANIFEST.read_text(encoding="utf-8")
    manifest = tomllib.loads(manifest_text)
    ext_id, version = manifest["id"], manifest["version"]

    wheels = sorted({wheel for per_platform in fetch_wheels(platforms, cache).values() for wheel in per_platform})
    full = set(platforms) == set(ALL_PLATFORMS)

    # ./wheels/ keeps what the tracked manifest lists plus what this build ships.
    listed = {pathlib.PurePosixPath(path).name for path in manifest.get("wheels", [])}
    names = {wheel.name for wheel in wheels}
    sync_wheels(wheels, names if full else names | listed)

    out.mkdir(parents=True, exist_ok=True)
    zips = [out / f"{ext_id}-{version}-{platform.replace('-', '_')}.zip" for platform in sorted(platforms)]
    for stale in zips:
        stale.unlink(missing_ok=True)

    build_args = ["build", "--split-platforms", "--output-dir", str(out), f"--valid-tags={tags}"]
    if full:
        new_text = manifest_with(manifest_text, platforms, names)
        if new_text != manifest_text:
            MANIFEST.write_text(new_text, encoding="utf-8")
            print(f"updated {MANIFEST.relative_to(ROOT)}: platforms and wheels", flush=True)
        run_tool(tool, [*build_args, "--source-dir", str(ROOT)], "build")
    else:
        with tempfile.TemporaryDirectory(prefix="headadapt-ext-") as staging:
            source = pathlib.Path(staging) / "headadapt"
            shutil.copytree(ROOT, source, ignore=STAGING_IGNORE)
            (source / "wheels").mkdir()
            for wheel in wheels:
                shutil.copy2(WHEELS_DIR / wheel.name, source / "wheels" / wheel.name)
            (source / MANIFEST.name).write_text(manifest_with(manifest_text, platforms, names), encoding="utf-8")
            run_tool(tool, [*build_args, "--source-dir", str(source)], "build")

    for zip_path in zips:
        if not zip_path.is_file():
            raise BuildError(f"blender_ext.py build did not write {zip_path}")
        run_tool(tool, ["validate", f"--valid-tags={tags}", str(zip_path)], f"validate {zip_path.name}")
    return zips


def parse_args(argv):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=pathlib.Path, default=ROOT / "dist", help="output folder (default: dist)")
    parser.add_argument(
        "--platforms", default=",".join(ALL_PLATFORMS),
        help=f"comma-separated Blender platforms (default: all of {','.join(ALL_PLATFORMS)})",
    )
    parser.add_argument(
        "--wheel-cache", type=pathlib.Path, default=None,
        help=f"where downloaded wheels are kept and reused (default: {default_wheel_cache()})",
    )
    args = parser.parse_args(argv)
    platforms = sorted({p.strip() for p in args.platforms.split(",") if p.strip()})
    unknown = [p for p in platforms if p not in PIP_PLATFORM]
    if not platforms or unknown:
        parser.error(f"unknown platform(s) {', '.join(unknown) or '(none)'}; choose from {', '.join(ALL_PLATFORMS)}")
    args.platforms = platforms
    args.wheel_cache = (args.wheel_cache or default_wheel_cache()).expanduser().resolve()
    args.out = args.out.expanduser().resolve()
    return args


def main(argv=None):
    args = parse_args(argv)
    try:
        zips = build(args.out, args.platforms, args.wheel_cache)
    except (BuildError, OSError) as error:
        print(f"build_extension: {error}", file=sys.stderr)
        return 1
    for zip_path in zips:
        print(f"{zip_path.name}  {zip_path.stat().st_size / 1e6:.1f} MB  (validated)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
