"""MPEG-4 .fap files (core/fapfile.py): exact round trip, both FAP 1/2 layouts, errors that name file and line."""
import numpy as np
import pytest

from headadapt_addon.core import mpeg4
from headadapt_addon.core.exceptions import FileFormatError, HeadAdaptError
from headadapt_addon.core.fapfile import FapAnimation, fap_column, read_fap, write_fap

MASK = lambda *on: " ".join("1" if i in on else "0" for i in range(1, 69))


def _random_anim(n, rng):
    vals = np.where(rng.random((n, 69)) < 0.4, rng.integers(-2000, 2000, (n, 69)).astype(float), np.nan)
    vals[:, 0] = np.nan
    vals[[0, 3, 5], 1] = vals[[1, 3, 8], 2] = 0                      # FAP 1 and 2 on some frames for sure
    vals[::3, 5] = [12.5, -0.125, 1234567.25][: len(vals[::3])]     # floats, one needing 9 digits
    vis, exp = np.full((n, 4), np.nan), np.full((n, 6), np.nan)
    has_v, has_e = ~np.isnan(vals[:, 1]), ~np.isnan(vals[:, 2])
    vis[has_v] = np.c_[rng.integers(0, 15, (has_v.sum(), 2)), rng.integers(0, 64, has_v.sum()), rng.integers(0, 2, has_v.sum())]
    exp[has_e] = np.c_[rng.integers(0, 7, has_e.sum()), rng.integers(0, 64, has_e.sum()), rng.integers(0, 7, has_e.sum()),
                       rng.integers(0, 64, (has_e.sum(), 3))]
    vals[:, 1], vals[:, 2] = vis[:, 0], exp[:, 0]
    return FapAnimation("take one", 29.97, np.arange(n), vals, vis, exp)


def test_round_trip_is_exact_with_compound_viseme_and_expression(tmp_path):
    anim = _random_anim(9, np.random.default_rng(3))
    assert (~np.isnan(anim.visemes[:, 0])).sum() >= 2 and (~np.isnan(anim.expressions[:, 0])).sum() >= 2
    write_fap(tmp_path / "a.fap", anim)
    assert [p.name for p in tmp_path.iterdir()] == ["a.fap"]             # no temp file left behind
    back = read_fap(tmp_path / "a.fap")
    assert back.name == "take one" and back.fps == 29.97 and back.duration_s == pytest.approx(9 / 29.97)
    assert back.frames.dtype.kind == "i"
    for got, want in ((back.frames, anim.frames), (back.values, anim.values), (back.visemes, anim.visemes),
                      (back.expressions, anim.expressions)):
        np.testing.assert_array_equal(got, want)                         # NaN in the same places
    data = (tmp_path / "a.fap").read_text().splitlines()[2::2]
    row = int(np.flatnonzero(~np.isnan(anim.visemes[:, 0]))[0])
    assert data[row].split()[1:5] == [str(int(v)) for v in anim.visemes[row]]   # 4 values for FAP 1, integers
    assert "1234567.25" in (tmp_path / "a.fap").read_text()


def test_hand_written_file_with_both_layouts(tmp_path):
    (tmp_path / "h.fap").write_text(
        "# made by hand\n2.1 hello 25 3\n\n"
        f"{MASK(1, 2, 3, 49)}\n0 5 7 20 0 1 40 6 10 0 0 -100 3.5\n"   # compound: 4 + 6 values
        f"{MASK(1, 2, 3)}\n1 12 4 200\n"                                # one value for FAP 1 and 2
        f"# comment between frames\n{MASK(4)}\n2 -7\n")
    anim = read_fap(tmp_path / "h.fap")
    assert anim.name == "hello" and anim.fps == 25 and anim.frames.tolist() == [0, 1, 2]
    np.testing.assert_array_equal(anim.visemes[:2], [[5, 7, 20, 0], [12, 0, 63, 0]])
    np.testing.assert_array_equal(anim.expressions[:2], [[1, 40, 6, 10, 0, 0], [4, 63, 0, 0, 0, 0]])
    assert np.isnan(anim.visemes[2]).all() and np.isnan(anim.expressions[2]).all()
    np.testing.assert_array_equal(fap_column(anim, "open_jaw"), [-100, 200, np.nan])
    np.testing.assert_array_equal(fap_column(anim, 49), [3.5, np.nan, np.nan])
    np.testing.assert_array_equal(fap_column(anim, "viseme"), [5, 12, np.nan])
    np.testing.assert_array_equal(fap_column(anim, mpeg4.FAP_BY_NAME["lower_t_midlip"].number), [np.nan, np.nan, -7])
    assert np.isnan(anim.values[:, 0]).all() and np.isnan(anim.values).sum() == 3 * 69 - 8
    # the one-value frame is written back in the compound layout and reads back the same
    write_fap(tmp_path / "h2.fap", anim)
    again = read_fap(tmp_path / "h2.fap")
    np.testing.assert_array_equal(again.values, anim.values)
    np.testing.assert_array_equal(again.expressions, anim.expressions)


