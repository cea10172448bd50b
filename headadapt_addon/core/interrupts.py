"""Ctrl-C held over a call that must not be cut short, then raised: Blender's start-up scripts crashed
the process at exit (segfault) when a KeyboardInterrupt came inside them, and Blender's handlers
(version_update on loading a file) print one and go on, so a run ended 'done' after the user's Ctrl-C."""

from __future__ import annotations

import contextlib
import signal
import threading


@contextlib.contextmanager
def held_ctrl_c():
    """Within: a SIGINT is only noted; after: raised as KeyboardInterrupt. Main thread only (Python
    takes signals there), where Python holds SIGINT's handler; elsewhere the block runs as it is."""
    # (in a Blender binary Python did not install SIGINT's handler, Blender did: getsignal gives None,
    # and Python could not put Blender's back)
    if threading.current_thread() is not threading.main_thread() or signal.getsignal(signal.SIGINT) is None:
        yield
        return
    came = []
    previous = signal.signal(signal.SIGINT, lambda *_: came.append(True))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
    if came:
        raise KeyboardInterrupt
