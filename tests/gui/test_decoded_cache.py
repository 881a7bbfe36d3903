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
