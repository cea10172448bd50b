"""The adaptation (paper sec 3 to 5) on numpy arrays: ``adapt(template, scan_verts, scan_tris,
clicks, AdaptOptions())`` -> ``AdaptResult``.

pipeline: the steps in order; options: settings, level report, result; fit: the scan side, pairs
and the fit in progress; level0: the global map; pairs: a level's feature-point pairs; levels: the
CSRBF level and its ICP rounds; clicks: wrong clicks, swapped labels, the closed mouth; outcome: how
it ended; calibration, rbf, metrics, suggest: the paper's building blocks.
"""

from .options import AdaptOptions, AdaptResult, Level
from .pipeline import adapt

__all__ = ["AdaptOptions", "AdaptResult", "Level", "adapt"]
