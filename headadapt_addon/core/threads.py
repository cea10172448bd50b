"""The core's worker threads: numpy and scipy release the GIL on large arrays and sparse products, so
independent pieces of one step (a level's three coordinate solves, two halves of a ray walk) run
side by side on a 2-core machine. Tasks given to the pool must not wait on the pool themselves."""

from __future__ import annotations

_POOL = []


def pool():
    """The shared ThreadPoolExecutor (3 workers), made on first use."""
    if not _POOL:
        from concurrent.futures import ThreadPoolExecutor
        _POOL.append(ThreadPoolExecutor(max_workers=3, thread_name_prefix="headadapt"))
    return _POOL[0]


def shutdown():
    """Let the pool's idle threads end (the add-on disabled); the next pool() makes a new one.
    Work still queued runs to its end first, on its own threads: nothing waits here."""
    while _POOL:
        _POOL.pop().shutdown(wait=False)
