"""Head calibration (paper sec 3.1): the similarity that maps scan coordinates into the template frame.

Two estimators: the paper's (rotation centre, Rz/Ry from the l axis, Rx from the m axis, scale from
m; written frame-invariantly so any scan pose works) and the least-squares similarity over the
common FDPs (Umeyama 1991). "auto" keeps the one with the lower RMS residual over those FDPs. The
adaptation fits it to the firm FDPs, not to the loose ones on the skull, the hairline, the jaw's
angles, the brows and the backs of the ears (clicks.LOOSE_FDPS), when at least MIN_FDPS remain.
"""

from __future__ import annotations

import collections
import dataclasses

import numpy as np

from .. import mpeg4
from ..exceptions import LandmarkError
from ..tol import MM

MIN_FDPS = 4
FAR_FACTOR = 20.0    # a click this many times the clicks' median distance from their middle is a slip


@dataclasses.dataclass(frozen=True)
class Similarity:
    """x -> scale * rotation @ x + translation (rotation proper, scale > 0)."""
    scale: float
    rotation: np.ndarray
    translation: np.ndarray

    def apply(self, points):
        """Transform points (n,3) or (3,)."""
        p = np.asarray(points, dtype=np.float64)
        return self.scale * p @ self.rotation.T + self.translation

    def inverse(self):
        """The inverse similarity."""
        r = self.rotation.T
        return Similarity(1.0 / self.scale, r, -(r @ self.translation) / self.scale)

    def compose(self, other):
        """self after other: x -> self(other(x))."""
        return Similarity(self.scale * other.scale, self.rotation @ other.rotation,
                          self.apply(other.translation))

    def matrix4(self):
        """4x4 homogeneous matrix."""
        m = np.eye(4)
        m[:3, :3] = self.scale * self.rotation
        m[:3, 3] = self.translation
        return m


def umeyama(src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None) -> Similarity:
    """Least-squares similarity taking src (n,3) onto dst (n,3) (Umeyama 1991, no reflections)."""
    src, dst = np.asarray(src, float), np.asarray(dst, float)
    w = np.ones(len(src)) if weights is None else np.asarray(weights, float)
    w = w / w.sum()
    mu_s, mu_d = w @ src, w @ dst
    s0, d0 = src - mu_s, dst - mu_d
    cov = (d0 * w[:, None]).T @ s0
    u, sig, vt = np.linalg.svd(cov)
    fix = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        fix[2, 2] = -1
    rot = u @ fix @ vt
    var = np.sum(w * np.sum(s0 * s0, axis=1))
    scale = float(np.trace(np.diag(sig) @ fix) / var)
    return Similarity(scale, rot, mu_d - scale * rot @ mu_s)


def _paper_frame(p):
    """(centre, frame rows x/y/z, |m|) of the paper's construction from the 8 calibration FDPs."""
    l_axis = (p["3.7"] - p["3.12"]) + (p["10.9"] - p["10.10"]) + (p["8.3"] - p["8.4"])
    m_axis = 0.5 * (p["3.7"] + p["3.12"]) - 0.5 * (p["8.3"] + p["8.4"])
    x = l_axis / np.linalg.norm(l_axis)
    y = m_axis - (m_axis @ x) * x
    y /= np.linalg.norm(y)
    z = np.cross(x, y)
    face_mid = 0.25 * (p["8.3"] + p["8.4"] + p["3.7"] + p["3.12"])
    ear_mid = 0.5 * (p["10.9"] + p["10.10"])
    centre = face_mid + ((ear_mid - face_mid) @ z) * z     # face centre in x/y, ears' depth in z
    return centre, np.stack([x, y, z]), float(np.linalg.norm(m_axis))


