"""The simulator's VDI/VDE 2634-2 acceptance set: counts, sizes against the measuring volume's diagonal
as the guideline asks, every pose seen, lit and inside the calibrated height range (no rendering: the
exact per-pixel truth)."""

import numpy as np
import pytest

from ptpcore.simulate.scanner import ScannerRig, acceptance_objects, measuring_volume, scanner_preset


@pytest.fixture(scope="module", params=["scanner-mild", "scanner-rough"])
def scanner(request):
    rig, sim, sc = scanner_preset(request.param, 128, heights=5)
    return ScannerRig(rig, sim, sc, seed=1)


def test_counts_and_sizes_follow_the_guideline(scanner):
    lo, hi = measuring_volume(scanner)
    l0 = float(np.linalg.norm(hi - lo))
    objs = acceptance_objects(scanner)
    kinds = [o.kind for o in objs.values()]
    assert kinds.count("sphere") >= 10 and kinds.count("ballbar") >= 7 and kinds.count("plane") >= 6
    for o in objs.values():
        if o.kind == "sphere":
            assert 0.1 <= 2 * o.radius / l0 <= 0.2
        elif o.kind == "ballbar":
            assert np.linalg.norm(np.subtract(*o.centres)) >= 0.3 * l0
        else:
            assert o.size >= 0.5 * l0
    # the ball bars point in 7 different directions (the space diagonals among them)
    dirs = np.array([np.subtract(*o.centres) for o in objs.values() if o.kind == "ballbar"])
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    cos = np.abs(dirs @ dirs.T)[np.triu_indices(len(dirs), 1)]
    assert cos.max() < 0.99 and np.sum(np.abs(dirs[:, 2]) > 0.1) >= 4


def test_every_pose_is_seen_lit_and_inside_the_height_range(scanner):
    lo, hi = measuring_volume(scanner)
    for name, o in acceptance_objects(scanner).items():
        t = scanner.scan_truth(o)
        p = t["xyz"][t["lit"]]
        assert p.shape[0] > 50, name
        assert p[:, 2].min() >= lo[2] and p[:, 2].max() <= hi[2], name
        if o.kind == "ballbar":  # both balls seen
            d = np.linalg.norm(p[:, None, :] - np.asarray(o.centres)[None], axis=2)
            assert min(np.sum(d[:, 0] < d[:, 1]), np.sum(d[:, 1] < d[:, 0])) > 20, name
