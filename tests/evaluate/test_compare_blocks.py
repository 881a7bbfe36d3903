"""The comparison's statistics one held-out position at a time against the whole-array formulas (issue 15).

:func:`ptpcore.evaluate.compare` keeps its per-position error maps in a temporary
file and computes every statistic reading one position at a time. Here the same
numbers are recomputed from whole ``(E, H, W)`` arrays, as the comparison did
before: per-position statistics, heatmaps, p95, max and counts must be identical,
RMS and means (sums of per-position sums) equal to 1e-12 relative, and the point
pairs the same pixels as drawn from the concatenated index lists.
"""

from __future__ import annotations

import errno
import gc
import os
import math
from types import SimpleNamespace

import numpy as np
import pytest

import ptpcore.evaluate.statistics as st
from ptpcore.atomic import DiskFullError, live_temporaries
from ptpcore.evaluate import METHODS, compare, coordinate_stats
from ptpcore.evaluate.report import ErrorMaps, HeldOutMaps
from ptpcore.io import SimulatedSource
from ptpcore.run import collect_samples
from ptpcore.simulate import VirtualRig, scaled_preset


@pytest.fixture(scope="module")
def small():
    """The rough preset at 160 px wide, 9 positions (4 held out), truth given; row blocks of 7 rows."""
    rig, settings = scaled_preset("rough", 160, positions=9)
    vr = VirtualRig(rig, settings, seed=4)
    samples = collect_samples(SimulatedSource(vr))
    truth = vr.truth()
    import ptpcore.evaluate.protocol as protocol

    keep = protocol._BLOCK_PIXELS
    protocol._BLOCK_PIXELS = 7 * 160  # many row blocks per position (and a short last one)
    try:
        result = compare(samples, vr.rig, truth=truth, seed=1, n_points=500, n_pairs=2000)
    finally:
        protocol._BLOCK_PIXELS = keep
    return SimpleNamespace(vr=vr, samples=samples, truth=truth, result=result)


def _whole_formulas(r, ref):
    """The statistics as computed from whole (E, H, W) arrays (the comparison before issue 15)."""
    mask = r.mask
    out = {}
    for m in r.methods:
        em = np.asarray(r.error_vs_measured[m]).astype(np.float64)
        if ref == "truth":
            em = em + np.asarray(r.measured_minus_truth)
        dx, dy = em[0], em[1]
        per = [coordinate_stats(dx[i][mask[i]], dy[i][mask[i]]) for i in range(mask.shape[0])]
        sq = np.where(mask, dx * dx + dy * dy, 0.0).sum(axis=0)
        n = mask.sum(axis=0)
        heat = np.full(r.shape, np.nan)
        np.sqrt(np.divide(sq, n, out=np.zeros_like(sq), where=n > 0), out=heat, where=n > 0)
        out[m] = (coordinate_stats(dx[mask], dy[mask]), per, heat, (dx, dy))
    return out


def _assert_same_stats(mine, whole, exact_sums: bool = False):
    """n, p95, max identical; the sums' statistics identical or to 1e-12 relative."""
    assert mine.n == whole.n and mine.p95_um == whole.p95_um and mine.max_um == whole.max_um
    for key in ("rms_um", "mean_um", "rms_x_um", "rms_y_um", "mean_x_um", "mean_y_um"):
        if exact_sums:
            assert getattr(mine, key) == getattr(whole, key), key
        else:
            assert getattr(mine, key) == pytest.approx(getattr(whole, key), rel=1e-12, abs=1e-9), key