def paper_calibration(scan_fdps, template_fdps):
    """The paper's similarity (eq 3: q* = s R (q - q_c) + p_c) from FDPs 2.1, 11.1, 3.7, 3.12, 8.3, 8.4, 10.9, 10.10."""
    missing = [k for k in mpeg4.CALIBRATION_FDPS if k not in scan_fdps]
    if missing:
        raise LandmarkError("the paper's calibration needs FDP " + ", ".join(
            f"{k} ({mpeg4.FDPS[k].label})" for k in missing))
    qc, fq, mq = _paper_frame({k: np.asarray(v, float) for k, v in scan_fdps.items()})
    pc, fp, mp = _paper_frame({k: np.asarray(v, float) for k, v in template_fdps.items()})
    rot = fp.T @ fq
    scale = mp / mq
    return Similarity(scale, rot, pc - scale * rot @ qc)


def _residuals(sim, scan_fdps, template_fdps):
    names = [k for k in scan_fdps if k in template_fdps]
    q = sim.apply(np.array([scan_fdps[k] for k in names]))
    p = np.array([template_fdps[k] for k in names])
    d = np.linalg.norm(q - p, axis=1)
    return float(np.sqrt(np.mean(d ** 2))), dict(zip(names, d.tolist()))


def calibrate(scan_fdps: dict[str, np.ndarray], template_fdps: dict[str, np.ndarray],
              method: str = "auto", lean_on=None) -> tuple[Similarity, dict]:
    """(Similarity scan -> template frame, info {method, rms, residuals}); rms in template units.
    lean_on: the FDPs the least-squares similarity is fitted to and "auto" chooses by (default all;
    used only if at least MIN_FDPS of them are given); the residuals are reported for every FDP."""
    common = {k: v for k, v in scan_fdps.items() if k in template_fdps}
    if len(common) < MIN_FDPS:
        raise LandmarkError(f"calibration needs at least {MIN_FDPS} FDPs on both the scan and the template "
                            f"(the paper's method uses {', '.join(mpeg4.CALIBRATION_FDPS)}); got "
                            f"{len(common)}: {', '.join(common) or 'none'}")
    fitted = common if lean_on is None else {k: v for k, v in common.items() if k in lean_on}
    fitted = fitted if MIN_FDPS <= len(fitted) < len(common) else common      # `is common`: all leaned on
    candidates = {}
    have_paper = all(k in fitted for k in mpeg4.CALIBRATION_FDPS)
    if method in ("paper", "auto") and (have_paper or method == "paper"):
        candidates["paper"] = paper_calibration(common, template_fdps)
    if method in ("umeyama", "auto"):
        names = list(fitted)
        candidates["umeyama"] = umeyama(np.array([fitted[k] for k in names]),
                                        np.array([template_fdps[k] for k in names]))
    if not candidates:
        raise LandmarkError(f"unknown calibration method {method!r} (use 'auto', 'paper' or 'umeyama')")
    scored = {name: _residuals(sim, common, template_fdps) for name, sim in candidates.items()}
    chosen = scored if fitted is common else {name: _residuals(sim, fitted, template_fdps)
                                              for name, sim in candidates.items()}
    best = min(chosen, key=lambda name: chosen[name][0])
    rms, per = scored[best]
    # in the template's metres, and in its mm as the rest of report.json ("paper": None where the
    # paper's 8 FDPs are not all given)
    by_method = {name: (scored[name][0] if name in scored else None) for name in ("paper", "umeyama")
                 if name in scored or method == "auto"}
    info = {"method": best, "rms": rms, "residuals": per, "rms_by_method": by_method,
            "rms_mm": rms * MM, "residuals_mm": {k: d * MM for k, d in per.items()},
            "rms_by_method_mm": {k: (v * MM if v is not None else None) for k, v in by_method.items()},
            "units": "rms, residuals, rms_by_method: template frame, m; *_mm: template frame, mm",
            **({"not_leaned_on": sorted(set(common) - set(fitted))} if fitted is not common else {})}
    return candidates[best], info


MAY_COINCIDE = (("2.4", "8.3"), ("2.5", "8.4"), ("2.2", "2.3"))   # FDPs one click may rightly share
SWAP_GAIN = 0.5      # a relabelling counts only if it at least halves the calibration residual
SUSPECT = 2.0        # a click this many times the clicks' median calibration residual may carry another's label


