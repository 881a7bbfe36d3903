"""The layout checks themselves (``ptp_studio.layoutcheck``) on small widgets: each finds what it is for
(a cut cell, combo box text, a plot drawn past its widget) and passes the same widget given room."""

from __future__ import annotations

import pyqtgraph as pg
from PySide6.QtWidgets import QComboBox, QHBoxLayout, QHeaderView, QTableWidget, QTableWidgetItem, QWidget

from ptp_studio.layoutcheck import cut_cells, cut_combos, cut_plots


def _page(qtbot, *widgets, width=400, height=300) -> QWidget:
    page = QWidget()
    lay = QHBoxLayout(page)
    for w in widgets:
        lay.addWidget(w)
    qtbot.addWidget(page)
    page.resize(width, height)
    page.show()
    qtbot.waitExposed(page)
    qtbot.wait(50)
    return page


def test_cut_cells_finds_an_elided_row_name_and_a_wrapped_text_taller_than_its_row(qtbot):
    table = QTableWidget(2, 2)
    table.setWordWrap(False)
    table.setItem(0, 0, QTableWidgetItem("PTP smooth across z"))
    table.setItem(1, 0, QTableWidgetItem("PTP"))
    table.horizontalHeader().setSectionResizeMode(QHeaderView.Fixed)
    table.setColumnWidth(0, 40)
    page = _page(qtbot, table)
    assert [c for c in cut_cells(page) if "PTP smooth across z" in c] and not [c for c in cut_cells(page)
                                                                                 if "'PTP'" in c]
    table.setColumnWidth(0, 300)
    assert cut_cells(page) == []
    # wrapping: whole when its lines fit the row's height
    table.setWordWrap(True)
    table.setColumnWidth(0, 80)
    table.setRowHeight(0, 20)
    assert [c for c in cut_cells(page) if "PTP smooth" in c]
    table.resizeRowsToContents()
    assert cut_cells(page) == []


def test_cut_combos_finds_a_combo_text_wider_than_its_field(qtbot):
    combo = QComboBox()
    combo.addItem("realistic — strong distortion, non-central pupil, gamma, noise, stage errors")
    combo.setSizeAdjustPolicy(QComboBox.AdjustToMinimumContentsLengthWithIcon)
    combo.setMinimumContentsLength(8)
    combo.setFixedWidth(150)
    page = _page(qtbot, combo)
    assert len(cut_combos(page)) == 1
    combo.setItemText(0, "realistic")
    assert cut_combos(page) == []


def test_cut_plots_finds_a_plot_item_wider_than_its_widget(qtbot):
    plot = pg.PlotWidget()
    plot.setFixedWidth(160)
    page = _page(qtbot, plot)
    assert cut_plots(page) == []
    # a title needing more room than the widget has makes the plot item wider than the widget
    plot.setTitle("Coordinate RMS per held-out z, every method, every height", size="14pt")
    plot.getPlotItem().layout.setMinimumWidth(400)
    qtbot.wait(100)
    found = cut_plots(page)
    assert len(found) == 1 and "in a 160x" in found[0], found
