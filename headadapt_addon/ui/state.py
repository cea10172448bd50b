"""What the operators and panels read of the scene: the bundled template, the add-on's settings, whether
the scan and its clicks are what the batch accepts (each problem as a sentence for a greyed button or a
report), the scan's arrays and the options the panels make."""

import numpy as np

from ..blender import bridge, landmarks
from ..core import mpeg4
from ..core.exceptions import HeadAdaptError


def template():
    """The bundled template (loaded once per session: core.template.bundled_template)."""
    from ..core.template import bundled_template
    return bundled_template()


def settings(context):
    return context.scene.headadapt


def scan_problem(context):
    """None when the scene has a usable scan, else what is wrong (for poll messages and reports)."""
    scan = settings(context).scan
    if scan is None:
        return "no scan selected: pick the scan object in the Scan panel"
    if scan.type != "MESH":
        return f"{scan.name!r} is not a mesh"
    if context.scene.objects.get(scan.name) != scan:
        return f"the scan {scan.name!r} is not in the scene (deleted?): pick the scan object in the Scan panel"
    scale = scan.matrix_world.to_scale()
    if max(scale) - min(scale) > 1e-4 * max(abs(max(scale)), 1e-12):
        # the result's root takes the scan's transform, and an object cannot hold the shear that a
        # stretch and the fit's turn make together: the head would be drawn off the scan
        return (f"the scan {scan.name!r} is scaled unevenly ({', '.join(f'{c:g}' for c in scale)}): apply "
                "its scale first (Object > Apply > Scale)")
    if len(scan.data.polygons) == 0:
        return f"scan {scan.name!r} has no faces (a point cloud is not a surface)"
    return None


def visible_template_fdps():
    """The template FDPs a scanner can see ({id: (3,)} template frame): the ones adapt calibrates on."""
    from ..core.adapt.options import SCANNER_VISIBLE_PARTS
    tpl = template()
    return {k: p for k, p in tpl.fdp_points().items() if tpl.meta["fdps"][k]["part"] in SCANNER_VISIBLE_PARTS}


def landmark_problem(context):
    """None when the scan and its landmarks are what the batch's adapt accepts (core.adapt.calibration:
    at least MIN_FDPS visible FDPs, finite, distinct, not on one line or plane; the paper's method
    also needs its 8), else what is missing, as a sentence for a poll message or a report."""
    from ..core.adapt import calibration
    problem = scan_problem(context)
    if problem:
        return problem
    s = settings(context)
    pts = landmarks.get_landmarks(s.scan)
    if not pts:
        return (f"no landmarks on {s.scan.name!r}: click at least {calibration.MIN_FDPS} FDPs "
                f"(best {', '.join(mpeg4.CLICKS_8)}) or import a landmark file")
    try:
        given = calibration.validate_landmarks(pts, what=f"scan {s.scan.name!r}")
    except HeadAdaptError as exc:
        return str(exc)
    visible = visible_template_fdps()
    usable = [k for k in given if k in visible]
    if len(usable) < calibration.MIN_FDPS:
        return (f"{len(usable)} of the placed FDPs lie on the skin or the eyes; calibration needs at least "
                f"{calibration.MIN_FDPS} (best {', '.join(mpeg4.CLICKS_8)})")
    if s.calibration == "paper":
        missing = [k for k in mpeg4.CALIBRATION_FDPS if k not in given]
        if missing:
            return ("the paper's calibration needs FDP " + ", ".join(missing)
                    + ": place them or choose Auto or Least squares")
    return None


def calibration_ready(context):
    """The scene has a usable scan with enough landmarks to calibrate and adapt (the batch's rule)."""
    return landmark_problem(context) is None


def scan_arrays(context):
    """(the scan object, its vertices (n,3) and triangles (m,3) in its own frame, as numpy arrays)."""
    scan = settings(context).scan
    verts, tris = bridge.mesh_arrays(scan, world=False)
    return scan, verts, tris


def head_size_mm():
    """The template head's width (ear to ear), mm: what calibration residuals are judged against."""
    return float(np.ptp(template().skin.verts[:, 0])) * 1000.0


def adapt_options(s, levels=-1):
    """The AdaptOptions of the scene settings s (levels >= 0 overrides s.max_levels): the one place the
    panels make their options, from the same fields and defaults as the batch (batch.adapt_options)."""
    from ..batch import adapt_options as batch_options
    return batch_options(levels=s.max_levels if levels < 0 else levels, calibration=s.calibration,
                         keep_flagged=not s.drop_flagged)
