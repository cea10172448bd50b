"""How an adaptation ended, honestly (fit_outcome), and the same in words for the batch log, the
Adapt operator's report and the Report panel. `outcome` is AdaptResult.outcome (report()["outcome"]):
folds_left, seen_rms_mm, seen_vertices, marker_rms_mm (None without markers), scan_beyond_pct,
warnings, ok."""

from __future__ import annotations

import numpy as np

from ..tol import MM

BEYOND_SAMPLE = 8000          # scan points looked at by scan_beyond (every k-th): a share, to about 0.2%


def scan_beyond(fit, verts):
    """The share (%) of the scan's points by the face and ears that lie over options.beyond_mm outside
    the adapted skin verts (n,3; template frame): scan the fit did not reach, such as an ear's rim the
    adapted ear does not cover. The seen-skin RMS cannot show it (it counts the vertices matched to
    the scan, and those are not). A point counts by the skin's nearest vertex (its normal within 60
    degrees of the point's) and, when that vertex's tangent plane puts it half that far out, by its
    exact closest point on the skin (outside, on a face or ear triangle, the normals agreeing)."""
    from scipy.spatial import cKDTree  # here: enabling the add-on imports this module, and no scipy

    from ..mesh import geometry, spatial
    from .options import FACE_REGIONS

    o, tris, step = fit.options, fit.tris, max(1, len(fit.scan.verts) // BEYOND_SAMPLE)
    P, N = fit.scan.verts[::step], fit.scan.vertex_normals[::step]
    near = fit.tpl.region_mask(*FACE_REGIONS, "ear_l", "ear_r")
    n = geometry.vertex_normals(verts, tris)
    i = cKDTree(verts).query(P, workers=-1)[1]
    use = near[i] & (np.einsum("ij,ij->i", N, n[i]) > 0.5)
    cand = np.flatnonzero(use & (np.einsum("ij,ij->i", P - verts[i], n[i]) > 0.5 * o.beyond_mm / MM))
    if not len(cand):
        return 0.0
    q, f, d = spatial.MeshQuery(verts, tris, backend=o.backend).closest_points(P[cand])
    fn = geometry.face_normals(verts, tris[f])
    out = ((np.einsum("ij,ij->i", P[cand] - q, fn) > 0) & (d > o.beyond_mm / MM)
           & (np.einsum("ij,ij->i", N[cand], fn) > 0.5) & geometry.all_corners(near, tris[f]))
    return round(100.0 * int(out.sum()) / max(int(use.sum()), 1), 2)


def fit_outcome(distances, face, folds_left, marker_rms_mm, flagged, options, notes=(), beyond=None):
    """How a fit ended, honestly: folds left, distance RMS over the face the scan shows (mm; `face` a
    vertex mask, FACE_REGIONS), marker RMS (mm), the scan it did not reach (beyond: scan_beyond's %),
    one warning line per problem, and ok (False: no folds may be left, the RMS must stay under
    options.bad_fit_rms_mm; scan not reached warns, the fit may still be trusted where it lies)."""
    seen = np.isfinite(distances) & face
    rms = float(np.sqrt(np.mean(distances[seen] ** 2)) * MM) if seen.any() else float("nan")
    warnings = list(notes) + [f"FDP {k}: {why}" for k, why in flagged.items()]
    ok = True
    if folds_left:
        ok = False
        warnings.append(f"{folds_left} folded triangles left in the adapted skin")
    if not np.isfinite(rms) or rms > options.bad_fit_rms_mm:
        ok = False
        warnings.append(f"the adapted face lies {rms:.2f} mm RMS from the scan over {int(seen.sum())} seen "
                        f"vertices (limit {options.bad_fit_rms_mm:.2f} mm): the fit did not reach the scan")
    if beyond is not None and beyond > options.beyond_pct:
        warnings.append(f"{beyond:.1f}% of the scan by the face and ears lies over {options.beyond_mm:.0f} mm "
                        f"outside the adapted skin (an ear's rim, often): the fit did not reach it there")
    return {"folds_left": int(folds_left), "seen_rms_mm": rms, "seen_vertices": int(seen.sum()),
            "marker_rms_mm": marker_rms_mm, "scan_beyond_pct": beyond, "warnings": warnings, "ok": ok}


def measures(outcome):
    """The outcome's figures as short phrases: folds left, seen-skin RMS, marker RMS (if markers), the
    share of the scan by the face and ears not reached (scan_beyond, if measured)."""
    out = [f"{outcome['folds_left']} folded triangles left",
           f"seen-skin RMS {outcome['seen_rms_mm']:.2f} mm over {outcome['seen_vertices']} vertices"]
    if outcome.get("marker_rms_mm") is not None:
        out.append(f"marker RMS {outcome['marker_rms_mm']:.2f} mm")
    if outcome.get("scan_beyond_pct") is not None:
        out.append(f"scan not reached {outcome['scan_beyond_pct']:.1f}%")
    return out


def verdict(outcome):
    """One line: whether the fit can be trusted, and its figures."""
    return ("fit ok" if outcome["ok"] else "fit NOT trustworthy") + ": " + ", ".join(measures(outcome))


def warning_lines(outcome, flagged=None, dropped=()):
    """One line per warning: the outcome's own (swapped labels, flagged FDPs, folds left, too far from
    the scan), each flagged FDP marked dropped or kept, and any flagged FDP the outcome does not name."""
    lines = list((outcome or {}).get("warnings", []))
    flagged = flagged or {}
    for name, why in flagged.items():
        tag = " (dropped)" if name in dropped else " (kept)"
        i = next((i for i, w in enumerate(lines) if w.startswith(f"FDP {name}:")), None)
        if i is None:
            lines.append(f"FDP {name}: {why}{tag}")
        else:
            lines[i] += tag
    return lines
