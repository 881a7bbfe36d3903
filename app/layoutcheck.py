"""What a program can tell about a page's layout: the main view's share of the window and whether it is
whole in view, horizontal scroll bars, and text or plots cut at their widget's edge.

Used by the tests (offscreen) and by ``python -m benchmarks.gui_walk`` (the real wizard under Xvfb).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import pyqtgraph as pg
from PySide6.QtCore import QRect, Qt
from PySide6.QtGui import QFontMetrics, QTextDocument
from PySide6.QtWidgets import (QAbstractScrollArea, QComboBox, QHeaderView, QLabel, QStyle, QStyleOptionComboBox,
                               QTableWidget, QWidget)

__all__ = ["PageLayout", "check_page", "cut_cells", "cut_combos", "cut_labels", "cut_headers", "cut_plot_titles", "cut_plots",
           "horizontal_bars", "view_share"]

MIN_VIEW_SHARE = 0.5
"""The main view's least share of the window's area (issue 31: at least half)."""


@dataclass
class PageLayout:
    """What :func:`check_page` found on one page.

    Attributes
    ----------
    page : str
        The page's key.
    view_share : float or None
        The main view's area over the window's (None: the page has no main view).
    view_inside : bool
        The main view lies whole inside the page's viewport (seen without scrolling).
    horizontal_bars, cut_texts : list of str
        Scroll areas showing a horizontal bar; labels, headers and plot titles wider than their room.
    """

    page: str
    view_share: float | None
    view_inside: bool
    horizontal_bars: list[str] = field(default_factory=list)
    cut_texts: list[str] = field(default_factory=list)

    @property
    def problems(self) -> list[str]:
        out = []
        if self.view_share is not None and self.view_share < MIN_VIEW_SHARE:
            out.append(f"main view {100 * self.view_share:.0f} % of the window (< {100 * MIN_VIEW_SHARE:.0f} %)")
        if not self.view_inside:
            out.append("main view not whole in view (scroll to see it)")
        out += [f"horizontal scroll bar: {name}" for name in self.horizontal_bars]
        out += [f"cut: {text}" for text in self.cut_texts]
        return out


def _name(w: QWidget) -> str:
    return w.objectName() or type(w).__name__


def _shown(w: QWidget, top: QWidget) -> bool:
    return w.isVisibleTo(top) and w.isVisible() and w.width() > 0 and w.height() > 0


def view_share(page, window: QWidget) -> tuple[float | None, bool]:
    """The main view's share of ``window``'s area and whether it lies whole inside the page's viewport."""
    view = getattr(page, "main_view", None)
    if view is None:
        return None, True
    port = page.scroll.viewport()
    top_left = view.mapTo(port, view.rect().topLeft())
    rect = QRect(top_left, view.size())
    seen = rect.intersected(port.rect())
    inside = seen == rect
    return seen.width() * seen.height() / max(1, window.width() * window.height()), inside


def horizontal_bars(page) -> list[str]:
    """Scroll areas of ``page`` (the page itself, side panels, tables) showing a horizontal scroll bar."""
    return [_name(a) for a in [page.scroll, *page.findChildren(QAbstractScrollArea)]
            if _shown(a, page) and a.horizontalScrollBar().isVisible()]


def _plain(label: QLabel) -> str:
    text = label.text()
    if label.textFormat() != 0 and ("<" in text):  # rich text: what is drawn
        doc = QTextDocument()
        doc.setHtml(text)
        text = doc.toPlainText()
    return text


def cut_labels(page) -> list[str]:
    """Labels (not word-wrapped) whose text is wider than the label."""
    out = []
    for label in page.findChildren(QLabel):
        if not _shown(label, page) or label.wordWrap() or not label.text() or label.pixmap() is not None \
                and not label.pixmap().isNull():
            continue
        fm = QFontMetrics(label.font())
        need = max(fm.horizontalAdvance(line) for line in _plain(label).splitlines() or [""])
        if need > label.contentsRect().width() + 1:
            out.append(f"label '{_plain(label)[:40]}' needs {need} px, has {label.contentsRect().width()}")
    return out


def cut_headers(page) -> list[str]:
    """Table header sections whose text is wider than the section (Qt elides it with "...")."""
    out = []
    for header in page.findChildren(QHeaderView):
        if not _shown(header, page):
            continue
        model = header.model()
        fm = QFontMetrics(header.font())
        for i in range(header.count()):
            if header.isSectionHidden(i):
                continue
            text = model.headerData(i, header.orientation())
            text = "" if text is None else str(text)
            need = fm.horizontalAdvance(text) + 8  # the section's margins
            if text and need > header.sectionSize(i) and header.orientation() == Qt.Horizontal:
                out.append(f"header '{text}' needs {need} px, has {header.sectionSize(i)}")
            elif text and header.orientation() == Qt.Vertical and need > header.width():
                out.append(f"row name '{text}' needs {need} px, has {header.width()}")
    return out


