"""Help → Keyboard shortcuts: every action of a window that has keys, read from the actions themselves so
the list cannot drift from what the keys do, then the window's mouse gestures."""

from __future__ import annotations

from PySide6.QtCore import Qt
from PySide6.QtGui import QAction, QKeySequence
from PySide6.QtWidgets import QDialog, QHeaderView, QTableWidget, QTableWidgetItem, QVBoxLayout, QWidget


def shortcut_rows(window: QWidget, mouse: list[tuple[str, str]]) -> list[tuple[str, str]]:
    """(what, keys) for every action of `window` (and its tools and docks) with a shortcut, then `mouse`."""
    rows = {(a.text().replace("&", ""), ", ".join(s.toString(QKeySequence.SequenceFormat.NativeText)
                                                  for s in a.shortcuts()))
            for a in window.findChildren(QAction) if a.shortcuts()}
    return sorted(rows) + mouse


def show_shortcuts(window: QWidget, rows: list[tuple[str, str]]) -> QDialog:
    """A non-modal table of the rows; it deletes itself when closed."""
    dialog = QDialog(window)
    dialog.setObjectName("shortcuts-dialog")
    dialog.setWindowTitle("Keyboard shortcuts")
    table = QTableWidget(len(rows), 2)
    table.setHorizontalHeaderLabels(["Action", "Keys"])
    for r, (what, keys) in enumerate(rows):
        table.setItem(r, 0, QTableWidgetItem(what))
        table.setItem(r, 1, QTableWidgetItem(keys))
    table.horizontalHeader().setSectionResizeMode(QHeaderView.ResizeMode.Stretch)
    table.verticalHeader().hide()
    QVBoxLayout(dialog).addWidget(table)
    dialog.resize(520, 600)
    dialog.setAttribute(Qt.WidgetAttribute.WA_DeleteOnClose)
    dialog.show()
    return dialog
