"""``/height``'s range rule and the reader's checks that the C reader (readers/c) shares with Python."""

import h5py
import numpy as np
import pytest

from ptpcore.errors import FileFormatError
from ptpcore.io.heightmap import RANGE_EPS_PX, RANGE_REL, HeightMap
from ptpcore.io.lutfile import Lut, load_lut, save_lut
from ptpcore.rig.rigfile import Projector

H, W = 3, 4


def _lower_edge() -> float:
    """A float64 u_p whose float32 rounding lies above it (the stored u_min is then above the true edge)."""
    u = 1000.3
    while float(np.float32(u)) <= u:
        u = np.nextafter(u, np.inf) + 1e-4
    return u


def _map(lo: float) -> HeightMap:
    f32 = np.float32
    centre, scale = np.full((H, W), lo + 20.0), np.full((H, W), 20.0)
    valid = np.ones((H, W), bool)
    return HeightMap(1, "x", centre, scale, np.stack([np.full((H, W), 20.0), np.full((H, W), -20.0)]),
                     np.zeros((1, H, W)), valid, np.full((H, W), lo, f32), np.full((H, W), lo + 40.0, f32),
                     np.zeros((H, W), f32), np.zeros((H, W), f32), np.full((H, W), 0.01, f32),
                     np.full((H, W), 5, np.uint16), design=Projector().design_attrs, chosen_by="test")


def test_a_sample_on_the_calibrated_edge_is_in_range_not_beyond():
    lo = _lower_edge()
    hm = _map(lo)
    stored = float(hm.u_min[0, 0])
    assert stored > lo  # float32 moved the bound inwards
    tol = RANGE_EPS_PX + abs(stored) * RANGE_REL
    u = np.full((H, W), lo)
    u[0, 1], u[0, 2], u[0, 3] = stored - 0.99 * tol, stored - 1.01 * tol, lo - 1e-3
    ev = hm.evaluate(u)
    assert ev.in_range[0, 0] and ev.in_range[0, 1]
    assert not ev.in_range[0, 2] and not ev.in_range[0, 3] and np.isnan(ev.z[0, 3])
    assert abs(ev.z[0, 0] - 40.0) < 1e-3  # s = -1: Z = 20 + 20 (the map's own end, not extrapolated)


@pytest.mark.parametrize("edit, message", [
    (lambda f: f["height/valid"].__setitem__((0, 0), 2), "/height/valid must hold only 0 and 1"),
    (lambda f: f["height"].attrs.__setitem__("steps", np.array([4.0, 4.5, 8.0])), "'steps' of /height must hold whole"),
    (lambda f: f["height"].attrs.__setitem__("steps", np.array([4, 4])), "'periods_px' and 'steps' of /height differ"),
])
def test_the_reader_refuses_what_the_c_reader_refuses(tmp_path, edit, message):
    f32 = np.float32
    zero = np.zeros((H, W), f32)
    lut = Lut("poly", 1, 20.0, 20.0, 0.0, 40.0, np.zeros((2, H, W)), np.zeros((2, H, W)), None, np.ones((H, W), bool),
              np.full((H, W), 9, np.uint16), zero, zero + f32(40.0), zero, zero, zero, zero, height=_map(500.0))
    path = tmp_path / "h.lut.h5"
    save_lut(lut, path)
    assert load_lut(path).height is not None
    with h5py.File(path, "r+") as f:
        edit(f)
    with pytest.raises(FileFormatError, match=message.replace("(", r"\(")):
        load_lut(path)
