"""The transferred anatomy (template frame, metres) and its plain-number form."""

from __future__ import annotations

import dataclasses

import numpy as np

from ..adapt.calibration import Similarity


@dataclasses.dataclass
class Anatomy:
    """The transferred anatomy: part vertices, muscle ends, sphincters, FDPs, FAPUs, jaw pivot (m)."""
    parts: dict
    muscles: list
    sphincters: list
    fdps: dict
    fapus: dict
    jaw_pivot: np.ndarray
    rigid: dict

    def to_plain(self) -> dict:
        """The anatomy as numbers only (float64 kept; names and regions come from the template):
        what a Blender ID property or JSON holds."""
        def flat(a):
            return np.asarray(a, dtype=np.float64).ravel().tolist()
        return {"parts": {k: flat(v) for k, v in self.parts.items()},
                "muscles": {m["name"]: flat([m["attachment"], m["insertion"]]) for m in self.muscles},
                "sphincters": {s["name"]: flat([s["centre"], *s["axes"]]) for s in self.sphincters},
                "fdps": {k: flat(v) for k, v in self.fdps.items()},
                "fapus": {k: float(v) for k, v in self.fapus.items()},
                "jaw_pivot": flat(self.jaw_pivot),
                "rigid": {k: flat([[s.scale, 0.0, 0.0], *s.rotation, s.translation]) for k, s in self.rigid.items()}}

    @classmethod
    def from_plain(cls, plain, tpl) -> Anatomy:
        """The Anatomy of to_plain's numbers (muscle and sphincter regions from the template)."""
        def pts(a):
            return np.asarray(a, dtype=np.float64).reshape(-1, 3)
        regions = {m["name"]: m["regions"] for m in (*tpl.meta["muscles"], *tpl.meta["sphincters"])}
        muscles = [{"name": k, "regions": regions[k], "attachment": pts(v)[0], "insertion": pts(v)[1]}
                   for k, v in plain["muscles"].items()]
        sphincters = [{"name": k, "regions": regions[k], "centre": pts(v)[0], "axes": [pts(v)[1], pts(v)[2]]}
                      for k, v in plain["sphincters"].items()]
        rigid = {k: Similarity(float(pts(v)[0, 0]), pts(v)[1:4], pts(v)[4]) for k, v in plain["rigid"].items()}
        return cls(parts={k: pts(v) for k, v in plain["parts"].items()}, muscles=muscles, sphincters=sphincters,
                   fdps={k: pts(v)[0] for k, v in plain["fdps"].items()}, fapus=dict(plain["fapus"]),
                   jaw_pivot=pts(plain["jaw_pivot"])[0], rigid=rigid)
