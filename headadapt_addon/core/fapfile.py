"""MPEG-4 FAP files (.fap): read and write, values in FAPUs, no bpy.

Format: a header `2.1 <name> <frame rate> <frames>`, then per frame a mask line of 68 bits and a
data line `frame value ...` with the values of the masked-in FAPs in FAP order. In the reference
files FAP 1 (viseme) takes 4 values (select1, select2, blend, def) and FAP 2 (expression) 6
(select1, intensity1, select2, intensity2, init_face, def); files that give one value for each
are read too (decided per line by counting). Errors name the file and the line; writes are atomic.
The file's size is checked before it is read, the header's frame count against the lines the file
holds before any array is sized from it.
"""

from __future__ import annotations

import dataclasses
import math
import pathlib

import numpy as np

from . import limits, mpeg4
from .exceptions import FileFormatError, HeadAdaptError
from .meshio import write_atomic

N = mpeg4.N_FAPS                                              # 68
# The rest of the compound vector when a file gives FAP 1 / FAP 2 as one value (the select1):
# viseme 2 = none with blend 63 (all viseme 1); expression at intensity 63, second one neutral.
_FULL = float(mpeg4.INTENSITY_MAX)
_ONE_VALUE_REST = {1: (0.0, _FULL, 0.0), 2: (_FULL, 0.0, 0.0, 0.0, 0.0)}


@dataclasses.dataclass
class FapAnimation:
    """A FAP stream: name, fps, frame numbers (F,), values (F,69) in FAPUs by FAP number (NaN = not
    given, column 0 unused), visemes (F,4) and expressions (F,6) (NaN rows where FAP 1 / 2 are not given)."""
    name: str
    fps: float
    frames: np.ndarray
    values: np.ndarray
    visemes: np.ndarray
    expressions: np.ndarray

    @property
    def duration_s(self):
        """Length in seconds, from the first to the end of the last frame number."""
        return float(self.frames[-1] - self.frames[0] + 1) / self.fps if len(self.frames) else 0.0


def _error(path, line_no, what):
    return FileFormatError(f"{path}, line {line_no}: {what}")


def _shown(text):
    """repr of a token from the file, cut to 40 characters (a line may hold megabytes)."""
    return repr(text) if len(text) <= 40 else repr(text[:37] + "...")


def _number(tok, path, line_no):
    try:
        value = float(tok)
    except ValueError:
        value = math.nan
    if not math.isfinite(value):
        raise _error(path, line_no, f"{_shown(tok)} is not a number")
    return value


def _numbers(tokens, path, line_no):
    """The tokens of a data line as float64, all finite; else the first bad one named."""
    try:
        nums = np.array(tokens, dtype=np.float64)
    except ValueError:
        nums = None
    if nums is None or not np.isfinite(nums).all():
        for tok in tokens:
            _number(tok, path, line_no)
    return nums


