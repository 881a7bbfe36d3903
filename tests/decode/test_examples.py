"""The shipped examples (examples/NAME, issue 32) decode as their rig.toml says, from the checkout."""

from pathlib import Path

import h5py
import numpy as np
import pytest

from ptpcore.cli import main

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = ROOT / "examples"
SOFAST_SCREEN = 759.0  # px per OpenCSP fractional screen unit
EXPECTED = ROOT / "tests" / "data" / "opencsp-sofast" / "expected_screen_points.h5"


def _decode(name, tmp_path):
    out = tmp_path / f"{name}.decoded.h5"
    assert main(["decode", str(EXAMPLES / name), "--out", str(out), "-q"]) == 0
    with h5py.File(out, "r") as f:
        return f["u"][0], f["v"][0]


def test_every_example_carries_its_licence():
    for name, files in (("sofast", ("LICENSE.txt", "COPYRIGHT.txt")), ("kamino410", ("LICENSE",))):
        for n in files:
            assert (EXAMPLES / name / n).stat().st_size > 100
        assert "ptp decode examples/" + name in (EXAMPLES / name / "rig.toml").read_text()


def test_sofast_example_decodes_to_opencsp_screen_points(tmp_path):
    u, v = _decode("sofast", tmp_path)
    with h5py.File(EXPECTED, "r") as f:
        base = "DataSofastCalculation/facet/facet_000/"
        mask = f[base + "CalculationImageProcessingFacet/mask_processed"][()]
        frac = f[base + "CalculationDataGeometryFacet/v_screen_points_fractional_screens"][()]
    both = mask & np.isfinite(u) & np.isfinite(v)
    assert both.sum() / mask.sum() >= 0.85
    u_ref = np.full(mask.shape, np.nan)
    v_ref = np.full(mask.shape, np.nan)
    u_ref[mask] = frac[0] * SOFAST_SCREEN
    v_ref[mask] = (1.0 - frac[1]) * SOFAST_SCREEN
    rms = np.sqrt(np.mean(np.concatenate([u[both] - u_ref[both], v[both] - v_ref[both]]) ** 2))
    assert rms < 0.05, rms


@pytest.mark.parametrize("name", ["kamino410"])
def test_kamino410_example_decodes_the_object(tmp_path, name):
    u, v = _decode(name, tmp_path)
    ok = np.isfinite(u) & np.isfinite(v)
    assert ok.mean() > 0.5
    # projector coordinates grow with the camera's columns and rows (it sees the projector directly)
    gu = np.nanmedian(np.diff(u, axis=1))
    gv = np.nanmedian(np.diff(v, axis=0))
    assert gu > 0 and gv > 0
