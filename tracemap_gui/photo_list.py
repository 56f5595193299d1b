"""The project's photos as a list with their trace counts; choosing one shows it in the editor."""

from __future__ import annotations

from collections import Counter

from PySide6.QtCore import Qt, Signal
from PySide6.QtWidgets import QListWidget, QListWidgetItem, QWidget

from tracemap_gui.session import Session


class PhotoList(QListWidget):
    chosen = Signal(str)  # the user picked this photo

    def __init__(self, session: Session, parent: QWidget | None = None):
        super().__init__(parent)
        self.setObjectName("photo-list")
        self._session = session
        self._items: dict[str, QListWidgetItem] = {}
        session.opened.connect(self._reload)
        session.closed.connect(self._reload)
        session.traces2d_changed.connect(self._recount)  # a bound method: dropped when the list is deleted
        self.currentItemChanged.connect(self._picked)
        self._reload()

    def _recount(self, image: str) -> None:
        self._label(image, len(self._session.traces2d(image)))

    def names(self) -> list[str]:
        return list(self._items)

    def set_current(self, image: str) -> None:
        """Highlight `image` without announcing it (the editor already shows it)."""
        self.blockSignals(True)
        self.setCurrentItem(self._items[image])
        self.blockSignals(False)

    def _picked(self, item: QListWidgetItem | None, _previous: QListWidgetItem | None) -> None:
        if item is not None:
            self.chosen.emit(item.data(Qt.ItemDataRole.UserRole))

    def _reload(self) -> None:
        self.blockSignals(True)
        self.clear()
        self._items = {}
        if self._session.is_open:
            counts = Counter(self._session.project.traces2d_counts())  # one query for all photos
            for image in self._session.images():
                item = QListWidgetItem()
                item.setData(Qt.ItemDataRole.UserRole, image)
                self.addItem(item)
                self._items[image] = item
                self._label(image, counts[image])
        self.blockSignals(False)

    def _label(self, image: str, count: int) -> None:
        if image in self._items:
            self._items[image].setText(f"{image}   ({count} traces)")
