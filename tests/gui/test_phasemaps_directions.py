"""Phase maps page: the invalid-pixel reasons of each direction apart, not combined (issue 13)."""

from __future__ import annotations

import numpy as np
from gui_helpers import run_job

from ptpcore.decode import Reason
from ptpcore.evaluate import reason_counts, reason_rgba
from ptpcore.run import decode_position
from ptpcore.run.decoding import direction_reasons


def test_validity_per_direction(wizard, qtbot):
    s = wizard.model.session
    pos = decode_position(s.make_source(), 0)
    wizard.model.set_decoded(pos)
    ph = wizard.page_by_key["phase"]
    per = direction_reasons(s.rig, pos)
    rx, ry = per["x"], per["y"]
    # The view looks at the LCD's corner (conftest): the two directions reject different pixels
    # and for different reasons (not one combined mask).
    assert np.any((rx != 0) != (ry != 0)) and np.any(rx != ry)
    # a pixel valid in both directions is valid in the position (samples need both)
    assert not np.any((pos.reasons != 0) & (rx == 0) & (ry == 0) & ((pos.reasons & Reason.SPATIAL) == 0))
    for d, r in (("x", rx), ("y", ry)):
        ph.select(position=0, direction=d, kind="validity")
        if ph.jobs.busy:
            run_job(qtbot, ph.jobs.job)
        np.testing.assert_array_equal(ph.view.image.image, reason_rgba(r))
        assert f"direction {d} alone" in ph.title.text()
        counts = reason_counts(r)
        assert ph.legend.texts()[0] == "valid"
        assert f"{100 * counts[0] / r.size:.1f} %" in ph.legend._rows[0][2].text()
        # the coordinate map blanks this direction's invalid pixels only
        ph.select(kind="coord")
        coord = pos.u if d == "x" else pos.v
        np.testing.assert_allclose(ph.view.image.image, np.where(r == 0, pos.directions[d].coord, np.nan),
                                   equal_nan=True)
        assert np.isfinite(coord).any()


def test_a_gray_code_design_acquires_and_decodes_in_the_wizard(wizard, qtbot):
    """Unwrapping by a Gray code chosen on the Fringes page: the simulated acquisition and the
    Phase maps page get the Gray-code frames through their frame sources."""
    s = wizard.model.session
    fr = wizard.page_by_key["fringes"]
    fr.unwrap.setCurrentText("gray")
    assert s.rig.fringes.unwrap == "gray" and s.rig.fringes.bits("x") >= 1 and fr.blocker() is None
    wizard.next()
    wizard.next()
    acq = wizard.page_by_key["acquire"]
    assert run_job(qtbot, acq.start()) == "finished"
    assert s.samples is not None and np.mean(s.samples.reasons == 0) > 0.3
    s.decoded.clear()
    ph = wizard.page_by_key["phase"]
    wizard.next()
    ph.select(position=1, direction="y", kind="validity")
    outcomes = []
    while ph.jobs.busy:  # entering the page started position 1's decode, or another one it cancels
        outcomes.append(run_job(qtbot, ph.jobs.job))
    assert outcomes and outcomes[-1] == "finished", outcomes
    assert 1 in s.decoded and np.mean(ph.reasons_of("y") == 0) > 0.3
