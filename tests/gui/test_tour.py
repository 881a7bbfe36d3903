"""`ptp-studio --tour` writes one screenshot per page with real data showing."""

from __future__ import annotations

from PySide6.QtGui import QImage

from ptp_studio.tour import run_tour


def test_tour_writes_a_screenshot_per_page(qapp, tmp_path):
    seen = {}

    def on_page(name, wiz):  # what the tour's clicks, keys and drags set (run_tour checks each took, too)
        p = wiz.page_by_key
        if name == "fringes":
            seen[name] = (p["fringes"].s_dir.currentText(), p["fringes"].s_level.value(), p["fringes"].s_step.value(),
                          p["fringes"].s_pos.value())
        elif name == "phase-validity":
            seen[name] = (p["phase"].kind_combo.currentData(), p["phase"].line_endpoints())
        elif name.startswith("calibrate"):
            seen[name] = (p["calibrate"].selected, p["calibrate"].degree.value())

    shots = run_tour(tmp_path, 96, 72, 9, log=lambda *_: None, on_page=on_page)
    assert seen["fringes"] == ("x", 1, 1, 4)
    kind, (p0, p1) = seen["phase-validity"]
    assert kind == "validity"  # the profile line dragged by its two handles to (5 %, 15 %) and (95 %, 85 %)
    for (x, y), (tx, ty) in zip((p0, p1), ((0.05 * 96, 0.15 * 72), (0.95 * 96, 0.85 * 72))):
        assert abs(x - tx) <= 1.5 and abs(y - ty) <= 1.5, (p0, p1)
    assert seen["calibrate"][0] is not None and seen["calibrate-smooth-sigma"] == (seen["calibrate"][0], 2)
    names = [p.name for p in shots]
    for page in ("rig", "fringes", "acquire", "phase-validity", "calibrate", "compare", "compare-table", "export",
                 "export-cloud", "export-trust"):
        assert any(n.endswith(f"-{page}.png") for n in names), page
    for p in shots:
        img = QImage(str(p))
        assert not img.isNull() and img.width() > 800
        # real content, not a blank window: many distinct colours
        colours = {img.pixel(x, y) for x in range(0, img.width(), 7) for y in range(0, img.height(), 7)}
        assert len(colours) > 20, p.name
    assert (tmp_path / "export" / "calibration.lut.h5").is_file()