def test_blocked_statistics_equal_the_whole_array_formulas(small):
    r = small.result
    assert r.methods == METHODS and len(r.held_positions) == 4
    for ref in ("measured", "truth"):
        whole = _whole_formulas(r, ref)
        for m in r.methods:
            mr = r.references[ref].methods[m]
            overall, per, heat, (dx, dy) = whole[m]
            _assert_same_stats(mr.coordinate, overall)
            assert [s.__dict__ for s in mr.per_position] == [s.__dict__ for s in per]  # one position: identical
            np.testing.assert_array_equal(mr.heatmap_mm, heat)  # running sums in position order: bit for bit
            e_dx, e_dy = r.errors(m, ref)
            np.testing.assert_array_equal(e_dx, dx)
            np.testing.assert_array_equal(e_dy, dy)
            # distance errors: a method's pair end is the measured point plus its error there
            for kind, p in r.pairs.items():
                ends = []
                for ei, row, col in ((p.held_a, p.row_a, p.col_a), (p.held_b, p.row_b, p.col_b)):
                    meas = np.stack([small.samples.x_ref[row, col] + small.samples.x[r.held_positions[ei], row, col],
                                     small.samples.y_ref[row, col] + small.samples.y[r.held_positions[ei], row, col],
                                     r.z_held[ei]], axis=1)
                    em = np.asarray(r.error_vs_measured[m])
                    mp = meas.copy()
                    mp[:, 0] += em[0, ei, row, col]
                    mp[:, 1] += em[1, ei, row, col]
                    if ref == "truth":
                        z = r.z_held[ei]
                        t = small.truth
                        meas = np.stack([t.x0[row, col] + t.sx[row, col] * z, t.y0[row, col] + t.sy[row, col] * z, z],
                                        axis=1)
                    ends.append((mp, meas))
                err = np.linalg.norm(ends[0][0] - ends[1][0], axis=1) - np.linalg.norm(ends[0][1] - ends[1][1], axis=1)
                np.testing.assert_array_equal(mr.distance[kind].error_mm, err)
    mmt = np.asarray(r.measured_minus_truth)
    mask = r.mask
    _assert_same_stats(r.reference_noise, coordinate_stats(mmt[0][mask], mmt[1][mask]))


def test_error_maps_read_one_position_or_whole(small):
    r = small.result
    em = r.error_vs_measured["ptp"]
    assert isinstance(em, ErrorMaps) and em.shape == (2, 4, *r.shape) and em.dtype == np.float32
    whole = np.asarray(em)
    assert whole.shape == em.shape and whole.dtype == np.float32
    for e in range(4):
        np.testing.assert_array_equal(em.position(e), whole[:, e])
        np.testing.assert_array_equal(r.maps.mask_at(e), np.isfinite(whole[0, e]))
    np.testing.assert_array_equal(em[1, 2], whole[1, 2])
    np.testing.assert_array_equal(r.coverage.n_compared, r.mask.sum(axis=(1, 2)))
    # the coverage counts were summed over row blocks: the same as over whole maps
    valid = small.samples.valid[r.held_positions]
    np.testing.assert_array_equal(r.coverage.n_measured, valid.sum(axis=(1, 2)))


def _old_draw_pairs(mask, groups, kind, n_pairs, n_bins, rng, measured_xyz):
    """The pair draw from the whole mask and the concatenated index lists (before issue 15)."""
    e_n, h, w = mask.shape
    flat = [np.flatnonzero(mask[e]) for e in range(e_n)]
    sizes = np.array([f.size for f in flat], dtype=np.int64)
    combos = ([(e, e) for e in range(e_n) if sizes[e] >= 2] if kind == "same_height" else
              [(a, b) for g in groups for a in g for b in g if a < b and sizes[a] and sizes[b]])
    combos = np.asarray(combos, dtype=np.int64)
    offsets = np.concatenate([[0], np.cumsum(sizes)])
    all_flat = np.concatenate(flat)
    diag = math.hypot(h - 1, w - 1)
    m = 20 * n_pairs
    c = combos[rng.integers(len(combos), size=m)]
    swap = rng.random(m) < 0.5
    ea = np.where(swap, c[:, 1], c[:, 0])
    eb = np.where(swap, c[:, 0], c[:, 1])
    pa = all_flat[offsets[ea] + (rng.random(m) * sizes[ea]).astype(np.int64)]
    ra, ca = np.divmod(pa, w)
    length = rng.random(m) * diag
    theta = rng.random(m) * 2 * np.pi
    cb = np.rint(ca + length * np.cos(theta)).astype(np.int64)
    rb = np.rint(ra + length * np.sin(theta)).astype(np.int64)
    ok = (cb >= 0) & (cb < w) & (rb >= 0) & (rb < h)
    ok[ok] = mask[eb[ok], rb[ok], cb[ok]]
    ok &= ~((ea == eb) & (ra == rb) & (ca == cb))
    return ea[ok], eb[ok], ra[ok], ca[ok], rb[ok], cb[ok]