def _rms(scan_fdps, template_fdps, names):
    sim = umeyama(np.array([scan_fdps[k] for k in names]), np.array([template_fdps[k] for k in names]))
    return _residuals(sim, {k: scan_fdps[k] for k in names}, template_fdps)[0]


def check_handedness(scan_fdps, template_fdps):
    """Labels that look swapped: (relabelled FDPs, {"swapped": [(a, b)], "all": bool, "relabelled": [(a, b)]}).

    People often label from the viewer's side: then every left/right pair is swapped, and the clicks
    are the mirror image of the template's FDPs (so is a mirrored scan with its own labels; the
    caller can tell them apart by the scan's winding). All left/right pairs at once are tried first;
    then, one at a time and the best first, any two labels (a left/right pair goes to "swapped", two
    other FDPs, such as one eye's outer corner and the other's inner, to "relabelled") or a group's
    left/right pairs together (both eyes' corners): a swap is made only if it at least halves the
    least-squares calibration residual. Needs at least 4 FDPs
    besides the pair; returns the input unchanged when nothing helps."""
    common = [k for k in scan_fdps if k in template_fdps]
    pairs = sorted({tuple(sorted((k, mpeg4.FDPS[k].mirror))) for k in common
                    if mpeg4.FDPS[k].mirror in scan_fdps and mpeg4.FDPS[k].mirror in template_fdps})
    none = {"swapped": [], "all": False, "relabelled": []}
    if len(common) < MIN_FDPS + 1:
        return dict(scan_fdps), none

    def swap(points, which):
        out = dict(points)
        for a, b in which:
            out[a], out[b] = points[b], points[a]
        return out

    rms = _rms(scan_fdps, template_fdps, common)
    if pairs:
        everything = swap(scan_fdps, pairs)
        if _rms(everything, template_fdps, common) < SWAP_GAIN * rms:
            return everything, {**none, "swapped": [list(p) for p in pairs], "all": True}
    fixed, found, done = dict(scan_fdps), dict(none), set()
    while True:
        # every left/right pair, and the pairs of clicks far from their places (two other labels
        # exchanged put both so; every pair of 74 clicks took 0.6 s a round)
        sim = umeyama(np.array([fixed[k] for k in common]), np.array([template_fdps[k] for k in common]))
        per = _residuals(sim, {k: fixed[k] for k in common}, template_fdps)[1]
        typical = float(np.median(list(per.values())))
        suspects = sorted(k for k in common if per[k] > SUSPECT * typical and k not in done)
        # ... and a group's left/right pairs at once (both eyes' corners labelled from the viewer's
        # side, the lips right: either eye pair alone does not halve the residual)
        free = [p for p in pairs if not done & set(p)]
        groups = collections.defaultdict(list)
        for p in free:
            groups[p[0].split(".")[0]].append(p)
        candidates = [[p] for p in free] + [g for g in groups.values() if len(g) > 1] + [
            [(a, b)] for i, a in enumerate(suspects) for b in suspects[i + 1:] if (a, b) not in pairs]
        trials = [_rms(swap(fixed, which), template_fdps, common) for which in candidates]
        if not trials or not min(trials) < SWAP_GAIN * rms:
            break
        which = candidates[int(np.argmin(trials))]
        fixed, rms = swap(fixed, which), min(trials)
        for pair in which:
            key = "swapped" if pair in pairs else "relabelled"
            found[key] = found[key] + [list(pair)]
            done |= set(pair)
    return fixed, found


