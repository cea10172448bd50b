"""The adaptation (paper sec 3 to 5) on numpy arrays: ``adapt(template, scan_verts, scan_tris,
clicks, AdaptOptions())`` -> ``AdaptResult``.

pipeline: the steps in order; options: settings, level report, result; fit: the scan side, pairs
and the fit in progress; level0: the global map; pairs: a level's feature-point pairs; levels: the
CSRBF level and its ICP rounds; clicks: wrong clicks, swapped labels, the closed mouth; outcome: how
it ended; calibration, rbf, metrics, suggest: the paper's building blocks.
"""

from .options import AdaptOptions, AdaptResult, Level

__all__ = ["AdaptOptions", "AdaptResult", "Level", "adapt"]


def __getattr__(name):
    """``adapt`` imported when first asked for: the add-on's registration (Blender's start) needs the
    options only, not the pipeline and scipy behind it."""
    if name == "adapt":
        from .pipeline import adapt
        return adapt
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