def read_fap(path):
    """Read a .fap file into a FapAnimation (values in FAPUs); FileFormatError names the file and line.
    Frame numbers must increase. A line is split only when its frame is read, a data line's numbers are
    converted at once and a mask line's bits once per distinct mask (an hour at 30 fps: 108,000
    frames), so the file's text is most of the memory it takes."""
    path = pathlib.Path(path)
    text = limits.read_capped(path, limits.FAP_MAX_BYTES, "FAP file").decode("utf-8-sig", errors="replace")
    lines = [(no, ln) for no, ln in enumerate(text.splitlines(), 1) if ln.strip() and not ln.lstrip().startswith("#")]
    del text
    head_no, head = (lines[0][0], lines[0][1].split()) if lines else (1, [])
    if len(head) < 4:
        raise _error(path, head_no, f"bad header {_shown(' '.join(head))}, expected '2.1 <name> <frame rate> <frames>'")
    _number(head[0], path, head_no)
    fps, n_frames = _number(head[-2], path, head_no), _number(head[-1], path, head_no)
    if fps <= 0:
        raise _error(path, head_no, f"frame rate {fps:g} must be positive")
    if n_frames < 0 or not n_frames.is_integer():
        raise _error(path, head_no, f"number of frames {_shown(head[-1])} is not a whole number >= 0")
    n, body = int(n_frames), lines[1:]
    if len(body) < 2 * n:
        raise FileFormatError(f"{path}: the header (line {head_no}) says {n} frames, the file holds only {len(body) // 2}")
    frames, values = np.zeros(n, np.int64), np.full((n, N + 1), np.nan)
    visemes, expressions = np.full((n, 4), np.nan), np.full((n, 6), np.nan)
    masks = {}                                  # mask line -> (FAP columns of the rest, FAP 1, FAP 2, k, full)
    for f in range(n):
        (mask_no, mask_line), (data_no, data_line) = body[2 * f], body[2 * f + 1]
        mask = masks.get(mask_line)
        if mask is None:
            tokens = mask_line.split()
            if len(tokens) != N:
                raise _error(path, mask_no, f"the mask of frame {f + 1} has {len(tokens)} entries, expected {N} bits")
            bad = [t for t in tokens if t not in ("0", "1")]
            if bad:
                raise _error(path, mask_no, f"mask entry {_shown(bad[0])} is not 0 or 1")
            bits = np.array(tokens) == "1"
            k = int(bits.sum())
            mask = masks[mask_line] = (np.flatnonzero(bits[2:]) + 3, bool(bits[0]), bool(bits[1]), k,
                                       k + 3 * int(bits[0]) + 5 * int(bits[1]))
        rest, has = mask[0], {1: mask[1], 2: mask[2]}
        k, full = mask[3], mask[4]
        data = data_line.split()
        nums = _numbers(data, path, data_no)
        if not nums[0].is_integer() or abs(nums[0]) >= 2 ** 63:
            raise _error(path, data_no, f"frame number {_shown(data[0])} is not a whole number of 64 bits")
        got = len(nums) - 1
        if got not in (k, full):
            raise _error(path, data_no, f"{got} values for {k} FAPs in the mask, expected {k}"
                         + (f" or {full} (FAP 1/2 with 4/6 values)" if full != k else ""))
        frames[f] = int(nums[0])
        if f and frames[f] <= frames[f - 1]:
            raise _error(path, data_no, f"frame number {frames[f]} does not follow frame {frames[f - 1]}: "
                                        "the frame numbers must increase")
        wide, vals, pos = got == full and full != k, nums[1:], 0
        for fap, out in ((1, visemes), (2, expressions)):
            if has[fap]:
                width = out.shape[1] if wide else 1
                out[f] = vals[pos:pos + width] if wide else (vals[pos], *_ONE_VALUE_REST[fap])
                values[f, fap], pos = vals[pos], pos + width
        values[f, rest] = vals[pos:]
    if len(body) > 2 * n:
        raise _error(path, body[2 * n][0], f"more lines than the header's {n} frames")
    return FapAnimation(" ".join(head[1:-2]), fps, frames, values, visemes, expressions)


def _fmt(v):
    """A value as text: an integer when integral, else up to 6 decimals."""
    v = float(v)
    if v.is_integer():
        return str(int(v))
    text = f"{v:.6f}".rstrip("0").rstrip(".")
    return "0" if text in ("-0", "") else text


def write_fap(path, anim):
    """Write a FapAnimation as a .fap file (values in FAPUs, FAP 1/2 in the 4/6-value layout), atomically."""
    n = len(anim.frames)
    values, vis, exp = (np.asarray(a, np.float64) for a in (anim.values, anim.visemes, anim.expressions))
    if values.shape != (n, N + 1) or vis.shape != (n, 4) or exp.shape != (n, 6) or not anim.fps > 0:
        raise HeadAdaptError(f"FAP animation {anim.name!r}: expected {n} frames of values (69), visemes (4), "
                             f"expressions (6) and fps > 0, got {values.shape}, {vis.shape}, {exp.shape}, fps {anim.fps}")
    if np.isinf(values).any() or np.isinf(vis).any() or np.isinf(exp).any():
        raise HeadAdaptError(f"FAP animation {anim.name!r} holds infinite values")
    out = [f"2.1 {' '.join(str(anim.name).split()) or 'headadapt'} {_fmt(anim.fps)} {n}"]
    for i, frame in enumerate(anim.frames):
        given = ~np.isnan(values[i, 1:])
        groups = []
        for fap, row in ((1, vis[i]), (2, exp[i])):
            select = row[0] if not np.isnan(row[0]) else values[i, fap]
            given[fap - 1] = not np.isnan(select)
            defaults = np.array((select, *_ONE_VALUE_REST[fap]))
            groups.append(np.where(np.isnan(row), defaults, row) if given[fap - 1] else [])
        rest = values[i, np.flatnonzero(given[2:]) + 3]
        out.append(" ".join("1" if g else "0" for g in given))
        out.append(" ".join([str(int(frame))] + [_fmt(v) for v in (*groups[0], *groups[1], *rest)]))
    write_atomic(path, "\n".join(out) + "\n")


def fap_column(anim, fap):
    """Values (F,) in FAPUs of one FAP, by number (1..68) or name, NaN where not given."""
    if isinstance(fap, str):
        if fap not in mpeg4.FAP_BY_NAME:
            raise HeadAdaptError(f"unknown FAP name {fap!r}")
        fap = mpeg4.FAP_BY_NAME[fap].number
    elif fap not in mpeg4.FAPS:
        raise HeadAdaptError(f"FAP number {fap} is not one of 1..{N}")
    return anim.values[:, int(fap)].copy()
