"""Per-pixel weighted polynomial least squares, vectorised over the pixels (the smooth fit's building block).

A module of its own, below :mod:`.noise` and :mod:`.pixel_fits`, which both use it (the noise scale's
leverages and every pixel's own fit): neither may import the other's module graph in a cycle.
"""

from __future__ import annotations

import numpy as np

__all__ = ["weighted_poly_fits"]


def weighted_poly_fits(t: np.ndarray, values_list, weights: np.ndarray, degree: int, full: bool = False):
    """Per-pixel weighted least squares of several value arrays sharing the weights (X and Y).

    The normal equations of every pixel are solved together by Gauss-Jordan
    elimination vectorised over the pixels (symmetric positive definite: no
    pivoting); batched LAPACK calls cost far more than the arithmetic.

    Parameters
    ----------
    t : (K,) ; values_list : list of (K, P) (anything where ``weights == 0``) ; weights : (K, P)

    Returns
    -------
    coefs : list of (D+1, P), NaN where fewer than D+1 samples
    var : (D+1, P) diagonal of the inverse normal matrix (coefficient variances for inverse-variance weights)
    n : (P,) samples used
    cov : (D+1, D+1, P), only with ``full``: the whole inverse normal matrix
    """
    d1 = degree + 1
    p = weights.shape[1]
    used = weights > 0
    n = used.sum(axis=0)
    ok = n >= d1
    tp = t[:, None] ** np.arange(2 * degree + 1)  # (K, 2D+1)
    m = np.einsum("kp,km->mp", weights, tp)
    a = m[np.add.outer(np.arange(d1), np.arange(d1))]  # (D+1, D+1, P)
    inv = np.zeros((d1, d1, p))
    inv[np.arange(d1), np.arange(d1)] = 1.0
    with np.errstate(divide="ignore", invalid="ignore"):
        for i in range(d1):
            piv = a[i, i].copy()
            a[i] /= piv
            inv[i] /= piv
            for r in range(d1):
                if r != i:
                    f = a[r, i].copy()
                    a[r] -= f * a[i]
                    inv[r] -= f * inv[i]
    inv[:, :, ~ok] = np.nan
    coefs = []
    for values in values_list:
        wv = weights * np.where(used, values, 0.0)
        b = np.einsum("kp,kj->jp", wv, tp[:, :d1])
        coefs.append(np.einsum("ijp,jp->ip", inv, b))
    var = inv[np.arange(d1), np.arange(d1)]
    if full:
        return coefs, var, n, inv
    return coefs, var, n
