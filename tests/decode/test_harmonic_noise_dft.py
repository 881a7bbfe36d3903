"""The harmonic-free noise's DFT bins in real arithmetic (issue 33): the complex ``tensordot`` they
replace, to rounding, and the noise they give unchanged in what it measures."""

import numpy as np
import pytest

from ptpcore.decode import harmonics


@pytest.mark.parametrize("n", [5, 8, 12])
def test_dft_bins_equal_the_complex_sum(n):
    rng = np.random.default_rng(n)
    stack = rng.integers(0, 256, (n, 7, 33)).astype(np.float64)
    delta = 2.0 * np.pi * np.arange(n) / n
    for hh in [1, *harmonics.noise_bins(n)]:
        want = np.tensordot(np.exp(-1j * hh * delta), stack, axes=(0, 0))
        got = harmonics._dft_bin(stack, hh)
        assert got.dtype == np.complex128 and got.shape == want.shape
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-12 * np.abs(want).max())


def test_noise_samples_are_the_complex_sums_ones(monkeypatch):
    """8-step fringes with a display harmonic and noise: every output of ``harmonic_noise_samples`` is
    the one the complex ``tensordot`` gave, to rounding."""
    rng = np.random.default_rng(0)
    n, h, w = 8, 40, 300
    xx = np.arange(w)[None, :]
    frames = []
    for k in range(n):
        phase = 2 * np.pi * xx / 23.0 + 2 * np.pi * k / n
        clean = 120 + 60 * np.cos(phase) + 9 * np.cos(2 * phase)
        frames.append(np.clip(np.rint(clean + rng.normal(0, 2.0, (h, w))), 0, 255).astype(np.uint8))
    got = harmonics.harmonic_noise_samples(frames, 2, 1)

    def complex_sum(stack, hh):
        delta = 2.0 * np.pi * np.arange(stack.shape[0]) / stack.shape[0]
        return np.tensordot(np.exp(-1j * hh * delta), stack, axes=(0, 0))

    monkeypatch.setattr(harmonics, "_dft_bin", complex_sum)
    want = harmonics.harmonic_noise_samples(frames, 2, 1)
    assert got.keys() == want.keys()
    for name in ("background", "var", "harmonic", "modulation"):
        np.testing.assert_allclose(got[name], want[name], rtol=1e-12, err_msg=name)
    assert np.median(got["harmonic"]) == pytest.approx(9.0, rel=0.1)  # the harmonic is seen
