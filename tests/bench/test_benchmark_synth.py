"""The benchmarks' analytic rays (``benchmarks/synth.py``) are ones a pinhole camera can see:
a pinhole + Brown fit puts the camera 500 mm in front of the LCD's face (Z = -500, METHOD section 2)
with every point in front of it.
(When the rays were a mirror image the best fit put the points behind the camera, and casting
rays through it gave NaN.)"""

from __future__ import annotations

import numpy as np
import pytest

synth = pytest.importorskip("benchmarks.synth")


def test_synthetic_rays_fit_a_pinhole_camera():
    from ptpcore.pinhole import fit_pinhole

    rig = synth.make_rig(0.3, 5)
    truth = synth.SyntheticStack(rig, 0).truth
    h, w = rig.camera.shape
    rng = np.random.default_rng(0)
    rows, cols = rng.integers(0, h, 3000), rng.integers(0, w, 3000)
    z = rng.uniform(0, 12, 3000)
    x = truth.x0[rows, cols] + truth.sx[rows, cols] * z
    y = truth.y0[rows, cols] + truth.sy[rows, cols] * z
    fit = fit_pinhole(np.column_stack([x, y, z]), np.column_stack([cols, rows]).astype(float))
    assert np.isfinite(fit.reprojection_rms_px) and fit.reprojection_rms_px < 0.05
    m = fit.model
    assert m.centre[2] == pytest.approx(-500.0, abs=1.0)
    depth = (np.column_stack([x, y, z]) @ m.R.T + m.tvec)[:, 2]
    assert (depth > 400).all()
    # Seen from the camera (facing the screen, image rows along +Y): X grows with the column,
    # Y with the row.
    assert truth.x0[h // 2, -1] > truth.x0[h // 2, 0] and truth.y0[-1, w // 2] > truth.y0[0, w // 2]
