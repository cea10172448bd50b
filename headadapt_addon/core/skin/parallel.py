"""Many keys' equilibria on two cores. A key's skin depends on its recipe alone (the same skin to the
bit in any order, in a model built anew), and the bake was a one-core loop: a helper process (this
Python, sys.executable) builds the same SkinModel from the template's folder and the anatomy and
takes keys from the same queue as this process. Where no helper can start (one core, an executable
that is not a Python, a template not loaded from a folder, too few keys) or it fails on the way,
this process bakes what is left: the keys are the same either way."""

from __future__ import annotations

import os
import pathlib
import pickle
import subprocess
import sys
import threading
import time

MIN_KEYS = 12           # fewer keys are baked here alone: the helper's start (Python, numpy, scipy and
                        # the model's build: about 0.5 s) would cost more than it saves
LAST_KEY_WAIT = 2.0     # once this process is done, the helper's last key is waited for this many times
                        # as long as a key took here (at least 1 s), then made here (a hung helper costs no more)

# the helper: the add-on's folder's parent on the path, the add-on imported by its folder's name
# (Blender names an extension's package bl_ext.<repository>.<id>, which a plain Python cannot import)
_CHILD = ("import importlib, sys; sys.path.insert(0, sys.argv[1]); "
          "importlib.import_module(sys.argv[2] + '.core.skin.parallel').serve(sys.stdin.buffer, sys.stdout.buffer)")


def serve(inp, out):
    """The helper's side: (Python's, numpy's and scipy's versions, template folder, anatomy or None,
    recipes) read from `inp` (other versions than its own: it ends), then key indices until None; for
    each, (index, skin (n,3)) written to `out`."""
    from ..template import load_template
    from .build import build

    versions, directory, anatomy, recipes = pickle.load(inp)
    if versions != _versions():             # another Python, numpy or scipy than this process's: other skins
        return
    model = build(load_template(directory), anatomy)
    while (i := pickle.load(inp)) is not None:
        pickle.dump((i, model.equilibrium(recipes[i])), out, protocol=pickle.HIGHEST_PROTOCOL)
        out.flush()


def start(directory, recipes, anatomy=None):
    """The helper process for these recipes, begun (it builds its model while this process builds its
    own), or None where none can start: `directory` the template's folder (Template.directory; None:
    none starts), `anatomy` the model's (None: the template's own); fewer than MIN_KEYS recipes, one
    core, an executable that is not a Python, or HEADADAPT_BAKE_HELPER=0 in the environment (the
    batch's folder mode, whose scans side by side fill the cores): none."""
    exe = pathlib.Path(sys.executable or "").name.lower()
    if (directory is None or len(recipes) < MIN_KEYS or (os.cpu_count() or 1) < 2 or not exe.startswith("python")
            or os.environ.get("HEADADAPT_BAKE_HELPER") == "0"):
        return None
    addon = pathlib.Path(__file__).resolve().parents[2]
    # one BLAS thread in the helper (the user's setting wins): two processes on two cores, OpenBLAS's
    # own threads beside them only spin for work
    env = {"OPENBLAS_NUM_THREADS": "1", **os.environ, "PYTHONPATH": os.pathsep.join(p for p in sys.path if p)}
    try:
        proc = subprocess.Popen([sys.executable, "-c", _CHILD, str(addon.parent), addon.name], stdin=subprocess.PIPE,
                                stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, env=env)
    except OSError:
        return None
    try:
        payload = pickle.dumps((_versions(), str(directory), anatomy, recipes), protocol=pickle.HIGHEST_PROTOCOL)
    except pickle.PicklingError:
        stop(proc)
        return None
    # written on a thread: the helper reads it only once it has imported numpy and scipy (about 0.4 s),
    # and the pipe holds 64 kB of the anatomy's megabytes, so a write here would hold this process's
    # model build back until then
    proc.sender = threading.Thread(target=_send, args=(proc, payload), daemon=True)
    proc.sender.start()
    return proc


def _send(proc, payload):
    try:
        proc.stdin.write(payload)
        proc.stdin.flush()
    except (OSError, ValueError):           # the helper died, or was stopped: the feeder finds out
        pass


def equilibria(model, recipes, proc=None, progress=None):
    """([model.equilibrium(r) for r in recipes], how many of them the helper `proc` made (start's, for
    the same recipes; None: this process makes them all)). progress(fraction done, recipe index) after
    each key this process makes; an exception it raises (a cancel) stops the helper too."""
    out = [None] * len(recipes)
    queue, lock = list(range(len(recipes)))[::-1], threading.Lock()

    def take():
        with lock:
            return queue.pop() if queue else None

    helped, made, t0 = [0], 0, time.perf_counter()
    feeder = threading.Thread(target=_feed, args=(proc, take, out, helped), daemon=True) if proc else None
    try:
        if feeder:
            feeder.start()
        while (i := take()) is not None:
            out[i] = model.equilibrium(recipes[i])
            made += 1
            if progress:
                progress(sum(x is not None for x in out) / len(out), i)
        if feeder:
            feeder.join(max(1.0, LAST_KEY_WAIT * (time.perf_counter() - t0) / max(made, 1)))
    finally:
        if proc:
            stop(proc)
    if feeder:
        feeder.join()
    for i, skin in enumerate(out):              # what the helper took but did not give back
        if skin is None:
            out[i] = model.equilibrium(recipes[i])
    return out, helped[0]


def _versions():
    """This Python's and numpy's and scipy's versions: the helper bakes only where they are this
    process's, so that its skins are this process's (a Blender may name another Python as
    sys.executable: Debian's 3.4 found a pyenv 3.11.7 on the PATH for its own 3.11.2)."""
    import platform

    import numpy
    import scipy
    return tuple(sys.version_info[:3]), platform.python_implementation(), numpy.__version__, scipy.__version__


def _feed(proc, take, out, helped):
    """The helper's loop (on a thread): a key from the queue to the helper, its skin back (counted in
    helped[0]), until the queue is empty or the helper fails (its key is then left to this process)."""
    proc.sender.join()                          # the helper has its recipes before it is sent a key
    try:
        while (i := take()) is not None:
            pickle.dump(i, proc.stdin)
            proc.stdin.flush()
            j, skin = pickle.load(proc.stdout)
            out[j] = skin
            helped[0] += 1
        pickle.dump(None, proc.stdin)
        proc.stdin.flush()
    except (OSError, EOFError, pickle.UnpicklingError, ValueError):
        return


def stop(proc):
    """End the helper (done, failed or cancelled) and reap it."""
    if proc.poll() is None:
        try:
            proc.wait(0.5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    for pipe in (proc.stdin, proc.stdout):
        try:
            pipe.close()
        except OSError:
            pass