def validate_landmarks(points: dict, need: tuple = (), what: str = "scan") -> dict[str, np.ndarray]:
    """Checked float copies {id: (3,)} of landmarks; LandmarkError names the FDP or the problem.

    Unknown names, wrong shapes, NaN/inf, missing FDPs from `need`, fewer than 4 FDPs,
    two FDPs at one spot, all FDPs on one line or one plane.
    """
    out = {}
    for name, xyz in points.items():
        mpeg4.check_fdp_name(str(name))
        arr = np.asarray(xyz, dtype=np.float64)
        if arr.shape != (3,):
            raise LandmarkError(f"FDP {name} on the {what} must be three numbers, got shape {arr.shape}")
        if not np.isfinite(arr).all():
            raise LandmarkError(f"FDP {name} ({mpeg4.FDPS[name].label}) on the {what} has NaN or infinite coordinates")
        out[str(name)] = arr
    missing = [k for k in need if k not in out]
    if missing:
        raise LandmarkError(f"the {what} lacks FDP " + ", ".join(f"{k} ({mpeg4.FDPS[k].label})" for k in missing))
    if len(out) < MIN_FDPS:
        raise LandmarkError(f"the {what} has {len(out)} FDP(s) ({', '.join(out) or 'none'}); calibration needs "
                            f"at least {MIN_FDPS}, best the paper's 8: {', '.join(mpeg4.CALIBRATION_FDPS)}")
    names = list(out)
    p = np.array([out[k] for k in names])
    # one point far from all the others (a typed coordinate, another scan's click) would make the rest
    # look like one spot: a head's clicks lie within a few times their median distance from their middle
    with np.errstate(over="ignore", invalid="ignore"):          # a coordinate of 1e300: inf, said below
        far = np.linalg.norm(p - np.median(p, axis=0), axis=1)
    typical = float(np.median(far))
    k = int(np.argmax(far))
    if typical > 0 and far[k] > FAR_FACTOR * typical:
        times = f"{far[k] / typical:.3g} times" if np.isfinite(far[k]) else "immeasurably"
        raise LandmarkError(f"FDP {names[k]} ({mpeg4.FDPS[names[k]].label}) on the {what} lies {times} farther "
                            "from the clicks' middle than the others do: a slip in its coordinates, or another "
                            "scan's point")
    spread = float(np.ptp(p, axis=0).max())
    d = np.linalg.norm(p[:, None] - p[None], axis=2)
    d[np.tril_indices(len(p))] = np.inf
    for a, b in MAY_COINCIDE:              # a closed mouth's inner and outer lip corners are one spot
        if a in out and b in out:
            d[min(names.index(a), names.index(b)), max(names.index(a), names.index(b))] = np.inf
    i, j = np.unravel_index(np.argmin(d), d.shape)
    if spread == 0 or d[i, j] < 1e-3 * spread:
        raise LandmarkError(f"FDP {names[i]} and FDP {names[j]} on the {what} are at the same spot: "
                            "one of them was clicked twice")
    sv = np.linalg.svd(p - p.mean(axis=0), compute_uv=False)
    if sv[1] < 1e-3 * sv[0]:
        raise LandmarkError(f"all {len(p)} FDPs on the {what} lie on one line: calibration needs them spread over the face")
    if sv[2] < 1e-3 * sv[0]:
        raise LandmarkError(f"all {len(p)} FDPs on the {what} lie in one plane: calibration needs depth "
                            "(add the ears 10.9/10.10 or the nose tip 9.3)")
    return out


def unit_hint(verts: np.ndarray, points: dict[str, np.ndarray], what: str = "landmarks") -> str:
    """A sentence naming a unit mismatch when the clicks' spread and the scan's size differ by more
    than a factor of 5 (clicks span about 2/3 of a head scan), else ''. Any frame, both in the same;
    verts: the scan's vertices, or its box's corners; what: the points' name in the sentence."""
    p = np.array(list(points.values()), dtype=float).reshape(-1, 3)
    if len(p) < 2 or len(verts) == 0 or not np.isfinite(p).all():
        return ""
    v = np.asarray(verts, dtype=float).reshape(-1, 3)
    ratio = float(np.ptp(v, axis=0).max()) / max(float(np.ptp(p, axis=0).max()), 1e-300) / 1.5
    if 0.2 < ratio < 5.0:
        return ""
    power = round(float(np.log10(np.clip(ratio, 1e-300, 1e300))))
    return (f"the {what} are about 10^{abs(power)} times {'smaller' if power > 0 else 'larger'} than the "
            "scan: they are in another unit (mm, cm, m?) or belong to another scan")
