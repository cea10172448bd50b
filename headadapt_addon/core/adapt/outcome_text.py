"""How an adaptation ended, in words: the same lines for the batch log, the Adapt operator's report
and the Report panel (no bpy). `outcome` is AdaptResult.outcome (report()["outcome"]): folds_left,
seen_rms_mm, seen_vertices, marker_rms_mm (None without markers), warnings, ok."""


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
