"""The last calibration the panel made, kept for the Adapt that follows it.

Calibrate (and Suggest the Rest, which judges the clicks the same way) runs the adaptation's step 1,
pipeline.calibrate: the scan taken into the template frame, a dense scan clustered, its normals,
border and spatial tree made. On a 1M-vertex scan that is about 0.7 s, which Adapt would spend again
on the same scan, clicks and options. Its answer is kept here under a digest of those (one answer at
a time; the levels asked for left out: they do not change it), and an Adapt of the same takes it
(adapt(calibrated=...): the same fit to the bit) and gives it back when it is done. An Adapt holds
it while it runs, so no two runs share it; a cancelled or failed Adapt drops it. Any change of the
mesh, a click or another option is another digest: calibrated anew.
"""

import dataclasses
import hashlib

import numpy as np

_KEPT = {}


def digest(verts, tris, clicks, options):
    """A digest of the scan's arrays (as read, scan frame), the clicks and the options (a 1M-vertex
    scan's 72 MB: about 0.04 s)."""
    h = hashlib.sha1(usedforsecurity=False)       # no secret: the fastest of hashlib here (SHA extensions)
    for a in (verts, tris):
        a = np.ascontiguousarray(a)
        h.update(f"{a.dtype.str}{a.shape}".encode())
        h.update(a.data.cast("B"))
    for name in sorted(clicks):
        h.update(name.encode() + b"\0" + np.asarray(clicks[name], dtype=np.float64).tobytes())
    # the levels asked for do not change the calibration (Adapt All Levels and Level 0 Only share it)
    h.update(repr(dataclasses.replace(options, max_levels=0)).encode())
    return h.hexdigest()


def get(key):
    """The answer kept under key, left kept (None: none)."""
    return _KEPT.get(key)


def take(key):
    """The answer kept under key, no longer kept (None: none)."""
    return _KEPT.pop(key, None)


def keep(key, answer):
    """Keep one answer: this one."""
    _KEPT.clear()
    _KEPT[key] = answer


def forget():
    """Keep nothing (the add-on unregistered, a file loaded)."""
    _KEPT.clear()
