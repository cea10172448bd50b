"""Blender tests: each leaves Blender's factory file behind it, so no test sees another's objects."""

import pytest


@pytest.fixture(autouse=True)
def fresh_file():
    """After each test, Blender's empty factory file again."""
    yield
    import bpy

    bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
