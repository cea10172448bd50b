"""MPEG-4 FAP files (.fap): read and write, values in FAPUs, no bpy.

Format: a header `2.1 <name> <frame rate> <frames>`, then per frame a mask line of 68 bits and a
data line `frame value ...` with the values of the masked-in FAPs in order. FAP 1 (viseme) takes
4 values (select1, select2, blend, def) and FAP 2 (expression) 6 (select1, intensity1, select2,
intensity2, init_face, def) in the reference files; files that give one value for each are read
too (select1, and intensity 63 for an expression).
"""

from __future__ import annotations

import dataclasses
import pathlib

import numpy as np

from . import mpeg4
from .exceptions import FileFormatError, HeadAdaptError
from .meshio import write_atomic


@dataclasses.dataclass
class FapAnimation:
    """A FAP stream: name, fps, frame numbers (F,), values (F,69) by FAP number (NaN = not given),
    visemes (F,4) and expressions (F,6) (NaN rows where FAP 1 / 2 are not given)."""
    name: str
    fps: float
    frames: np.ndarray
    values: np.ndarray
    visemes: np.ndarray
    expressions: np.ndarray

    @property
    def duration_s(self):
        """Length of the stream in seconds."""
        return len(self.frames) / self.fps


def _numbers(tokens, path, line_no):
    try:
        return [float(t) for t in tokens]
    except ValueError:
        raise FileFormatError(f"{path}, line {line_no}: not a number in {' '.join(tokens)!r}") from None


def read_fap(path):
    """Read a .fap file into a FapAnimation; FileFormatError names the file and line."""
    path = pathlib.Path(path)
    try:
        text = path.read_text(errors="replace")
    except OSError as exc:
        raise FileFormatError(f"cannot read {path}: {exc.strerror or exc}") from exc
    lines = [(i + 1, ln.split()) for i, ln in enumerate(text.splitlines()) if ln.strip() and not ln.lstrip().startswith("#")]
    if not lines or len(lines[0][1]) < 4:
        raise FileFormatError(f"{path}, line 1: expected the header '2.1 <name> <frame rate> <frames>'")
    _, head = lines[0]
    fps, n_frames = _numbers(head[-2:], path, lines[0][0])
    if fps <= 0:
        raise FileFormatError(f"{path}, line {lines[0][0]}: frame rate {fps:g} must be positive")
    body = lines[1:]
    if len(body) < 2 * int(n_frames):
        raise FileFormatError(f"{path}: the header says {int(n_frames)} frames, the file holds {len(body) // 2}")
    frames, values, visemes, expressions = [], [], [], []
    for f in range(int(n_frames)):
        (mask_no, mask), (data_no, data) = body[2 * f], body[2 * f + 1]
        if len(mask) != 68 or any(b not in ("0", "1") for b in mask):
            raise FileFormatError(f"{path}, line {mask_no}: a mask must be 68 bits of 0 or 1, got {len(mask)} tokens")
        bits = np.array(mask) == "1"
        nums = _numbers(data, path, data_no)
        k = int(bits.sum())
        compound = k + 3 * bits[0] + 5 * bits[1]
        if len(nums) - 1 not in (k, compound):
            raise FileFormatError(f"{path}, line {data_no}: {len(nums) - 1} values for {k} FAPs in the mask")
        row, vis, exp = np.full(mpeg4.N_FAPS + 1, np.nan), np.full(4, np.nan), np.full(6, np.nan)
        vals = iter(nums[1:])
        wide = len(nums) - 1 == compound and compound != k
        for number in np.flatnonzero(bits) + 1:
            if number == 1:
                vis[:] = [next(vals) for _ in range(4)] if wide else [next(vals), np.nan, 63.0, np.nan]
                row[1] = vis[0]
            elif number == 2:
                exp[:] = [next(vals) for _ in range(6)] if wide else [next(vals), 63.0, np.nan, np.nan, np.nan, np.nan]
                row[2] = exp[0]
            else:
                row[number] = next(vals)
        frames.append(int(nums[0]))
        values.append(row), visemes.append(vis), expressions.append(exp)
    return FapAnimation(" ".join(head[1:-2]), fps, np.array(frames), np.array(values).reshape(-1, mpeg4.N_FAPS + 1),
                        np.array(visemes).reshape(-1, 4), np.array(expressions).reshape(-1, 6))


def _fmt(v):
    return str(int(v)) if float(v).is_integer() else f"{v:.6g}"


def write_fap(path, anim):
    """Write a FapAnimation as a .fap file (compound FAP 1/2 layout), atomically."""
    out = [f"2.1 {anim.name or 'headadapt'} {_fmt(anim.fps)} {len(anim.frames)}"]
    for i, frame in enumerate(anim.frames):
        given = ~np.isnan(anim.values[i, 1:])
        given[0] |= ~np.isnan(anim.visemes[i, 0])
        given[1] |= ~np.isnan(anim.expressions[i, 0])
        vals = []
        for number in np.flatnonzero(given) + 1:
            src = anim.visemes[i] if number == 1 else anim.expressions[i] if number == 2 else [anim.values[i, number]]
            vals += [_fmt(0 if np.isnan(v) else v) for v in src]
        out.append(" ".join("1" if g else "0" for g in given))
        out.append(" ".join([str(int(frame))] + vals))
    write_atomic(path, "\n".join(out) + "\n")


def fap_column(anim, fap):
    """Values (F,) of one FAP (by number or name) in FAPUs, NaN where not given."""
    if isinstance(fap, str):
        if fap not in mpeg4.FAP_BY_NAME:
            raise HeadAdaptError(f"unknown FAP name {fap!r}")
        fap = mpeg4.FAP_BY_NAME[fap].number
    if not 1 <= int(fap) <= mpeg4.N_FAPS:
        raise HeadAdaptError(f"FAP number {fap} is not 1..{mpeg4.N_FAPS}")
    return anim.values[:, int(fap)]
