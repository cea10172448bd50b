"""Anatomy transfer (paper sec 6.2): skull, mandible, muscles, sphincters, eyes, teeth, tongue, FAPUs.

Everything in the template frame (metres); AdaptResult.to_scan takes points to the scan's frame.
pipeline: transfer(tpl, result) step by step; model: the Anatomy it gives; rigid: eyes, teeth and
tongue carried rigidly by their FDPs, the eyes seated in their orbits; bone: the skull kept under
the adapted skin and the visible skin kept out of the skull.
"""

from .bone import keep_inside
from .model import Anatomy
from .pipeline import transfer
from .rigid import RIGID_FDPS, eye_protrusion, rigid_from_fdps, surface_point

__all__ = ["RIGID_FDPS", "Anatomy", "eye_protrusion", "keep_inside", "rigid_from_fdps", "surface_point", "transfer"]
