"""examples/render_expected.py: the picture of what an example should show (issue 32)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import cv2
import h5py
import numpy as np

ROOT = Path(__file__).resolve().parents[2]


def _renderer():
    spec = importlib.util.spec_from_file_location("render_expected", ROOT / "examples" / "render_expected.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_rejected_pixels_are_grey_and_the_coordinate_runs_along_the_colour_map(tmp_path):
    r = _renderer()
    h, w = 40, 60
    u = np.tile(np.linspace(100.0, 700.0, w), (h, 1))
    v = np.tile(np.linspace(50.0, 400.0, h)[:, None], (1, w))
    reasons = np.zeros((1, 2, h, w), np.uint16)
    reasons[0, 0, :, : w // 2] = 1  # left half of u rejected
    decoded = tmp_path / "t.decoded.h5"
    with h5py.File(decoded, "w") as f:
        f["u"], f["v"], f["reasons"] = u[None], v[None], reasons
    uu, vv = r.decoded_maps(decoded)
    assert np.isnan(uu[:, : w // 2]).all() and np.isfinite(uu[:, w // 2:]).all() and np.isfinite(vv).all()
    panel = r._panel(uu, "u")
    scale = r.PANEL_HEIGHT / h
    map_rows = panel[28:28 + r.PANEL_HEIGHT]
    left = map_rows[:, : int(scale * w // 2) - 1]
    right = map_rows[:, int(scale * w // 2) + 1:]
    assert (left == r.GREY).all()
    assert not (right == r.GREY).all(axis=-1).any()
    # viridis: dark purple at the low end, yellow at the high end (BGR: red + green high)
    lo_px, hi_px = right[r.PANEL_HEIGHT // 2, 0], right[r.PANEL_HEIGHT // 2, -1]
    assert int(hi_px[1]) + int(hi_px[2]) > int(lo_px[1]) + int(lo_px[2]) + 200
    picture = r.render(uu, vv, "title")
    assert picture.shape[0] == 30 + panel.shape[0] and picture.dtype == np.uint8
    out = tmp_path / "x.png"
    assert r.main(["sofast", "--decoded", str(decoded), "--out", str(out)]) == 0
    assert cv2.imread(str(out)).shape == picture.shape


def test_the_shipped_pictures_exist_and_are_small():
    for name in ("sofast", "kamino410"):
        png = ROOT / "examples" / name / "expected.png"
        assert png.stat().st_size < 150_000, png
        assert cv2.imread(str(png)) is not None