@pytest.mark.parametrize("kind", ["same_height", "across_heights"])
def test_pairs_are_the_whole_mask_draw(small, kind):
    """The first round of candidates: the same pixels as drawn from the whole mask (later rounds append)."""
    r = small.result
    mask = r.mask
    groups = [np.arange(len(r.held_positions))]
    seen = {}

    def measured_xyz(e, row, col):
        seen["ends"] = (np.array(e), np.array(row), np.array(col))
        return np.stack([col, row, np.zeros(len(col))], axis=1).astype(float)

    n_pairs = 300
    old = _old_draw_pairs(mask, groups, kind, n_pairs, 10, np.random.default_rng(7), measured_xyz)
    st.draw_pairs(r.maps.mask_at, r.coverage.n_compared, r.shape, groups, kind, n_pairs, 10,
                   np.random.default_rng(7), measured_xyz)
    e, row, col = seen["ends"]
    assert old[0].size > 100 and e.size >= old[0].size
    np.testing.assert_array_equal(e[:old[1].size], old[1])
    np.testing.assert_array_equal(row[:old[1].size], old[4])
    np.testing.assert_array_equal(col[:old[1].size], old[5])


def test_accumulator_matches_coordinate_stats_bit_for_bit_where_promised(monkeypatch):
    rng = np.random.default_rng(2)
    for trial in range(60):
        blocks = [rng.normal(size=(2, int(rng.integers(0, 400)))) * 10.0 ** -int(rng.integers(1, 4))
                  for _ in range(int(rng.integers(1, 5)))]
        if trial % 3 == 0:
            blocks = [np.round(b, 3) for b in blocks]  # many equal lengths (ties across blocks)
        if trial % 5 == 0:
            monkeypatch.setattr(st, "_SELECT_LIMIT", 3)  # the refining second histogram
        acc = st.CoordinateAccumulator()
        for b in blocks:
            acc.add(b[0], b[1])
        mine = acc.result(lambda i: np.hypot(blocks[i][0], blocks[i][1]), len(blocks))
        whole = coordinate_stats(np.concatenate([b[0] for b in blocks]), np.concatenate([b[1] for b in blocks]))
        if whole.n == 0:
            assert mine.n == 0 and math.isnan(mine.p95_um)
        else:
            _assert_same_stats(mine, whole)
        monkeypatch.setattr(st, "_SELECT_LIMIT", 4_000_000)
    # one value, and NaN entries ignored as coordinate_stats ignores them
    acc = st.CoordinateAccumulator()
    acc.add(np.array([0.003, np.nan]), np.array([0.004, 1.0]))
    one = acc.result(lambda i: np.array([0.005]), 1)
    assert one.n == 1 and one.p95_um == pytest.approx(5.0) and one.max_um == pytest.approx(5.0)


def test_linear_percentile_is_numpys(monkeypatch):
    rng = np.random.default_rng(3)
    for n in list(range(1, 40)) + [1000, 12345]:
        a = rng.exponential(size=n)
        s = np.sort(a)
        assert st._linear_percentile(lambda ranks: {r: s[r] for r in ranks}, n, 95) == np.percentile(a, 95)


def test_maps_file_removed_and_disk_full(monkeypatch):
    maps = HeldOutMaps(("ptp", "3dstc"), 2, (3, 4), True)
    path = maps._store.path
    if os.name == "posix":  # unlinked at creation: nothing to remove, nothing a SIGKILL could leave
        assert not path.exists() and path not in live_temporaries()
    else:  # pragma: no cover - a named file, removed with its store
        assert path.exists() and path in live_temporaries()
    del maps
    gc.collect()
    assert not path.exists() and path not in live_temporaries()

    import ptpcore.store.positions as fastio

    def full(fh, nbytes):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(fastio, "_reserve", full)
    before = set(live_temporaries())
    with pytest.raises(DiskFullError, match="comparison's per-position error maps") as info:
        HeldOutMaps(("ptp",), 2, (3, 4), False)
    assert "ptp-samples-" in str(info.value) and set(live_temporaries()) == before
