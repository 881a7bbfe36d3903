"""`{dir}` optional with one direction, `{pos}` with one position (issue 32, FORMATS.md ptp-dataset/2).

The same simulated capture is written twice, under the usual templates and under templates
without the field its design makes redundant; `ptp decode` reads both to the same maps.
"""

from dataclasses import replace

import h5py
import numpy as np
import pytest

from ptpcore.cli import main
from ptpcore.decode.patterns import gray_code_rig
from ptpcore.errors import ConfigError
from ptpcore.rig import load_rig
from ptpcore.rig.rigfile import rig_from_toml, rig_to_toml
from ptpcore.simulate import scaled_preset, simulate_dataset


def _decode(ds, out):
    assert main(["decode", str(ds), "--out", str(out), "-q"]) == 0
    with h5py.File(out, "r") as f:
        return f["u"][()], f["v"][()], f["reasons"][()]


def _one_direction_rig(positions):
    rig, settings = scaled_preset("realistic", 96, positions=positions)
    rig = replace(rig, fringes=replace(rig.fringes, directions=("x",)))
    return rig, settings


@pytest.mark.parametrize("case", ["one direction, no {dir}", "one position, no {pos}",
                                  "one of each, neither", "Gray code, one direction, no {dir}"])
def test_a_capture_without_the_redundant_field_decodes(tmp_path, case):
    if case == "one position, no {pos}":
        rig, settings = scaled_preset("realistic", 96, positions=1)
        template = "{dir}_T{period}_n{step:02d}.png"
    elif case == "one of each, neither":
        rig, settings = _one_direction_rig(1)
        template = "T{period}_n{step:02d}.png"
    else:
        rig, settings = _one_direction_rig(2)
        template = "z{pos:03d}/T{period}_n{step:02d}.png"
    plain = rig
    if case.startswith("Gray"):
        plain = gray_code_rig(rig, 2, inverse=True)
        rig = replace(plain, template=template, gray_template="z{pos:03d}/G{bit:02d}_{inverse}.png")
    else:
        rig = replace(rig, template=template)
    if rig.stage.n_positions == 1:
        assert 'format = "ptp-dataset/2"' in rig_to_toml(rig)
    ref = simulate_dataset(tmp_path / "usual", plain, settings, seed=3)
    short = simulate_dataset(tmp_path / "short", rig, settings, seed=3)
    loaded = load_rig(short)
    assert loaded.template == template
    u0, v0, r0 = _decode(ref, tmp_path / "usual.decoded.h5")
    u1, v1, r1 = _decode(short, tmp_path / "short.decoded.h5")
    assert np.mean(np.isfinite(u1)) > 0.5  # most pixels decoded
    np.testing.assert_array_equal(u1, u0)
    np.testing.assert_array_equal(v1, v0)
    np.testing.assert_array_equal(r1, r0)


def test_the_field_stays_required_where_names_would_collide():
    rig, _ = scaled_preset("realistic", 96, positions=2)
    for template, field in (("z{pos:03d}/T{period}_n{step:02d}.png", "dir"),  # two directions
                            ("{dir}_T{period}_n{step:02d}.png", "pos")):      # two positions
        text = rig_to_toml(replace(rig, template=template))
        with pytest.raises(ConfigError, match=f"must contain '{{{field}}}'"):
            rig_from_toml(text)
