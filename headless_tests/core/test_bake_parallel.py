"""The bake on two cores (core/skin/parallel.py): a helper process bakes keys from the same queue; the
keys are one core's to the bit, and a helper that fails or a cancel loses nothing and leaves no process."""
import subprocess
import time

import numpy as np
import pytest

from headadapt_addon.core.skin import bake, drive, parallel
from headadapt_addon.core.skin.build import build
from headadapt_addon.core.template import load_template


@pytest.fixture(scope="module")
def tpl():
    return load_template()


@pytest.fixture(scope="module")
def model_and_recipes(tpl):
    recipes = [r for _, kind, r in drive.shape_key_recipes() if kind in ("expression", "viseme")]
    assert len(recipes) >= parallel.MIN_KEYS
    model = build(tpl)
    return model, recipes, [model.equilibrium(r) for r in recipes]


def test_keys_baked_on_two_cores_are_one_core_s_to_the_bit(tpl):
    # the 76 MPEG-4 keys (about 2 s here): with fewer the helper, starting, may find the queue empty
    kinds = ("expression", "viseme", "fap")
    two, timing = bake.bake(tpl, kinds=kinds)
    one, alone = bake.bake(tpl, kinds=kinds, helper=False)
    assert timing["helper_keys"] > 0 and alone["helper_keys"] == 0     # the helper did bake some
    assert [k.name for k in two] == [k.name for k in one] and len(one) >= parallel.MIN_KEYS
    for a, b in zip(two, one):
        assert a.moved.keys() == b.moved.keys() and a.fap_units == b.fap_units
        for part in a.moved:
            np.testing.assert_array_equal(a.moved[part], b.moved[part])


@pytest.mark.parametrize("child", ["import sys; sys.exit(3)",                        # dies at once
                                   "import sys; sys.stdin.buffer.read(100); print('junk')",    # answers junk
                                   "import sys, time; sys.stdin.buffer.read(100); time.sleep(600)"])   # hangs
def test_a_helper_that_fails_leaves_its_keys_to_this_process(tpl, model_and_recipes, monkeypatch, child):
    model, recipes, alone = model_and_recipes
    monkeypatch.setattr(parallel, "_CHILD", child)
    proc = parallel.start(tpl.directory, recipes)
    t0 = time.monotonic()
    skins, helped = parallel.equilibria(model, recipes, proc)
    assert helped == 0 and proc.poll() is not None
    assert time.monotonic() - t0 < 60          # a hung helper is not waited for (it sleeps 600 s)
    for a, b in zip(skins, alone):
        np.testing.assert_array_equal(a, b)


def test_a_helper_slow_to_read_holds_nothing_back(tpl, model_and_recipes, monkeypatch):
    # the helper reads its recipes and anatomy (megabytes) only once it has imported numpy and scipy:
    # start() returns at once all the same (this process builds its model meanwhile), and a helper
    # that never reads them costs no wait
    model, recipes, alone = model_and_recipes
    monkeypatch.setattr(parallel, "_CHILD", "import time; time.sleep(600)")
    t0 = time.monotonic()
    proc = parallel.start(tpl.directory, recipes, np.zeros(4_000_000))        # 32 MB: far over a pipe's 64 kB
    assert time.monotonic() - t0 < 30
    skins, helped = parallel.equilibria(model, recipes, proc)
    assert helped == 0 and proc.poll() is not None and time.monotonic() - t0 < 60
    for a, b in zip(skins, alone):
        np.testing.assert_array_equal(a, b)


def test_a_cancel_stops_the_helper(tpl, model_and_recipes, monkeypatch):
    model, recipes, _ = model_and_recipes
    started = []
    popen = subprocess.Popen

    def record(*args, **kwargs):
        started.append(popen(*args, **kwargs))
        return started[-1]

    monkeypatch.setattr(parallel.subprocess, "Popen", record)

    def cancel(fraction, index):
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        parallel.equilibria(model, recipes, parallel.start(tpl.directory, recipes), progress=cancel)
    assert len(started) == 1 and started[0].poll() is not None      # ended and reaped


def test_no_helper_for_a_template_not_loaded_from_a_folder_few_keys_or_the_folder_mode(tpl, model_and_recipes,
                                                                                      monkeypatch):
    model, recipes, alone = model_and_recipes
    monkeypatch.setattr(parallel.subprocess, "Popen", None)          # starting one would fail the test
    for directory, some in ((None, recipes), (tpl.directory, recipes[:parallel.MIN_KEYS - 1])):
        assert parallel.start(directory, some) is None
        skins, helped = parallel.equilibria(model, some, None)
        assert helped == 0 and all(np.array_equal(a, b) for a, b in zip(skins, alone))
    # the batch's folder mode runs a scan per core, and tells its scans' processes so
    from headadapt_addon.batch import SCAN_PROCESS_THREADS
    for name, value in SCAN_PROCESS_THREADS.items():
        monkeypatch.setenv(name, value)
    assert parallel.start(tpl.directory, recipes) is None
