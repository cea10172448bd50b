"""./ha, the set-up script: what it says when it cannot set up an environment."""
import os
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_ha_says_in_one_line_that_the_disk_is_too_full_and_creates_nothing(tmp_path):
    # a CI machine ran out of disk while pip installed the second environment; ./ha now looks first.
    # A df that reports 500 MB free stands in for the full disk (pip is kept offline, so that if the
    # check were gone the set-up would fail fast with pip's own words instead of ours)
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    (bin_dir / "df").write_text("#!/bin/sh\necho 'Filesystem 1048576-blocks Used Available Capacity Mounted on'\n"
                                "echo '/dev/full 100000 99500 500 100% /'\n")
    (bin_dir / "df").chmod(0o755)
    venv = tmp_path / "venv"
    env = {**os.environ, "PATH": f"{bin_dir}{os.pathsep}{os.environ['PATH']}", "HEADADAPT_VENV": str(venv),
           "PIP_CONFIG_FILE": os.devnull, "PIP_NO_INDEX": "1"}
    proc = subprocess.run(["bash", str(ROOT / "ha"), "python", "-c", "print('ran')"], env=env, cwd=tmp_path,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 1, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and str(venv) in lines[0] and "500 MB free" in lines[0], lines
    assert "ran" not in proc.stdout and not venv.exists()


def test_ha_python_runs_in_the_caller_s_folder_with_the_package_importable(tmp_path):
    """`./ha python -m headadapt_addon.batch adapt --scan head.ply ...` typed beside the scan: a relative
    path means the caller's folder (./ha used to run everything from the checkout: "head.ply: no
    such file")."""
    (tmp_path / "head.ply").write_bytes(b"ply\n")
    code = "import os, headadapt_addon; print(os.path.exists('head.ply'), headadapt_addon.__file__)"
    proc = subprocess.run(["bash", str(ROOT / "ha"), "python", "-c", code], cwd=tmp_path, capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split() == ["True", str(ROOT / "headadapt_addon" / "__init__.py")]
