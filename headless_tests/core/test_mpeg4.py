"""MPEG-4 tables: the 84 FDPs, their mirror pairs, the 68 FAPs, FAPUs, expressions and visemes."""
import numpy as np
import pytest

from headadapt_addon.core import mpeg4
from headadapt_addon.core.exceptions import LandmarkError

GROUP_SIZES = {2: 14, 3: 14, 4: 6, 5: 4, 6: 4, 7: 1, 8: 10, 9: 15, 10: 10, 11: 6}


def test_fdps_are_the_84_of_groups_2_to_11_in_order():
    names = list(mpeg4.FDPS)
    assert len(names) == 84 == sum(GROUP_SIZES.values())
    assert names == sorted(names, key=mpeg4.fdp_sort_key)
    for g, n in GROUP_SIZES.items():
        assert [k for k in names if k.startswith(f"{g}.")] == [f"{g}.{i}" for i in range(1, n + 1)]


def test_mirror_pairs_are_symmetric_and_sided():
    for name, fdp in mpeg4.FDPS.items():
        assert fdp.label, name
        if fdp.mirror is None:
            assert fdp.side == "M", name
            continue
        partner = mpeg4.FDPS[fdp.mirror]
        assert partner.mirror == name and {fdp.side, partner.side} == {"L", "R"}, name
        assert partner.part.replace("_r", "_l") == fdp.part.replace("_r", "_l"), name
    # the pairs the standard numbers crosswise
    for a, b in (("3.7", "3.12"), ("3.11", "3.8"), ("8.10", "8.9"), ("9.5", "9.4"), ("11.3", "11.2")):
        assert mpeg4.FDPS[a].mirror == b and mpeg4.FDPS[a].side == "L"


def test_unknown_fdp_name_is_named_in_the_error():
    assert mpeg4.check_fdp_name("3.7") == "3.7"
    with pytest.raises(LandmarkError, match="'3.15'"):
        mpeg4.check_fdp_name("3.15")


def test_faps_are_68_with_units_and_their_fdps():
    assert mpeg4.N_FAPS == 68 and list(mpeg4.FAPS) == list(range(1, 69))
    for fap in mpeg4.FAPS.values():
        if fap.kind == "high":
            continue
        assert fap.unit in mpeg4.FAPU_NAMES and fap.fdp in mpeg4.FDPS, fap
        if fap.kind == "translation":
            assert np.linalg.norm(fap.direction) == pytest.approx(1.0)
    assert mpeg4.FAP_BY_NAME["open_jaw"].number == 3 and mpeg4.FAPS[68].name == "pull_r_ear"
    # left/right FAP pairs move mirrored points in mirrored directions
    for fap in mpeg4.FAPS.values():
        if "_l_" in fap.name and fap.kind == "translation":
            right = mpeg4.FAP_BY_NAME[fap.name.replace("_l_", "_r_")]
            assert mpeg4.FDPS[fap.fdp].mirror == right.fdp
            assert np.allclose(np.multiply(fap.direction, [-1, 1, 1]), right.direction), fap.name
    assert len(mpeg4.EXPRESSIONS) == 6 and len(mpeg4.VISEMES) == 15


def test_fapus_from_points_and_missing_points_named():
    rng = np.random.default_rng(1)
    pts = {k: rng.normal(size=3) for k in mpeg4.FDPS}
    f = mpeg4.measure_fapus(pts)
    assert f["MW"] * 1024 == pytest.approx(np.linalg.norm(pts["8.3"] - pts["8.4"]))
    assert f["IRISD"] * 1024 == pytest.approx(np.linalg.norm(pts["3.1"] - pts["3.3"]))
    assert f["AU"] == 1e-5
    del pts["9.15"]
    with pytest.raises(LandmarkError, match="9.15"):
        mpeg4.measure_fapus(pts)
