"""The clicks and the held-out markers within the scan's reach: a point far off the scan is another
scan's, in another unit or another frame (LandmarkError naming it, the batch's exit 2)."""

from __future__ import annotations

import numpy as np

from .. import mpeg4
from ..exceptions import LandmarkError
from ..mesh import geometry
from ..template import Template
from ..tol import MM
from . import calibration
from .options import AdaptOptions
from .scan import ScanSide


def check_on_surface(scan: ScanSide, q_fdp: dict[str, np.ndarray], options: AdaptOptions) -> None:
    """Every FDP must lie on the scan (options.off_surface_mm; the ear FDPs twice that): a click far
    off is another scan's, or in another unit."""
    names = list(q_fdp)
    _, _, dist = scan.query.closest_points(np.array([q_fdp[k] for k in names]))
    _refuse_far(names, dist, "from the scan surface", options)


def check_in_reach(verts: np.ndarray, q_fdp: dict[str, np.ndarray], options: AdaptOptions, hint=None,
                   markers: bool = False) -> None:
    """check_on_surface's test against the scan's bounding box, before the scan is prepared (no point
    of the box is farther than the surface): clicks in another unit than the scan (millimetres on a
    scan in metres) shrink the scan to a speck in the template's frame, which clustering would erase.
    hint(): a sentence for the error (calibration.unit_hint in the file's frame: in the template's a
    speck's size is lost to rounding). markers: the points are held-out markers, not clicks."""
    names = list(q_fdp)
    q = np.array([q_fdp[k] for k in names])
    lo, hi = geometry.bounds(verts)
    dist = np.linalg.norm(np.maximum(lo - q, 0.0) + np.maximum(q - hi, 0.0), axis=1)
    _refuse_far(names, dist, "outside the scan's bounding box", options, hint, markers)


def check_markers(scan: ScanSide, tpl: Template, markers: dict | None, sim: calibration.Similarity,
                  scan_verts: np.ndarray, options: AdaptOptions) -> None:
    """Held-out markers (a landmark file's "markers", in the scan's frame) must name an FDP or one of the
    template's markers and lie within options.marker_reach_mm of the scan's bounding box (a marker may
    sit in a hole at the scan's edge). They choose the level by their error (E = alpha E_d + beta E_m,
    sec 5): the sample's markers left 1 m from its scan chose level 1 (seen-skin RMS 0.96 mm against
    0.13) and the run said "fit ok"; a misspelt marker was left out of the figure unsaid. LandmarkError
    names the first one wrong."""
    if not markers:
        return
    known = {**tpl.fdp_points(), **tpl.marker_points()}
    for name in markers:
        if name not in known:
            raise LandmarkError(f'marker "{name}" is neither an FDP nor one of the template\'s markers '
                                f'({", ".join(tpl.marker_points())})')
    given = {k: np.asarray(p, dtype=np.float64) for k, p in markers.items()}
    check_in_reach(scan.verts, {k: sim.apply(p) for k, p in given.items()}, options, markers=True,
                   hint=lambda: calibration.unit_hint(np.array(geometry.bounds(scan_verts)), given, "markers"))


def _refuse_far(names: list[str], dist: np.ndarray, where: str, options: AdaptOptions, hint=None,
                markers: bool = False) -> None:
    """LandmarkError naming the first FDP farther than options.off_surface_mm (ears: twice that), or the
    first marker farther than options.marker_reach_mm, with hint()'s sentence (calibration.unit_hint) if any."""
    for k, d in zip(names, dist):
        if d * MM > (options.marker_reach_mm if markers else options.off_surface_mm * (2 if k in ("3.5", "3.6") else 1)):
            said, far = hint() if hint else "", f"{d * MM:.{'1f' if d * MM < 1e6 else '3g'}} mm {where}"
            if said:            # the unit first: a distance in the template's frame says little then
                named = f"marker {k}" if markers else f"FDP {k}, {mpeg4.FDPS[k].label},"
                raise LandmarkError(f"{said[0].upper()}{said[1:]} ({named} is {far} in the template's frame)")
            if markers:
                raise LandmarkError(f"marker {k} is {far} after calibration: markers must be measured on this "
                                    "scan, in its frame and unit")
            raise LandmarkError(f"FDP {k} ({mpeg4.FDPS[k].label}) is {far} after calibration: landmarks must be "
                                "picked on this scan (a scan trimmed since, the wrong file or unit?)")