def cut_cells(page) -> list[str]:
    """Table cells whose text is wider than their column (Qt elides it: the Compare table's rows read
    "PTP ..." and its numbers "1..." in a narrow column)."""
    out = []
    for table in page.findChildren(QTableWidget):
        if not _shown(table, page):
            continue
        fm = QFontMetrics(table.font())
        for c in range(table.columnCount()):
            if table.isColumnHidden(c):
                continue
            room = table.columnWidth(c) - 6  # the cell's margins
            for r in range(table.rowCount()):
                item = table.item(r, c)
                if item is None or not item.text():
                    continue
                if table.wordWrap():  # whole when its lines, wrapped at words, fit the row's height
                    need = fm.boundingRect(QRect(0, 0, max(room, 1), 100_000), Qt.TextWordWrap, item.text())
                    if need.width() > room or need.height() > table.rowHeight(r):
                        out.append(f"cell '{item.text()[:40]}' needs {need.width()}x{need.height()} px, has "
                                   f"{room}x{table.rowHeight(r)}")
                elif fm.horizontalAdvance(item.text()) > room:
                    out.append(f"cell '{item.text()[:40]}' needs {fm.horizontalAdvance(item.text())} px, has {room}")
    return out


def cut_combos(page) -> list[str]:
    """Combo boxes whose current text is wider than the box's text field (drawn cut at its edge)."""
    out = []
    for combo in page.findChildren(QComboBox):
        if not _shown(combo, page) or not combo.currentText():
            continue
        opt = QStyleOptionComboBox()
        combo.initStyleOption(opt)
        room = combo.style().subControlRect(QStyle.CC_ComboBox, opt, QStyle.SC_ComboBoxEditField, combo).width()
        need = QFontMetrics(combo.font()).horizontalAdvance(combo.currentText())
        if need > room + 1:
            out.append(f"combo box '{combo.currentText()[:40]}' needs {need} px, has {room}")
    return out


def cut_plot_titles(page) -> list[str]:
    """pyqtgraph plot titles wider than their plot."""
    out = []
    for widget in page.findChildren(pg.GraphicsView):
        if not _shown(widget, page):
            continue
        for item in widget.scene().items():
            if isinstance(item, pg.PlotItem) and item.titleLabel.isVisible() and item.titleLabel.text:
                need = item.titleLabel.item.boundingRect().width()
                room = min(item.width(), widget.viewport().width())  # a plot wider than its widget is cut too
                if need > room + 1:
                    out.append(f"plot title '{item.titleLabel.item.toPlainText()[:40]}' needs {need:.0f} px,"
                               f" has {room:.0f}")
    return out


def cut_plots(page) -> list[str]:
    """pyqtgraph plots whose data area (view box) reaches past their widget's edge.

    A plot item wider than its widget (a title or a legend asking for more room than the widget has) is
    drawn from the widget's left edge and cut at its right one: the last heights' bars of the Compare page's
    chart were not drawn at all, though the view's range held them (issue 31).
    """
    out = []
    for widget in page.findChildren(pg.GraphicsView):
        if not _shown(widget, page):
            continue
        port = widget.viewport().rect()
        for item in widget.scene().items():
            if not isinstance(item, pg.PlotItem) or not item.isVisible():
                continue
            box = widget.mapFromScene(item.vb.sceneBoundingRect()).boundingRect()
            if box.right() > port.right() + 1 or box.bottom() > port.bottom() + 1 or box.left() < -1 \
                    or box.top() < -1:
                title = item.titleLabel.item.toPlainText()[:40] or type(widget).__name__
                out.append(f"plot '{title}': its data area spans x {box.left()}..{box.right()}, y {box.top()}.."
                           f"{box.bottom()} in a {port.width()}x{port.height()} px widget")
    return out


def check_page(page, window: QWidget) -> PageLayout:
    """Every check on the page shown now in ``window``."""
    share, inside = view_share(page, window)
    return PageLayout(page.key, share, inside, horizontal_bars(page),
                      cut_labels(page) + cut_headers(page) + cut_cells(page) + cut_combos(page) + cut_plot_titles(page)
                      + cut_plots(page))
