"""The jaw: the mandible turns about the template's jaw pivot and slides (SkinModel's jaw controls)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

JAW_OPEN_DEG = 22.0                   # jaw_open = 1: a wide-open mouth (ARKit jawOpen turns about 27 deg)
JAW_SLIDE = 0.004                     # jaw_thrust / jaw_shift = 1, m
JAW_STIFFNESS = 50.0                  # hypodermis on the mandible (outside the lips)


class JawMixin:
    """SkinModel's jaw: its fields jaw_pivot (3,) and jaw_axis (3,) give the mandible's turn."""

    def mandible_transform(self, activations):
        """(R, t) of the mandible for the jaw controls: x -> R (x - pivot) + pivot + t, metres."""
        a = activations or {}
        rot = Rotation.from_rotvec(np.radians(JAW_OPEN_DEG * a.get("jaw_open", 0.0)) * self.jaw_axis).as_matrix()
        t = JAW_SLIDE * (a.get("jaw_thrust", 0.0) * np.array([0.0, -1.0, 0.0])
                         + a.get("jaw_shift", 0.0) * np.array([-1.0, 0.0, 0.0]))
        return rot, t

    def on_jaw(self, points, rot, t):
        """Points (k,3) of the mandible's rest frame carried where the jaw (rot, t) puts them, metres."""
        return (points - self.jaw_pivot) @ rot.T + self.jaw_pivot + t

    def _jaw_local(self, points, rot, t):
        """Points (k,3) taken back into the mandible's rest frame (the inverse of on_jaw), metres."""
        return (points - self.jaw_pivot - t) @ rot + self.jaw_pivot
