"""The wizard keeps at most one decoded position in memory on a 5 MP camera (issue 15), two on small ones."""

from __future__ import annotations

from types import SimpleNamespace

import pytest


@pytest.mark.parametrize("size, kept", [((320, 240), 2), ((2448, 2048), 1)])
def test_decoded_positions_kept(size, kept):
    from ptp_studio.session import Session

    s = Session.from_preset("realistic", size)
    assert s.decoded_cache_size() == kept
    for k in (0, 1, 2, 1):
        s.cache_decoded(SimpleNamespace(index=k))
        assert len(s.decoded) <= kept and k in s.decoded
    assert list(s.decoded) == ([2, 1] if kept == 2 else [1])  # the latest, then the one before


@pytest.mark.parametrize("size, big", [((320, 240), False), ((2448, 2048), True)])
def test_only_the_last_position_travels_and_a_fit_lets_it_go(qtbot, size, big):
    """Above 2 MP the acquisition decodes no position's maps in full nor sends any (the Phase maps
    page decodes the one it shows), and a fit starting releases a cached one; small sensors keep them."""
    import numpy as np

    from ptp_studio.session import Session, SessionModel

    s = Session.from_preset("realistic", size)
    n = s.rig.stage.n_positions
    reasons = np.zeros((4, 4), np.uint8)
    sent = [s.position_message(SimpleNamespace(index=k, z_mm=float(k), reasons=reasons)) for k in range(n)]
    assert [m[0] for m in sent] == ["position"] * n
    assert [m[1].index for m in sent] == list(range(n)) and all(m[1].state == "done" for m in sent)
    travelled = [m[1].index for m in sent if m[2] is not None]
    assert travelled == ([] if big else list(range(n)))
    assert s.full_positions() == ([] if big else None)

    model = SessionModel(s)
    model.set_decoded(SimpleNamespace(index=n - 1))  # as the Phase maps page's own decode leaves it
    with qtbot.waitSignal(model.decodedReleased, timeout=1000, raising=False) as blocker:
        model.release_decoded()
    assert blocker.signal_triggered == big
    assert len(s.decoded) == (0 if big else 1)
