"""`ptp-studio --tour` writes one screenshot per page with real data showing."""

from __future__ import annotations

from PySide6.QtGui import QImage

from ptp_studio.tour import run_tour


def test_tour_writes_a_screenshot_per_page(qapp, tmp_path):
    shots = run_tour(tmp_path, 96, 72, 9, log=lambda *_: None)
    names = [p.name for p in shots]
    for page in ("rig", "fringes", "acquire", "phase-validity", "calibrate", "compare", "export"):
        assert any(n.endswith(f"-{page}.png") for n in names), page
    for p in shots:
        img = QImage(str(p))
        assert not img.isNull() and img.width() > 800
        # real content, not a blank window: many distinct colours
        colours = {img.pixel(x, y) for x in range(0, img.width(), 7) for y in range(0, img.height(), 7)}
        assert len(colours) > 20, p.name
    assert (tmp_path / "export" / "calibration.lut.h5").is_file()
