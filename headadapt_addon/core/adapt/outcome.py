"""How an adaptation ended, honestly (fit_outcome), and the same in words for the batch log, the
Adapt operator's report and the Report panel. `outcome` is AdaptResult.outcome (report()["outcome"]):
folds_left, seen_rms_mm, seen_vertices, marker_rms_mm (None without markers), warnings, ok."""

from __future__ import annotations

import numpy as np

from ..tol import MM


def fit_outcome(distances, face, folds_left, marker_rms_mm, flagged, options, notes=()):
    """How a fit ended, honestly: folds left, distance RMS over the face the scan shows (mm; `face` a
    vertex mask, FACE_REGIONS), marker RMS (mm), one warning line per problem, and ok (False: no
    folds may be left, the RMS must stay under options.bad_fit_rms_mm)."""
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
    return {"folds_left": int(folds_left), "seen_rms_mm": rms, "seen_vertices": int(seen.sum()),
            "marker_rms_mm": marker_rms_mm, "warnings": warnings, "ok": ok}


def measures(outcome):
    """The outcome's figures as short phrases: folds left, seen-skin RMS, marker RMS (if markers)."""
    out = [f"{outcome['folds_left']} folded triangles left",
           f"seen-skin RMS {outcome['seen_rms_mm']:.2f} mm over {outcome['seen_vertices']} vertices"]
    if outcome.get("marker_rms_mm") is not None:
        out.append(f"marker RMS {outcome['marker_rms_mm']:.2f} mm")
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
