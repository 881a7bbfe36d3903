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
    monkeypatch.setattr(harmonics, "_kernels", lambda frames: None)  # the numpy path's sums
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


@pytest.mark.parametrize("dtype, n", [(np.uint8, 8), (np.uint8, 5), (np.uint16, 7)])
@pytest.mark.parametrize("axis", [1, 0])
@pytest.mark.parametrize("stride", [1, 3])
def test_the_kernels_noise_samples_are_the_numpy_paths_bit_for_bit(monkeypatch, dtype, n, axis, stride):
    """The DFT bins and means straight from the integer frames (numba, bands on the tile pool): the same
    bits as the numpy path's gathered float64 stack, in bands of a few rows too."""
    from ptpcore.decode.phase import fused_kernels

    if fused_kernels() is None:
        pytest.skip("numba kernels off")
    rng = np.random.default_rng(n)
    top = np.iinfo(dtype).max if dtype == np.uint8 else 4095
    yy, xx = np.mgrid[0:61, 0:97]
    frames = [np.clip(top / 2 + top / 3 * np.cos(0.3 * xx + 0.1 * yy + 2 * np.pi * k / n)
                      + rng.normal(0, 2, xx.shape), 0, top).astype(dtype) for k in range(n)]
    monkeypatch.setattr(harmonics, "BAND_VALUES", 5 * n * 100)
    got = harmonics.harmonic_noise_samples(np.stack(frames), stride, axis)
    monkeypatch.setattr(harmonics, "_kernels", lambda frames: None)
    want = harmonics.harmonic_noise_samples(frames, stride, axis)
    assert set(got) == set(want)
    for name in want:
        assert np.array_equal(np.asarray(got[name]), np.asarray(want[name]), equal_nan=True), name
