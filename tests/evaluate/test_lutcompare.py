"""``ptpcore.evaluate.lutcompare``: two LUT files compared exactly, every group, dataset and attribute;
NaN equals NaN; ``created`` and ``software`` left out unless asked; names and paths in ``ignore``."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from ptpcore.errors import FileFormatError
from ptpcore.evaluate.lutcompare import LutComparison, compare_lut_files


def _write(path, created="2026-11-26T10:00:00", x=None, nan_payload=0, scale=16.0, extra=False, settings="{}"):
    x = np.arange(12, dtype=np.float64).reshape(3, 4) if x is None else x
    with h5py.File(path, "w") as f:
        f.attrs["created"] = created
        f.attrs["software"] = "ptp-studio 0.1.0"
        f.attrs["format"] = "ptp-lut/1"
        f["x"] = x
        g = f.create_group("model")
        g.attrs["smoothing_scale_px"] = scale
        g.attrs["method"] = "smooth"
        g["sigma"] = np.array([1.0, np.uint64(0x7FF8000000000000 + nan_payload).view(np.float64)], np.float64)
        g["valid"] = np.array([[True, False]])
        if extra:
            g["extra"] = np.zeros(2, np.float32)
        p = f.create_group("provenance")
        p.attrs["settings"] = settings


def test_equal_but_for_the_time_of_writing_and_the_software(tmp_path):
    _write(tmp_path / "a.h5")
    _write(tmp_path / "b.h5", created="2026-11-26T16:00:00")
    with h5py.File(tmp_path / "b.h5", "a") as f:
        f.attrs["software"] = "ptp-studio 0.2.0"
    result = compare_lut_files(tmp_path / "a.h5", tmp_path / "b.h5")
    assert isinstance(result, LutComparison) and result.equal and result.differences == []
    assert result.lines() == [f"identical: {tmp_path / 'a.h5'} vs {tmp_path / 'b.h5'}"]
    every = compare_lut_files(tmp_path / "a.h5", tmp_path / "b.h5", ignore=())
    assert not every.equal
    assert every.differences == ["attribute /@created: 1 of 1 strings differ", "attribute /@software: 1 of 1 strings differ"]


def test_every_difference_is_one_line_naming_what_and_the_largest_difference(tmp_path):
    _write(tmp_path / "a.h5")
    x = np.arange(12, dtype=np.float64).reshape(3, 4)
    x[1, 2] += 2.5e-9
    x[2, 3] += 1e-12
    # A NaN with another payload is still NaN (equal); a changed attribute in a subgroup, a dataset in B only.
    _write(tmp_path / "b.h5", x=x, nan_payload=1, scale=8.0, extra=True)
    result = compare_lut_files(tmp_path / "a.h5", tmp_path / "b.h5")
    assert not result.equal
    assert result.differences == [
        "attribute /model@smoothing_scale_px: 1 of 1 elements differ, largest |A - B| = 8",
        "/model/extra: only in B",
        "dataset /x: 2 of 12 elements differ, largest |A - B| = 2.5e-09",
    ]
    assert result.lines()[-1] == f"3 difference(s): {tmp_path / 'a.h5'} vs {tmp_path / 'b.h5'}"


def test_nan_against_a_number_dtypes_shapes_and_kinds(tmp_path):
    _write(tmp_path / "a.h5")
    _write(tmp_path / "b.h5", x=np.where(np.arange(12).reshape(3, 4) == 5, np.nan, np.arange(12.0).reshape(3, 4)))
    assert compare_lut_files(tmp_path / "a.h5", tmp_path / "b.h5").differences == [
        "dataset /x: 1 of 12 elements differ, largest |A - B| = n/a, NaN in one only at 1"]
    _write(tmp_path / "c.h5", x=np.arange(12, dtype=np.float32).reshape(3, 4))
    assert compare_lut_files(tmp_path / "a.h5", tmp_path / "c.h5").differences == [
        "dataset /x: dtype float64 != float32"]
    _write(tmp_path / "d.h5", x=np.arange(12, dtype=np.float64).reshape(4, 3))
    assert compare_lut_files(tmp_path / "a.h5", tmp_path / "d.h5").differences == [
        "dataset /x: shape (3, 4) != (4, 3)"]
    _write(tmp_path / "e.h5")
    with h5py.File(tmp_path / "e.h5", "a") as f:
        del f["x"]
        f.create_group("x")
    assert compare_lut_files(tmp_path / "a.h5", tmp_path / "e.h5").differences == [
        "/x: a dataset in A, a group in B"]


def test_ignore_takes_names_and_paths_of_attributes_and_datasets(tmp_path):
    _write(tmp_path / "a.h5")
    _write(tmp_path / "b.h5", scale=8.0, settings='{"degree": 3}', extra=True)
    assert len(compare_lut_files(tmp_path / "a.h5", tmp_path / "b.h5").differences) == 3
    for ignore in (["settings", "smoothing_scale_px", "extra"],
                   ["/provenance@settings", "/model@smoothing_scale_px", "/model/extra"],
                   ["/provenance/settings", "/model/smoothing_scale_px", "/model/extra"]):
        result = compare_lut_files(tmp_path / "a.h5", tmp_path / "b.h5", ignore=("created", "software", *ignore))
        assert result.equal, (ignore, result.differences)
    # A path leaves out that one object (a group with everything in it), not others of the name.
    _write(tmp_path / "c.h5", settings='{"degree": 3}')
    with h5py.File(tmp_path / "c.h5", "a") as f:
        f["model/sigma"][0] = 2.0
    assert compare_lut_files(tmp_path / "a.h5", tmp_path / "c.h5",
                             ignore=("created", "software", "/provenance", "/model/sigma")).equal
    assert compare_lut_files(tmp_path / "a.h5", tmp_path / "c.h5",
                             ignore=("created", "software", "/provenance", "/sigma")).differences == [
        "dataset /model/sigma: 1 of 2 elements differ, largest |A - B| = 1"]


def test_a_file_that_is_not_hdf5_is_named(tmp_path):
    _write(tmp_path / "a.h5")
    (tmp_path / "bad.h5").write_text("not hdf5")
    with pytest.raises(FileFormatError, match="bad.h5"):
        compare_lut_files(tmp_path / "a.h5", tmp_path / "bad.h5")
    with pytest.raises(FileFormatError, match="missing.h5"):
        compare_lut_files(tmp_path / "missing.h5", tmp_path / "a.h5")


def test_a_lut_written_twice_is_equal_and_a_changed_coefficient_is_found(tmp_path):
    """A real ``ptp-lut`` file (every group the writer makes, its string and JSON attributes): written twice
    from one fit it compares equal; one coefficient changed by 1 nm is found and named."""
    from ptpcore.fit import fit_lut
    from ptpcore.io.lutfile import load_lut, save_lut
    from ptpcore.simulate.synthetic import synthetic_photometric_samples

    samples, _rig, _truth = synthetic_photometric_samples(0.005, 5, spill=False)
    lut = fit_lut(samples, "poly", 2)
    save_lut(lut, tmp_path / "a.lut.h5")
    save_lut(lut, tmp_path / "b.lut.h5")
    assert compare_lut_files(tmp_path / "a.lut.h5", tmp_path / "b.lut.h5").equal
    changed = load_lut(tmp_path / "b.lut.h5")
    changed.x[0, 10, 10] += 1e-6
    save_lut(changed, tmp_path / "c.lut.h5")
    diffs = compare_lut_files(tmp_path / "a.lut.h5", tmp_path / "c.lut.h5").differences
    assert len(diffs) == 1 and diffs[0].startswith("dataset /") and "1 of" in diffs[0], diffs
