"""Size limits for every file HeadAdapt reads, checked before anything is allocated for it.

A reader first asks :func:`read_capped` for the file's bytes (its size is checked against the limit
before a byte is read), then checks every count a header declares against the bytes that are there
(:func:`check_count`), and only then lets a parser size arrays. Messages name the file.
"""

from __future__ import annotations

import io
import os
import pathlib

from .exceptions import FileFormatError

MB = 1 << 20
# A scan: 512 MB holds a binary PLY of about 10 million vertices and 20 million triangles.
SCAN_MAX_BYTES = 512 * MB
SCAN_MAX_VERTICES = 20_000_000
SCAN_MAX_FACES = 40_000_000
# Landmarks: the standard's 84 FDPs and as many markers fit in a few kB.
LANDMARKS_MAX_BYTES = 1 * MB
LANDMARKS_MAX_POINTS = 1000
# A .fap animation: up to about 370 bytes a frame (every FAP), so an hour at 30 fps is 40 MB; the
# reader takes about 4 times a file's size in memory and 7 s per 100 MB on a 2-core machine.
FAP_MAX_BYTES = 64 * MB


class CappedFile(io.FileIO):
    """A file opened for reading whose read(n) asks for no more than the bytes left in it: a parser
    (plyfile) that sizes a read from a length stored in the file must not turn it into an allocation
    of that length. `size` is the file's size when opened."""

    def __init__(self, path: pathlib.Path):
        super().__init__(path, "rb")
        self.size = os.fstat(self.fileno()).st_size

    def read(self, size: int = -1) -> bytes:
        if size is not None and size > 0:
            size = min(size, max(self.size - self.tell(), 0))
        return super().read(size)


def open_capped(path: os.PathLike | str, max_bytes: int, what: str) -> CappedFile:
    """path opened as a CappedFile, a `what` ("scan", "landmark file", ...): FileFormatError naming the
    file if it does not exist, cannot be read, is empty or is over max_bytes (checked before reading)."""
    path = pathlib.Path(path)
    try:
        fh = CappedFile(path)
    except FileNotFoundError:
        raise FileFormatError(f"{path}: no such file") from None
    except IsADirectoryError:
        raise FileFormatError(f"{path}: a folder, not a {what}") from None
    except OSError as exc:
        raise FileFormatError(f"{path}: cannot read the {what} ({exc.strerror or exc})") from None
    if fh.size > max_bytes:
        fh.close()
        raise FileFormatError(f"{path}: {fh.size / MB:.1f} MB is over the {max_bytes / MB:.0f} MB "
                              f"limit for a {what}")
    if fh.size == 0:
        fh.close()
        raise FileFormatError(f"{path}: the {what} is empty (0 bytes)")
    return fh


def read_capped(path: os.PathLike | str, max_bytes: int, what: str) -> bytes:
    """The bytes of path, a `what`: open_capped's checks, then read in blocks (read(n) would reserve n
    bytes before reading), no further than the size it had when opened (a file growing meanwhile)."""
    with open_capped(path, max_bytes, what) as fh:
        data = bytearray()
        try:
            while block := fh.read(MB):
                data += block
        except OSError as exc:
            raise FileFormatError(f"{path}: cannot read the {what} ({exc.strerror or exc})") from None
    if not data:
        raise FileFormatError(f"{path}: the {what} is empty (0 bytes)")
    return bytes(data)


def check_count(path: os.PathLike | str, what: str, count: int, limit: int,
                room: int | None = None, min_bytes: int = 0) -> int:
    """count (of `what`, as a header declares it) if it is >= 0, <= limit and, when room is given,
    fits: count * min_bytes <= room (the bytes left in the file); else FileFormatError naming path."""
    if count < 0:
        raise FileFormatError(f"{path}: the header declares {count} {what}")
    if count > limit:
        raise FileFormatError(f"{path}: the header declares {count:,} {what}, over the limit of {limit:,}")
    if room is not None and count * min_bytes > room:
        raise FileFormatError(f"{path}: the header declares {count:,} {what} (at least {count * min_bytes:,} "
                              f"bytes), the file holds only {room:,} bytes after it")
    return count
