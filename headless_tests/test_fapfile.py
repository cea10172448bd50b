"""MPEG-4 .fap files (core/fapfile.py): exact round trip, both FAP 1/2 layouts, errors that name file and line."""
import numpy as np
import pytest

from headadapt_addon.core import mpeg4
from headadapt_addon.core.exceptions import FileFormatError, HeadAdaptError
from headadapt_addon.core.fapfile import FapAnimation, fap_column, read_fap, write_fap


def test_round_trip_is_exact(tmp_path):
    rng = np.random.default_rng(1)
    n = 7
    vals = np.where(rng.random((n, 69)) < 0.3, rng.integers(-500, 500, (n, 69)).astype(float), np.nan)
    vals[:, :3] = np.nan
    vals[:, 3] = np.arange(n) * 10.0
    vis = np.full((n, 4), np.nan)
    vis[2] = [3, 7, 20, 0]
    exp = np.full((n, 6), np.nan)
    exp[4] = [1, 40, 6, 10, 0, 0]
    vals[2, 1], vals[4, 2] = 3, 1
    anim = FapAnimation("take", 25.0, np.arange(1, n + 1), vals, vis, exp)
    write_fap(tmp_path / "a.fap", anim)
    back = read_fap(tmp_path / "a.fap")
    assert back.name == "take" and back.fps == 25.0 and back.duration_s == pytest.approx(n / 25)
    np.testing.assert_array_equal(back.frames, anim.frames)
    np.testing.assert_array_equal(back.values, vals)
    np.testing.assert_array_equal(back.visemes, vis)
    np.testing.assert_array_equal(back.expressions, exp)
    np.testing.assert_array_equal(fap_column(back, "open_jaw"), np.arange(n) * 10.0)
    assert np.isnan(fap_column(back, 4)).sum() == np.isnan(vals[:, 4]).sum()


def test_one_value_per_fap_layout(tmp_path):
    mask = ["0"] * 68
    mask[0] = mask[1] = mask[2] = "1"
    (tmp_path / "s.fap").write_text("2.1 short 30 1\n" + " ".join(mask) + "\n0 12 4 100\n")
    anim = read_fap(tmp_path / "s.fap")
    assert anim.visemes[0, 0] == 12 and anim.expressions[0, :2].tolist() == [4, 63]
    assert anim.values[0, 3] == 100


@pytest.mark.parametrize("text, line", [
    ("", "line 1"),
    ("2.1 x 0 1\n" + "0 " * 68 + "\n0\n", "line 1"),
    ("2.1 x 25 1\n" + "0 " * 67 + "\n0\n", "line 2"),
    ("2.1 x 25 1\n" + "2 " * 68 + "\n0\n", "line 2"),
    ("2.1 x 25 1\n" + "0 0 1 " + "0 " * 65 + "\n0\n", "line 3"),
    ("2.1 x 25 1\n" + "0 0 1 " + "0 " * 65 + "\n0 abc\n", "line 3"),
    ("2.1 x 25 2\n" + "0 " * 68 + "\n0\n", "2 frames"),
])
def test_bad_files_name_the_file_and_line(tmp_path, text, line):
    path = tmp_path / "bad.fap"
    path.write_text(text)
    with pytest.raises(FileFormatError, match="bad.fap") as err:
        read_fap(path)
    assert line in str(err.value)


def test_missing_file_and_unknown_fap():
    with pytest.raises(FileFormatError, match="nope.fap"):
        read_fap("/nonexistent/nope.fap")
    anim = FapAnimation("x", 25, np.arange(1), np.full((1, mpeg4.N_FAPS + 1), np.nan), np.full((1, 4), np.nan),
                        np.full((1, 6), np.nan))
    with pytest.raises(HeadAdaptError, match="open_mouth"):
        fap_column(anim, "open_mouth")
