"""HeadAdapt: adapt an anatomical MPEG-4 template head onto a range scan, inside Blender.

Layers (one direction of dependency): operators/panels -> bridge (bpy <-> numpy) -> core (numpy/scipy).
``headadapt_addon.core`` never imports bpy; this module registers the Blender side lazily so the
core and the batch job import without Blender.
"""

from .core import __version__  # noqa: F401  (the package's version, kept in the core)


def _modules():
    from .ui import operators, panels, picker, props
    return (props, operators, picker, panels)


def register():
    """Register the add-on's properties, operators and panels with Blender."""
    for mod in _modules():
        mod.register()


def unregister():
    """Unregister everything :func:`register` added, in reverse order."""
    for mod in reversed(_modules()):
        mod.unregister()
