"""Errors the user can act on. Each message names what is wrong: which landmark, file or part."""


class HeadAdaptError(ValueError):
    """Bad input or an impossible request, with a message meant for the artist or the batch log."""


class LandmarkError(HeadAdaptError):
    """A landmark (FDP) is missing, unknown, duplicated, degenerate or far off the surface."""


class MeshError(HeadAdaptError):
    """A mesh is empty, not made of triangles/polygons, or holds NaN or infinite coordinates."""


class FileFormatError(HeadAdaptError):
    """A file could not be read or written; the message names the file and the reason."""
