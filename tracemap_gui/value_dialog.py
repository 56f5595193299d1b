"""A small form asking for values: OK checks them and, when they are bad, says why and stays open."""

from __future__ import annotations

from PySide6.QtWidgets import QDialog, QDialogButtonBox, QFormLayout, QLabel, QWidget

from engine.errors import InputError


class ValueDialog(QDialog):
    """Rows of fields, a message line and OK/Cancel. Subclasses add rows with `add_row` and implement
    `parse()`, returning the values or raising InputError; accepted dialogs hold them in `values`."""

    def __init__(self, title: str, name: str, parent: QWidget | None = None):
        super().__init__(parent)
        self.setWindowTitle(title)
        self.setObjectName(name)
        self.message = QLabel("", self)
        self.message.setStyleSheet("color: #b00020")
        self.message.setWordWrap(True)
        self.buttons = QDialogButtonBox(QDialogButtonBox.StandardButton.Ok | QDialogButtonBox.StandardButton.Cancel,
                                        self)
        self.buttons.accepted.connect(self.accept)
        self.buttons.rejected.connect(self.reject)
        self.form = QFormLayout(self)
        self.form.addRow(self.message)
        self.form.addRow(self.buttons)
        self.values = None

    def add_row(self, label: str, field: QWidget) -> None:
        self.form.insertRow(self.form.rowCount() - 2, label, field)

    def parse(self):
        raise NotImplementedError

    def accept(self) -> None:
        try:
            self.values = self.parse()
        except InputError as exc:
            self.message.setText(str(exc))
            return
        super().accept()