HEAD = "2.1 x 25 1\n"


@pytest.mark.parametrize("text, where", [
    ("", "the FAP file is empty (0 bytes)"),
    ("2.1 x 25 99999999\n", "line 1) says 99999999 frames, the file holds only 0"),   # 18 bytes asking for GBs
    ("2.1 x 25 1e300\n", "frames, the file holds only 0"),
    (HEAD + MASK(3) + "\n1e300 1\n", "line 3: frame number '1e300' is not a whole number of 64 bits"),
    (HEAD + MASK(3) + "\n0 1" + "0" * 5000 + "\n", "line 3: '1000"),
    ("# only a comment\n2.1 x 25\n", "line 2: bad header"),
    ("v2 x 25 1\n", "line 1: 'v2' is not a number"),
    ("2.1 x 0 1\n", "line 1: frame rate 0"),
    ("2.1 x -5 1\n", "line 1: frame rate -5"),
    ("2.1 x 25 1.5\n", "line 1: number of frames"),
    (HEAD + MASK() + " 0\n0\n", "line 2: the mask of frame 1 has 69 entries"),
    (HEAD + MASK().replace("0", "2", 1) + "\n0\n", "line 2: mask entry '2'"),
    (HEAD + MASK(3) + "\n0\n", "line 3: 0 values for 1 FAPs"),
    (HEAD + MASK(1, 3) + "\n0 1 2 3\n", "line 3: 3 values for 2 FAPs in the mask, expected 2 or 5"),
    (HEAD + MASK(3) + "\n0 abc\n", "line 3: 'abc' is not a number"),
    (HEAD + MASK(3) + "\n0 nan\n", "line 3: 'nan' is not a number"),
    (HEAD + MASK(3) + "\n0.5 1\n", "line 3: frame number '0.5'"),
    ("2.1 x 25 3\n" + MASK(3) + "\n0 1\n" + MASK(3) + "\n", "says 3 frames, the file holds only 1"),
    (HEAD + MASK(3) + "\n0 1\n" + MASK(3) + "\n1 2\n", "line 4: more lines than the header's 1 frames"),
    ("2.1 x 25 2\n" + MASK(3) + "\n10 1\n" + MASK(3) + "\n5 2\n", "line 5: frame number 5 does not follow frame 10"),
    ("2.1 x 25 2\n" + MASK(3) + "\n0 1\n" + MASK(3) + "\n0 2\n", "line 5: frame number 0 does not follow frame 0"),
    ("2.1 x 25 2\n" + MASK(3) + "\n0 1\n" + MASK(3) + "\n1 inf\n", "line 5: 'inf' is not a number"),
])
def test_bad_files_name_the_file_and_line(tmp_path, text, where):
    path = tmp_path / "bad.fap"
    path.write_text(text)
    with pytest.raises(FileFormatError) as err:
        read_fap(path)
    assert str(path) in str(err.value) and where in str(err.value), str(err.value)


def test_missing_file_unknown_fap_and_bad_animation(tmp_path):
    with pytest.raises(FileFormatError, match="nope.fap"):
        read_fap(tmp_path / "nope.fap")
    anim = FapAnimation("x", 25, np.arange(2), np.full((2, 69), np.nan), np.full((2, 4), np.nan), np.full((2, 6), np.nan))
    assert np.isnan(fap_column(anim, "head_yaw")).all()
    with pytest.raises(HeadAdaptError, match="open_mouth"):
        fap_column(anim, "open_mouth")
    with pytest.raises(HeadAdaptError, match="69"):
        fap_column(anim, 69)
    anim.values = anim.values[:, :68]
    with pytest.raises(HeadAdaptError, match="'x'"):
        write_fap(tmp_path / "x.fap", anim)
    assert not (tmp_path / "x.fap").exists()


def test_a_file_saved_with_a_byte_order_mark_reads_as_without(tmp_path):
    """Windows Notepad wrote UTF-8 with a BOM; the header's first token is then '\\ufeff2.1'."""
    text = "2.1 x 25 2\n" + MASK(3, 48) + "\n0 100 5\n" + MASK(3) + "\n7 200\n"
    (tmp_path / "plain.fap").write_text(text)
    (tmp_path / "bom.fap").write_bytes(b"\xef\xbb\xbf" + text.encode())
    plain, bom = read_fap(tmp_path / "plain.fap"), read_fap(tmp_path / "bom.fap")
    np.testing.assert_array_equal(bom.values, plain.values)
    assert bom.frames.tolist() == [0, 7] and bom.values[0, 48] == 5 and np.isnan(bom.values[1, 48])
