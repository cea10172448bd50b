"""Shared numeric tolerances and units of the core (one home, as trimesh's ``tol``)."""

MM = 1000.0         # millimetres per metre: the template frame is in metres, reports in mm
TINY = 1e-12        # guards a division or a normalisation against a zero length, area or weight sum
EXACT = 1e-12       # relative tolerance of the exact spatial queries (bounds widened by this much)
