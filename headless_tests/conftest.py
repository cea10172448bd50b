"""Shared fixtures: a private Blender user config, a clean scene, the real scans in ../shared."""

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
